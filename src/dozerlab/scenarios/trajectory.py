"""The blade trajectory and its per-step velocities (the thesis's algorithm 3; docs/physics.md).

``plan_trajectory`` turns a settled bed, a blade speed s and a cut depth d into tip positions and
the velocity to prescribe in each step:

1. height profile of the bed (:mod:`.heightfield`), smoothed by the thesis's filters (:mod:`.filters`);
2. the cut path: the tip runs d below the filtered surface where the surface is at or above the
   scenario's goal height, and d above it where the surface is lower (the carried material
   spreads below the blade); where the surface crosses the goal height the path changes
   between the two offsets vertically (the blade lifts or lowers in place). The tip never goes
   below the ground (z ≥ 0);
3. the approach: from the blade's start tip behind the bed (:func:`.blade.start_tip`) the path
   eases onto the cut path with a smoothstep over ``trajectory.approach_steps`` steps' worth of
   travel (approach_steps · s · dt along x);
4. the end: the path stops at x = length − ``trajectory.end_margin``, on the flat bed well before
   the end wall, so the material pushed ahead is not squeezed against it;
5. constant speed: the path is walked by inverting its arc length step by step — each point is
   the first point further along the path at distance s·dt from the previous one, so every step
   covers exactly s·dt even across the path's corners (on smooth stretches this is the thesis's
   L_i = i·s·dt sampling). The velocity of step i is (p_{i+1} − p_i)/dt, and the stored positions
   are re-integrated from it (p_{i+1} = p_i + dt·v_i), so a simulation that sets ``velocity[i]``
   in step i reproduces ``position`` exactly.
"""

from __future__ import annotations

import hashlib
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.integrity import DamagedFileError
from dozerlab.runtime import DozerlabError, OutputKind, atomic_output, first_line_is
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.blade import start_tip
from dozerlab.scenarios.filters import smooth_height
from dozerlab.scenarios.heightfield import height_field

CSV_COLUMNS = ("step", "time", "x", "y", "z", "vx", "vy", "vz")
#: The start of a trajectory CSV's last line, followed by the SHA-256 (hex) of the bytes before it.
_SHA_PREFIX = "# sha256 "
#: What ``dozerlab trajectory`` writes: a CSV with exactly this header.
TRAJECTORY_FILE = OutputKind("a dozerlab trajectory CSV", first_line_is(",".join(CSV_COLUMNS)))


#: The most steps a trajectory may have: 10^6 rows of blade motion, a run of hours of NDEM;
#: a path walked at a crawl would otherwise grow without bound (1e-9 m/s: 4e11 rows).
MAX_STEPS = 1_000_000


def _empty() -> np.ndarray:
    return np.zeros(0)


@dataclass
class Trajectory:
    """A planned blade path of T steps.

    ``time`` (T+1,) s; ``position`` (T+1, 3) tip positions in m at the start of each step (the
    last is the final position); ``velocity`` (T, 3) m/s applied during each step. ``speed``
    (m/s), ``depth`` (m), ``goal_height`` (m) and ``dt`` (s) are the planning inputs. For plots:
    ``height_x`` (Nx,) cell centres, ``height_raw``/``height_filtered`` (Nx,) the bed profile,
    and ``path`` (P, 2) the (x, z) polyline that was walked. A trajectory read back from CSV has
    empty height/path arrays, ``scenario`` "" and NaN depth and goal height.
    """

    time: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    speed: float
    depth: float
    scenario: str
    goal_height: float
    dt: float
    height_x: np.ndarray = field(default_factory=_empty)
    height_raw: np.ndarray = field(default_factory=_empty)
    height_filtered: np.ndarray = field(default_factory=_empty)
    path: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    @property
    def steps(self) -> int:
        """Number of steps T."""
        return len(self.velocity)

    def save_csv(self, path: str | Path) -> None:
        """Write ``step,time,x,y,z,vx,vy,vz`` rows (T+1; the last has zero velocity) and a last
        line ``# sha256 HEX`` of the bytes before it, atomically; a trajectory that
        :func:`check_table` refuses is refused unwritten."""
        vel = np.vstack([self.velocity, np.zeros((1, 3))])
        table = np.column_stack([np.arange(len(self.time)), self.time, self.position, vel])
        check_table(path, table)
        text = io.StringIO()
        np.savetxt(
            text,
            table,
            delimiter=",",
            header=",".join(CSV_COLUMNS),
            comments="",
            fmt=["%d"] + ["%.17g"] * 7,
        )
        body = text.getvalue().encode()
        with atomic_output(path, TRAJECTORY_FILE) as tmp:
            Path(tmp).write_bytes(
                body + f"{_SHA_PREFIX}{hashlib.sha256(body).hexdigest()}\n".encode()
            )

    @classmethod
    def load_csv(cls, path: str | Path) -> Trajectory:
        """Read a trajectory written by :meth:`save_csv` (positions and velocities bit-exact).

        Refuses, naming the file, one whose bytes differ from its ``# sha256`` line or that has
        none (written before it, or not by :meth:`save_csv`), and one :func:`check_table`
        refuses."""
        path = Path(path)
        if not path.is_file():
            raise DozerlabError(f"trajectory file not found: {path}")
        data = path.read_bytes()
        header = data.split(b"\n", 1)[0].strip()
        if header != ",".join(CSV_COLUMNS).encode():
            raise DozerlabError(
                f"{path}: expected the header {','.join(CSV_COLUMNS)!r}, got {header[:80]!r}"
            )
        body, sep, last = data.rstrip(b"\n").rpartition(b"\n")
        if not sep or not last.startswith(_SHA_PREFIX.encode()):
            raise DamagedFileError(
                f"{path} has no '{_SHA_PREFIX.strip()}' line at its end (cut short, or written by a "
                "dozerlab older than it), so it cannot be verified; re-run `dozerlab trajectory`"
            )
        if (
            last[len(_SHA_PREFIX) :].decode("ascii", "replace")
            != hashlib.sha256(body + b"\n").hexdigest()
        ):
            raise DamagedFileError(
                f"{path} is damaged: its bytes differ from the SHA-256 on its last line; re-run "
                "`dozerlab trajectory`, or copy it again"
            )
        try:
            table = np.loadtxt(io.StringIO(body.decode()), delimiter=",", skiprows=1, ndmin=2)
        except ValueError as exc:
            raise DamagedFileError(f"{path} is not a table of numbers: {exc}") from exc
        check_table(path, table)
        time, position, velocity = table[:, 1], table[:, 2:5], table[:-1, 5:8]
        return cls(
            time=np.ascontiguousarray(time),
            position=np.ascontiguousarray(position),
            velocity=np.ascontiguousarray(velocity),
            speed=float(np.median(np.linalg.norm(velocity, axis=1))),
            depth=float("nan"),
            scenario="",
            goal_height=float("nan"),
            dt=float(time[1] - time[0]),
        )


