"""The simulation run: drive the blade along a trajectory through a bed and record the fields.

Each solver step the blade gets the trajectory's velocity for that step; every
``sampling.every``-th step the fields around the blade, the blade force and torque (about
the tip), its velocity and tip position are appended to the field store, which is written while
the run goes (one chunk in memory) and appears only when the run succeeds. The job around it
(loading, labels, MLflow, plots) is :func:`dozerlab.fields.jobs.simulate`.
"""

from __future__ import annotations

import logging
import time as wallclock
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from tqdm import tqdm

from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import FieldStoreWriter
from dozerlab.runtime import DozerlabError, atomic_output, marked_folder
from dozerlab.scenarios.bed import bed_file_kind

if TYPE_CHECKING:
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory

log = logging.getLogger(__name__)
#: The folder of particle snapshots of ``simulate --vtk-dir`` (meshio's VTK XML unstructured
#: grids), written whole: a folder of the user's, even of ``.vtu`` files, is never written into.
VTK_FOLDER = marked_folder("a dozerlab folder of particle snapshots (VTK)", "vtk-snapshots")
#: NDEM's final particle state, ``simulate --state``: a bed file, but never a bed's.
STATE_FILE = bed_file_kind("a dozerlab final state (.npz) written by simulate", "simulate-state")


@dataclass
class RunStats:
    """Solver statistics gathered over a run (times in s, wall clock)."""

    steps: int = 0
    wall_time: float = 0.0
    step_time: float = 0.0
    sample_time: float = 0.0
    contact_iterations: float = 0.0
    active: float = 0.0
    relinearized_steps: int = 0
    forces: list[np.ndarray] = field(default_factory=list)

    def metrics(self, particles: int) -> dict[str, float]:
        """The MLflow metrics of the run."""
        f = np.array(self.forces).reshape(-1, 3)
        mag = np.linalg.norm(f, axis=1)
        out = {
            "wall_time_s": self.wall_time,
            "steps_per_s": self.steps / self.step_time if self.step_time > 0 else 0.0,
            "contact_iterations_per_s": self.contact_iterations / self.step_time
            if self.step_time > 0
            else 0.0,
            "sampling_fraction_of_step": self.sample_time / self.step_time
            if self.step_time > 0
            else 0.0,
            "particle_count": float(particles),
            "relinearized_steps": float(self.relinearized_steps),
            "active_fraction": self.active / (self.steps * particles)
            if self.steps and particles
            else 0.0,
        }
        if len(f):
            out |= {
                "force_x_mean": float(f[:, 0].mean()),
                "force_x_peak": float(np.abs(f[:, 0]).max()),
                "force_mag_mean": float(mag.mean()),
                "force_mag_peak": float(mag.max()),
            }
        return out


def _write_vtk(vtk_dir: Path, step: int, world: Any) -> None:
    import meshio

    pos = np.asarray(world.positions)
    mesh = meshio.Mesh(
        points=pos,
        cells=[("vertex", np.arange(len(pos)).reshape(-1, 1))],
        point_data={"radius": np.asarray(world.radii), "velocity": np.asarray(world.velocities)},
    )
    meshio.write(vtk_dir / f"particles_{step:06d}.vtu", mesh, file_format="vtu")


@contextmanager
def snapshots(vtk_dir: str | Path | None, vtk_every: int) -> Iterator[Path | None]:
    """The folder to write a run's VTK snapshots into: a temporary that becomes ``vtk_dir``
    (:data:`VTK_FOLDER`) when the run succeeds; None when there are none to write."""
    if vtk_dir is None or vtk_every <= 0:
        yield None
        return
    with atomic_output(vtk_dir, VTK_FOLDER) as tmp:
        tmp.mkdir()
        yield tmp


def drive(
    bed: Bed,
    traj: Trajectory,
    config: dict[str, Any],
    grid: SamplingGrid,
    attrs: dict[str, Any],
    out: Path,
    vtk_dir: str | Path | None = None,
    log_every: int | None = None,
    state_out: str | Path | None = None,
) -> RunStats:
    """The stepping loop: move the blade, step, sample, append to the store ``out`` (with
    ``attrs``); VTK snapshots to ``vtk_dir`` every ``sampling.vtk_every`` steps; a log line every
    ``log_every`` steps (default: 20 in the run); the final particle state to ``state_out`` (a bed
    file, ``Bed.load`` reads it) when given. The store's ``wall_time_s`` attribute is the loop's
    wall time (s). Returns the :class:`RunStats`.

    Raises :class:`DozerlabError` when the simulation diverges, leaving no store.
    """
    from dozerlab.ndem import DivergenceError
    from dozerlab.scenarios.blade import BladeGeometry, add_blade
    from dozerlab.scenarios.build import make_world

    s = config["sampling"]
    every, vtk_every = int(s["every"]), int(s["vtk_every"])
    world, _handles = make_world(bed, config)
    blade = add_blade(world, traj.position[0], config)
    centre_minus_tip = BladeGeometry.from_config(config).tip_offset
    log_every = log_every or max(1, traj.steps // 20)
    stats = RunStats()
    x, y, z = grid.centres()
    start = wallclock.perf_counter()
    window: list[tuple[float, int, float, float, int, bool]] = []
    with (
        FieldStoreWriter(
            out,
            x=x,
            y=y,
            z=z,
            attrs=attrs,
            chunk_steps=int(s["chunk_steps"]),
            steps=traj.steps // every,
        ) as writer,
        snapshots(vtk_dir, vtk_every) as vtk,
    ):
        for i in tqdm(
            range(traj.steps), desc=f"simulate {attrs['scenario']}", unit="step", disable=None
        ):
            world.set_velocity(blade, traj.velocity[i])
            t0 = wallclock.perf_counter()
            try:
                st = world.step()
            except DivergenceError as exc:
                raise DozerlabError(
                    f"simulation diverged at step {i} (t = {traj.time[i]:.4f} s): {exc}; "
                    "try a smaller solver.dt or more solver.iterations"
                ) from exc
            dt_wall = wallclock.perf_counter() - t0
            stats.steps += 1
            stats.step_time += dt_wall
            stats.contact_iterations += st.contacts * st.iterations
            stats.active += st.active
            stats.relinearized_steps += st.rounds > 0
            window.append(
                (dt_wall, st.contacts, st.residual, st.max_overlap, st.active, st.rounds > 0)
            )
            if (i + 1) % every == 0:
                t1 = wallclock.perf_counter()
                row = sample_row(world, blade, grid, traj, i + 1, centre_minus_tip)
                stats.sample_time += wallclock.perf_counter() - t1
                stats.forces.append(row[3])
                writer.append(*row)
            if vtk is not None and (i + 1) % vtk_every == 0:
                _write_vtk(vtk, i + 1, world)
            if (i + 1) % log_every == 0 or i + 1 == traj.steps:
                w = np.array(window)
                log.info(
                    "step %d/%d t=%.3f s: %.0f grains awake, contacts %.0f, residual %.3g m/s, "
                    "max overlap %.3g m, %d steps re-linearised, %.1f ms/step",
                    i + 1,
                    traj.steps,
                    traj.time[i + 1],
                    w[:, 4].mean(),
                    w[:, 1].mean(),
                    w[:, 2].mean(),
                    w[:, 3].max(),
                    w[:, 5].sum(),
                    1e3 * w[:, 0].mean(),
                )
                window.clear()
        # the stepping loop's own time (solver steps, sampling, store writes; not loading the
        # bed or building the world): the figure a reduced run is compared against
        stats.wall_time = wallclock.perf_counter() - start
        writer.update_attrs(wall_time_s=stats.wall_time)
    if state_out is not None:
        moved_bed(
            bed,
            world.positions,
            world.velocities,
            world.angular_velocities,
            {"time": float(traj.time[-1])},
        ).save(state_out, STATE_FILE)
    return stats


def load_inputs(
    bed_path: str | Path, trajectory_path: str | Path, config: dict[str, Any]
) -> tuple[Bed, Trajectory, float]:
    """The bed, the trajectory and ``solver.dt`` (s) of a run; refuses a trajectory planned with
    another time step."""
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory

    bed = Bed.load(bed_path)
    traj = Trajectory.load_csv(trajectory_path)
    dt = float(config["solver"]["dt"])
    if not np.isclose(traj.dt, dt, rtol=1e-6):
        raise ValueError(
            f"trajectory time step {traj.dt} s differs from solver.dt {dt} s; plan it with the same config"
        )
    return bed, traj, dt


def sample_row(
    world: Any,
    blade: int,
    grid: SamplingGrid,
    traj: Trajectory,
    step: int,
    centre_minus_tip: np.ndarray,
) -> tuple[float, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The store row after ``step`` solver steps of ``world``: the arguments of ``append``.

    (time s, velocity (Nx,Ny,Nz,3), density (Nx,Ny,Nz), force (3,) N, torque (3,) N·m about the
    tip, the blade velocity of the step that made the row, the tip position (3,) m).
    """
    tip = traj.position[step]
    vel, rho = grid.sample(world.positions, world.velocities, world.radii, world.masses, tip)
    force = np.asarray(world.force_on(blade), dtype=np.float64)
    # the blade only translates, so (centre − tip) is constant: torque about the tip as it was
    # during the step = torque about the centre + (centre − tip) × force
    torque = world.torque_on(blade) + np.cross(centre_minus_tip, force)
    return float(traj.time[step]), vel, rho, force, torque, traj.velocity[step - 1], tip


def moved_bed(
    bed: Bed,
    positions: np.ndarray,
    velocities: np.ndarray,
    angular_velocities: np.ndarray,
    info: dict[str, Any],
) -> Bed:
    """``bed`` with its grains at new ``positions`` (N, 3) m, in id order: a run's final state."""
    from dozerlab.scenarios.bed import Bed

    return Bed(
        scenario=bed.scenario,
        length=bed.length,
        width=bed.width,
        positions=positions,
        radii=bed.radii,
        masses=bed.masses,
        velocities=velocities,
        angular_velocities=angular_velocities,
        material=bed.material,
        seed=bed.seed,
        info=info,
    )