def check_table(path: str | Path, table: np.ndarray) -> None:
    """Refuse a trajectory table (rows ``step,time,x,y,z,vx,vy,vz``) that is not what
    :meth:`Trajectory.save_csv` writes, naming ``path`` and the first row that differs.

    Checked on saving, so that nothing else is written, and on loading after the file's SHA-256:
    ``step`` counts 0, 1, …; ``time`` is ``step · dt`` with ``dt`` = ``time[1]``;
    every position is the previous one plus ``dt`` times the previous row's velocity, bit for
    bit (:func:`plan_trajectory` re-integrates them so, and ``%.17g`` reads back exactly); the
    last row's velocity is zero; and every value is finite.
    """
    if table.ndim != 2 or table.shape[1] != len(CSV_COLUMNS):
        raise DamagedFileError(
            f"{path}: a trajectory has {len(CSV_COLUMNS)} columns, got shape {table.shape}"
        )
    if len(table) < 2:
        raise DozerlabError(f"{path}: a trajectory needs at least 2 rows, got {len(table)}")
    bad = np.argwhere(~np.isfinite(table))
    if bad.size:
        raise DamagedFileError(
            f"{path}: row {bad[0][0]} holds NaN/inf ('{CSV_COLUMNS[bad[0][1]]}')"
        )
    n = len(table)
    dt = table[1, 1] - table[0, 1]
    position, velocity = table[:, 2:5], table[:-1, 5:8]
    ties = {
        "step": table[:, 0] == np.arange(n),
        "time": table[:, 1] == np.arange(n) * dt,
        "position": np.concatenate(
            [[True], np.all(position[1:] == position[:-1] + dt * velocity, axis=1)]
        ),
    }
    if not dt > 0:
        raise DamagedFileError(f"{path}: the time step {dt} s is not positive (row 1)")
    for what, ok in ties.items():
        if not ok.all():
            row = int(np.flatnonzero(~ok)[0])
            raise DamagedFileError(
                f"{path} is damaged or edited: row {row}'s {what} does not follow from the rows "
                "before it as a planned trajectory's does; re-run `dozerlab trajectory`"
            )
    if np.any(table[-1, 5:8] != 0):
        raise DamagedFileError(f"{path} is damaged or edited: the last row's velocity is not zero")


def cut_path(x: np.ndarray, surface: np.ndarray, depth: float, goal_height: float) -> np.ndarray:
    """The (x, z) polyline (P, 2) at ``depth`` below/above the ``surface`` profile (both (Nx,)).

    Below (z = h − d) where h ≥ ``goal_height``, above (z = h + d) elsewhere; at each crossing
    of the goal height a vertical segment joins the two, at the crossing's interpolated x.
    """
    cutting = surface >= goal_height
    offset = np.where(cutting, -depth, depth)
    points = [(x[0], surface[0] + offset[0])]
    for i in range(1, len(x)):
        if cutting[i] != cutting[i - 1]:
            t = (goal_height - surface[i - 1]) / (surface[i] - surface[i - 1])
            xc = x[i - 1] + t * (x[i] - x[i - 1])
            points.append((xc, goal_height + offset[i - 1]))
            points.append((xc, goal_height + offset[i]))
        points.append((x[i], surface[i] + offset[i]))
    path = np.array(points)
    path[:, 1] = np.maximum(path[:, 1], 0.0)
    return path


def walk_path(path: np.ndarray, step_length: float) -> np.ndarray:
    """Points (T+1, 2) along the polyline ``path`` (P, 2), each ``step_length`` from the previous.

    Starts at ``path[0]``; each next point is the first point further along the path at
    Euclidean distance ``step_length`` from the current one. Stops when the rest of the path
    stays within ``step_length`` (the remainder, shorter than one step, is not travelled).
    """
    points = [path[0]]
    p, k, n = path[0], 0, len(path)
    while True:
        j = k + 1
        while j < n and np.hypot(*(path[j] - p)) < step_length:
            j += 1
        if j == n:
            return np.array(points)
        start = p if j - 1 == k else path[j - 1]
        a, b = start - p, path[j] - start
        ab, bb = a @ b, b @ b
        t = (-ab + np.sqrt(max(ab * ab - bb * (a @ a - step_length**2), 0.0))) / bb
        p = start + min(max(t, 0.0), 1.0) * b
        k = j - 1
        points.append(p)


def _smoothstep(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def plan_trajectory(bed: Bed, speed: float, depth: float, config: dict[str, Any]) -> Trajectory:
    """Plan the blade path over ``bed`` at ``speed`` (m/s) and cut ``depth`` (m).

    Reads ``scenarios.<bed.scenario>.goal_height``, ``solver.dt`` and the ``trajectory`` and
    ``blade`` sections of the validated ``config``. Raises ValueError for a non-positive speed or
    depth, a depth at least as deep as the bed is high, or a goal height not below the bed's top.
    """
    if not np.isfinite(speed) or speed <= 0:
        raise ValueError(f"speed must be a finite value > 0 m/s, got {speed}")
    if not np.isfinite(depth) or depth <= 0:
        raise ValueError(f"depth must be a finite value > 0 m, got {depth}")
    tcfg = config["trajectory"]
    dt = float(config["solver"]["dt"])
    goal = float(config["scenarios"][bed.scenario]["goal_height"])
    end_x = bed.length - float(tcfg["end_margin"])
    if end_x <= 0:
        raise ValueError(
            f"trajectory.end_margin must be < the bed length {bed.length} m, "
            f"got {tcfg['end_margin']}"
        )

    x, field = height_field(bed.positions, bed.radii, bed.length, bed.width, tcfg["subdivisions"])
    raw = field.mean(axis=1)
    smooth = smooth_height(raw)
    keep = x <= end_x
    top = float(smooth[keep].max()) if keep.any() else 0.0
    if depth >= top:
        raise ValueError(
            f"depth {depth} m is deeper than the bed: allowed 0 < depth < {top:.3f} m "
            "(the filtered bed's highest point before the path's end)"
        )
    if goal >= top:
        raise ValueError(
            f"scenarios.{bed.scenario}.goal_height {goal} m is outside the bed: allowed "
            f"0 <= goal_height < {top:.3f} m (the filtered bed's highest point)"
        )

    cut = cut_path(x, smooth, depth, goal)
    end_h = float(np.interp(end_x, x, smooth))
    end_z = max(end_h - depth if end_h >= goal else end_h + depth, 0.0)
    cut = np.vstack([cut[cut[:, 0] < end_x], [end_x, end_z]])

    tip0 = start_tip(bed, config)
    lead_x = np.arange(tip0[0], cut[0, 0], x[1] - x[0] if len(x) > 1 else bed.length)
    path = np.vstack([np.column_stack([lead_x, np.full(len(lead_x), cut[0, 1])]), cut])
    ease = _smoothstep((path[:, 0] - tip0[0]) / (int(tcfg["approach_steps"]) * speed * dt))
    path[:, 1] = tip0[2] + ease * (path[:, 1] - tip0[2])

    length = float(np.hypot(*np.diff(path, axis=0).T).sum())
    if length > MAX_STEPS * speed * dt:
        raise ValueError(
            f"the {length:.3g} m path at {speed} m/s takes {length / (speed * dt):.3g} steps of "
            f"solver.dt {dt} s, more than a run holds (allowed: at most {MAX_STEPS:.0e} steps; "
            "raise the speed or solver.dt)"
        )
    xz = walk_path(path, speed * dt)
    if len(xz) < 2:
        raise ValueError(
            f"the path is shorter than one step of {speed * dt} m; lower the speed or dt"
        )
    planned = np.column_stack([xz[:, 0], np.zeros(len(xz)), xz[:, 1]])
    velocity = np.diff(planned, axis=0) / dt
    position = np.empty_like(planned)
    position[0] = tip0
    for i, v in enumerate(velocity):
        position[i + 1] = position[i] + dt * v
    return Trajectory(
        time=np.arange(len(position)) * dt,
        position=position,
        velocity=velocity,
        speed=float(speed),
        depth=float(depth),
        scenario=bed.scenario,
        goal_height=goal,
        dt=dt,
        height_x=x,
        height_raw=raw,
        height_filtered=smooth,
        path=path,
    )
