"""The reduced stepping loop (docs/models.md): fields → learned models → particles moved and projected.

One reduced step spans ``reduced.step_rows`` store rows (of ``sampling.every`` solver steps
each, h = step_rows·every·dt; the loop in :mod:`dozerlab.reduce.run`). From row j to row k,
with the blade tip at p_k:

1. the field model gives the velocity field of each row j+1..k (it predicts m rows per call;
   the loop asks again every m rows), from the fields sampled from the reduced state over the
   last H rows and the blade velocity of those rows and the next m (the blade's control is
   known ahead); the grains move by the mean of those rows' fields (:meth:`ReducedState.step`);
2. **advection**: a grain whose centre lies in the sampling volume at p_k, or within
   ``reduced.advect_margin`` bins ahead of, beside or above it, takes the field's velocity,
   trilinearly interpolated (mass-weighted; beyond the volume the nearest bins' value) to its
   position, and moves by h·v (left frozen, the grains just outside the volume held back the
   material the field carries: 42 % height accuracy with the truth fields on the quick sweep
   against 66 % with 2 bins, BENCHMARKS.md), unless it is at rest and the field there is
   slower than ``reduced.rest_speed``: then it stays at rest and only the projection may move
   it (the cut floor behind the blade, the bed ahead of the pile: fewer grains to project for
   the same surface, BENCHMARKS.md); a grain above the volume keeps the top bins'
   horizontal velocity and falls until the grains below hold it up, but within
   ``reduced.crest_bins`` bins of the volume's top it also rises with them (the pile's crest,
   which tips over the blade's top; for the models named in ``reduced.crest_models``, which
   :meth:`ReducedSettings.for_model` resolves); a grain outside that
   region that is moving flies ballistically under gravity — a grain the field carried out of
   the region, or one in flight, moves until it has landed, one only nudged by the projection
   until it is slower than ``reduced.rest_speed``; one at rest stays frozen. For a model named
   in ``reduced.density_models`` a grain the field carries is also steered towards the model's
   density (:func:`density_correction`);
3. **projection**: the grains that moved, the grains the blade box reaches and every grain
   within reach of those (frozen ones too: they yield with their own mass, as a bed pushed by
   the pile does, but for those below the sampling volume, which hold like the ground) are
   projected out of overlap with each other, the ground, the walls, the
   blade and the ring of grains around them, held as obstacles
   (:func:`dozerlab.reduce.projection.project`): without the ring, a grain at the edge of the
   projected set was pushed into one outside it and that overlap stayed, unseen by the step's
   statistic (0.11–0.18 r in the final states of the default sweep, 0.06–0.07 reported); the
   statistic covers every pair with a grain the step could move; a grain's velocity is then its
   displacement over h; a grain the projection still leaves deeper than
   ``reduced.projection.overlap_limit`` goes back to where it started the step and the held
   grains it overlaps yield, for one more projection (a cage of held grains), and so does one
   that moved past the ring and overlaps that deep over the whole bed, without velocity (a
   fast grain landing almost on a held one, pushed out along an arbitrary line); a grain outside
   the volume that the projection pushed upwards, within
   ``reduced.support_angle`` of vertical, has landed and comes to rest (sticky, like a grain on
   a high-friction bed); pushed up a steeper slope, it slides on;
4. the fields are sampled at p_k with the NDEM algorithm (``SamplingGrid``), and the rows
   inside the step take the fields between the sampled rows either side; the force model
   predicts the blade force and torque from them, for every row in one batched call after the
   loop, since no grain reads the force. The field model's history is the sampled density
   and, for a model named in ``reduced.predicted_history`` (``ridge`` by default), the
   velocity it predicted for the row (resampled, the interpolated field is smoothed again each row and the pile's
   motion ahead of the blade fades); for the others, the velocity sampled the same way from
   each grain's *flow* (:attr:`ReducedState.flow`): the field's or the flight's velocity for
   the grains it moved, the projected velocity for the rest. Fed the projection's
   push-outs as flow (grains lifted out of overlap read as upwelling), the evolution U-Net
   answered with ever more upward and forward motion: piles 50 % too tall, the bed below the cut
   dragged along, 3–30 % height accuracy on the default sweep's held-out points against 33–51 %
   with the flow (BENCHMARKS.md).

The first H rows (the models' history) come from a short NDEM warm-up of the same bed along the
same trajectory; its time counts in ``wall_time_s``. A blade that reaches no grain before the
first predicted row leaves NDEM nothing to move: the rows are then the bed sampled as it lies. Only the grains near the blade or moving
are touched by the costly phases; the one pass over every grain per step is a cell lookup
(selection), tens of µs for 10⁴ grains.
"""

from __future__ import annotations

import logging
import time as wallclock
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numba import njit

from dozerlab.fields.sampling import SamplingGrid
from dozerlab.reduce.interpolate import interpolate, trilinear
from dozerlab.reduce.projection import (
    Bodies,
    ProjectionStats,
    largest_movable_overlap,
    overlapping,
    project,
)
from dozerlab.runtime import DozerlabError

log = logging.getLogger(__name__)

#: Phases of a reduced step whose wall time is recorded (s, summed over the run).
PHASES = (
    "warmup",
    "selection",
    "advection",
    "projection",
    "sampling",
    "field_inference",
    "force_inference",
    "output",
)


@dataclass(frozen=True)
class ReducedSettings:
    """The ``reduced`` config section's loop settings (units in the schema)."""

    iterations: int = 96
    method: str = "gauss_seidel"
    relaxation: float = 1.7
    slop: float = 0.05
    tolerance: float = 0.02
    overlap_limit: float = 0.1
    advect_margin: float = 2.0
    #: bins over the volume's top within which the top bins' lift carries a grain (the state
    #: applies it as given; :meth:`for_model` sets it to 0 for a model not in crest_models)
    crest_bins: float = 0.5
    #: the evolution models (by name) whose loops lift the pile's crest (crest_bins)
    crest_models: tuple[str, ...] = ("replay",)
    rest_speed: float = 0.05
    support_angle: float = 45.0
    divergence_overlap: float = 0.5
    #: the evolution models (by name) that read their own predicted velocity as history
    predicted_history: tuple[str, ...] = ("ridge",)
    #: store rows one reduced step spans (the grains move, are projected and sampled once)
    step_rows: int = 2
    #: the evolution models (by name) whose density the grains are steered towards
    density_models: tuple[str, ...] = ("replay",)
    #: the steering's gain (see :func:`density_correction`)
    density_gain: float = 0.5

    @classmethod
    def from_config(cls, config: Mapping[str, Any]) -> ReducedSettings:
        """The settings of a validated config: of its ``reduced`` section, the fields
        :data:`dozerlab.reduce.LOOP_FIELDS` only."""
        r = config["reduced"]
        p = r["projection"]
        return cls(
            iterations=int(p["iterations"]),
            method=str(p["method"]),
            relaxation=float(p["relaxation"]),
            slop=float(p["slop"]),
            tolerance=float(p["tolerance"]),
            overlap_limit=float(p["overlap_limit"]),
            advect_margin=float(r["advect_margin"]),
            crest_bins=float(r["crest_bins"]),
            crest_models=tuple(str(m) for m in r["crest_models"]),
            rest_speed=float(r["rest_speed"]),
            support_angle=float(r["support_angle"]),
            divergence_overlap=float(r["divergence_overlap"]),
            predicted_history=tuple(str(m) for m in r["predicted_history"]),
            step_rows=int(r["step_rows"]),
            density_models=tuple(str(m) for m in r["density_models"]),
            density_gain=float(r["density_gain"]),
        )

    def for_model(self, name: str) -> ReducedSettings:
        """These settings for the loop of field model ``name``: without the crest
        (``crest_bins`` 0) unless ``name`` is in ``crest_models``."""
        return self if name in self.crest_models else replace(self, crest_bins=0.0)

    def steers(self, name: str) -> bool:
        """Whether the loop of field model ``name`` steers its grains towards the model's
        density (``density_models``, at a gain above 0)."""
        return name in self.density_models and self.density_gain > 0.0


@dataclass
class PhaseTimes:
    """Wall time per phase (s) and the store rows they cover."""

    seconds: dict[str, float] = field(default_factory=lambda: dict.fromkeys(PHASES, 0.0))
    rows: int = 0

    def add(self, phase: str, t0: float) -> float:
        """Add the time since ``t0`` to ``phase``; returns now."""
        now = wallclock.perf_counter()
        self.seconds[phase] += now - t0
        return now

    def per_row_ms(self) -> dict[str, float]:
        """Mean ms per store row of each phase but the warm-up (NDEM's rows take the same
        simulated time: the figures compare with its wall time per row)."""
        n = max(self.rows, 1)
        return {k: 1e3 * v / n for k, v in self.seconds.items() if k != "warmup"}


@njit(cache=True)
def _select(
    x, moving, quiet, box_lower, box_upper, centre, reach, lo, cell, dims
):  # pragma: no cover
    """One pass over every grain: which lie in the advected box [box_lower, box_upper] (3,) m,
    which within ``reach`` (3,) m of the blade box ``centre`` (3,), and the grains to project
    (sorted indices): the movable ones, every grain whose selection cell is, or neighbours, the
    cell of a mover (in the box and not ``quiet`` (N,) bool, near the blade or ``moving``),
    then the ring of obstacles
    around them, every other grain whose cell neighbours a movable one's (a movable grain
    pushed into a grain outside the projected set would keep that overlap unseen). Returns
    (inside (N,) bool, near_blade (N,) bool, selected (S,) int64, movable (S,) bool)."""
    n = x.shape[0]
    inside = np.empty(n, np.bool_)
    near = np.empty(n, np.bool_)
    d0, d1, d2 = dims[0], dims[1], dims[2]
    # the box tests, cell and mark of a grain in scalars and one flat index: with three cell
    # indices a grain and the bounds read from their arrays, a step's selection on the trench
    # took 0.42 ms against 0.24 (BENCHMARKS.md, "The loop's passes over the grains, lighter")
    cells = np.empty(n, np.int64)
    # 3: a mover's cell; 2: its neighbour (movable grains); 1: their neighbours (obstacles)
    marks = np.zeros((d0, d1, d2), np.int8)
    flat = marks.reshape(-1)
    sources = np.empty((n, 3), np.int64)  # the movers' cells, each once
    ns = 0
    bl0, bl1, bl2 = box_lower[0], box_lower[1], box_lower[2]
    bu0, bu1, bu2 = box_upper[0], box_upper[1], box_upper[2]
    ce0, ce1, ce2 = centre[0], centre[1], centre[2]
    re0, re1, re2 = reach[0], reach[1], reach[2]
    lo0, lo1, lo2 = lo[0], lo[1], lo[2]
    for p in range(n):
        v0, v1, v2 = x[p, 0], x[p, 1], x[p, 2]
        ins = (bl0 <= v0) & (v0 <= bu0) & (bl1 <= v1) & (v1 <= bu1) & (bl2 <= v2) & (v2 <= bu2)
        nb = (abs(v0 - ce0) <= re0) & (abs(v1 - ce1) <= re1) & (abs(v2 - ce2) <= re2)
        c0 = min(max(int((v0 - lo0) / cell), 0), d0 - 1)
        c1 = min(max(int((v1 - lo1) / cell), 0), d1 - 1)
        c2 = min(max(int((v2 - lo2) / cell), 0), d2 - 1)
        c = (c0 * d1 + c1) * d2 + c2
        cells[p] = c
        inside[p], near[p] = ins, nb
        if ((ins and not quiet[p]) or nb or moving[p]) and flat[c] < 3:
            flat[c] = 3
            sources[ns, 0], sources[ns, 1], sources[ns, 2] = c0, c1, c2
            ns += 1
    for s in range(ns):
        c0, c1, c2 = sources[s, 0], sources[s, 1], sources[s, 2]
        for i in range(max(c0 - 2, 0), min(c0 + 3, d0)):
            inner_i = abs(i - c0) <= 1
            for j in range(max(c1 - 2, 0), min(c1 + 3, d1)):
                inner_ij = inner_i and abs(j - c1) <= 1
                for k in range(max(c2 - 2, 0), min(c2 + 3, d2)):
                    inner = inner_ij and abs(k - c2) <= 1
                    marks[i, j, k] = max(marks[i, j, k], 2 if inner else 1)
    count = 0
    chosen = np.empty(n, np.int64)
    movable = np.empty(n, np.bool_)
    for p in range(n):
        mark = flat[cells[p]]
        if mark > 0:
            chosen[count] = p
            movable[count] = mark >= 2
            count += 1
    return inside, near, chosen[:count], movable[:count]


@njit(cache=True)
def _settle(
    x, v, moving, flow, sel, x0, xs, vs, ins, bal, near, h, cos_angle, rest_speed
):  # pragma: no cover - compiled
    """Write the projected grains ``sel`` (S,) back: positions ``xs`` (S, 3) m into ``x``, and
    into ``v``, ``moving`` and ``flow`` (N, …) what they are doing now (step 3 of the module
    doc), from their start ``x0`` and the field's or flight's velocity ``vs`` (S, 3) m/s.

    A grain outside the volume (``ins`` False) and not near the blade that the projection
    pushed up within the support cone (``cos_angle``: the cosine of its half angle) has landed
    and rests; a grain only the projection nudged (neither ``ins`` nor ``bal``, ballistic)
    rests once no faster than ``rest_speed``; any other is moving with its displacement over
    ``h`` s. Its flow is ``vs`` if the field or its flight moved it, else that velocity.
    """
    slow = rest_speed * rest_speed
    for q in range(sel.shape[0]):
        p = sel[q]
        push2 = 0.0  # |projection's push|²: where it left the grain against where it sent it
        speed2 = 0.0
        for a in range(3):
            d = xs[q, a] - (x0[q, a] + h * vs[q, a])
            push2 += d * d
            v[p, a] = (xs[q, a] - x0[q, a]) / h
            speed2 += v[p, a] * v[p, a]
        push_z = xs[q, 2] - (x0[q, 2] + h * vs[q, 2])
        carried = ins[q] or bal[q]
        landed = not ins[q] and not near[q] and push_z > cos_angle * np.sqrt(push2)
        still = landed or (not carried and speed2 <= slow)
        moving[p] = not still
        for a in range(3):
            if still:
                v[p, a] = 0.0
            x[p, a] = xs[q, a]
            flow[p, a] = vs[q, a] if carried else v[p, a]


@njit(cache=True)
def _quiet(x, moving, box_lower, upper, field, weight, lower, size, rest2):  # pragma: no cover
    """(N,) bool: the grains of ``x`` (N, 3) m at rest (not ``moving``) in the box
    [box_lower, upper] (3,) m where the field ``field`` (X, Y, Z, 3) m/s, blended by ``weight``
    (X, Y, Z) kg/m³ (:func:`trilinear`; the volume's corner ``lower`` (3,) m, bins ``size`` (3,)
    m), is slower than √rest2 m/s. One pass over the grains, one blend of those in the box (the
    NumPy masks, gather and product around the blend were a tenth to a sixth of the loop's
    selection; BENCHMARKS.md, "The loop's selection and sampling without their gathers")."""
    n = x.shape[0]
    out = np.zeros(n, np.bool_)
    which = np.empty(n, np.int64)
    c = 0
    for p in range(n):
        if (
            not moving[p]
            and box_lower[0] <= x[p, 0] <= upper[0]
            and box_lower[1] <= x[p, 1] <= upper[1]
            and box_lower[2] <= x[p, 2] <= upper[2]
        ):
            which[c] = p
            c += 1
    pts = np.empty((c, 3))
    for q in range(c):
        for a in range(3):
            pts[q, a] = x[which[q], a]
    v = np.empty((c, 3))
    trilinear(field, weight, lower, size, pts, v)
    for q in range(c):
        out[which[q]] = v[q, 0] * v[q, 0] + v[q, 1] * v[q, 1] + v[q, 2] * v[q, 2] < rest2
    return out


@njit(cache=True)
def _advect(
    x,
    v,
    m,
    moving,
    sel,
    movable,
    inside,
    ballistic,
    near_blade,
    field,
    weight,
    lower,
    size,
    top,
    crest_top,
    h,
    gravity,
):  # pragma: no cover - compiled
    """Step 2 of the module doc for the selected grains ``sel`` (S,) of ``x``, ``v`` (N, 3) m,
    m/s (masses ``m``, ``moving``, ``inside``, ``ballistic``, ``near_blade`` (N,)), in one pass:
    the field ``field`` (X, Y, Z, 3) m/s interpolated mass-weighted by ``weight`` (X, Y, Z)
    kg/m³ (the volume's lower corner ``lower`` (3,) m, bins ``size`` (3,) m) for those in the
    volume, the fall above its ``top`` (m; below ``crest_top`` m a grain the top bins lift rises
    with them), the ballistic flight, each over ``h`` s under ``gravity`` (3,) m/s².

    Returns the start positions x0 (S, 3) m, the advected ones xs, their velocities vs (S, 3)
    m/s, which were carried by the field (ins) or flying (bal), which move (mover: carried,
    flying, near the blade or moving), all (S,) bool, and the projection's inverse masses
    inv_m (S,) 1/kg: 0 for an obstacle (not ``movable`` (S,)) and for a grain at rest below
    the volume.
    """
    n = sel.shape[0]
    x0 = np.empty((n, 3))
    xs = np.empty((n, 3))
    vs = np.empty((n, 3))
    ins = np.empty(n, np.bool_)
    bal = np.empty(n, np.bool_)
    mover = np.empty(n, np.bool_)
    inv_m = np.empty(n)
    # the carried grains' positions gathered in the pass that reads the grains, and xs made
    # once: with the blend's sums in registers, a step's advection on the trench took
    # 0.36-0.38 ms against 0.46-0.51 (BENCHMARKS.md, "The loop's passes over the grains, lighter")
    pts = np.empty((n, 3))
    carried = 0
    for q in range(n):
        p = sel[q]
        for a in range(3):
            x0[q, a] = x[p, a]
        ins[q], bal[q] = inside[p], ballistic[p]
        if ins[q]:
            for a in range(3):
                pts[carried, a] = x0[q, a]
            carried += 1
    out = np.empty((carried, 3))
    trilinear(field, weight, lower, size, pts[:carried], out)
    c = 0
    for q in range(n):
        p = sel[q]
        if ins[q]:
            for a in range(3):
                vs[q, a] = out[c, a]
            c += 1
            # Above the volume the field says nothing: a grain there keeps the top bins'
            # horizontal velocity and falls until the grains below hold it up. Given their
            # upward velocity too, the pile in front of the blade grew to 1.27 m where NDEM's
            # stops below 0.8 m (step 1.0/0.12, the truth fields; BENCHMARKS.md) ... but just
            # above the top a grain the top bins lift rises with them: the pile's crest, which in
            # NDEM climbs past the blade's top and tips over it (held down there, the strip over
            # and behind the blade lost 0.02-0.05 of the smoothed surface against the twin's
            # 0.01-0.03 with NDEM's own fields; BENCHMARKS.md, "The pile's crest over the blade's
            # top")
            if x0[q, 2] > top and (vs[q, 2] <= 0.0 or x0[q, 2] > crest_top):
                vs[q, 2] = v[p, 2] + h * gravity[2]
        elif bal[q]:
            for a in range(3):
                vs[q, a] = v[p, a] + h * gravity[a]
        else:
            for a in range(3):
                vs[q, a] = 0.0
        for a in range(3):
            xs[q, a] = x0[q, a] + h * vs[q, a]
        mover[q] = ins[q] or bal[q] or near_blade[p] or moving[p]
        # the bed at rest below the sampling volume holds like the ground: yielding with its
        # own mass, it was packed ever deeper under the pile (grains moved from 0.3 m below the
        # surface: 1.6-2.0 thousand with the learned fields, 0.35 thousand in NDEM)
        inv_m[q] = 1.0 / m[p] if movable[q] and (mover[q] or x0[q, 2] >= lower[2]) else 0.0
    return x0, xs, vs, ins, bal, mover, inv_m


@njit(cache=True)
def _beyond(step, mover, movable, far, near):  # pragma: no cover - compiled
    """(S,) bool: the ``movable`` (S,) rows of ``step`` (S, 3) m longer than ``far`` m for a
    ``mover`` (S,) bool, else ``near`` m; one pass (NumPy's norm and masks cost 0.2 ms a step)."""
    out = np.empty(step.shape[0], np.bool_)
    for q in range(step.shape[0]):
        d = np.sqrt(step[q, 0] * step[q, 0] + step[q, 1] * step[q, 1] + step[q, 2] * step[q, 2])
        out[q] = movable[q] and d > (far if mover[q] else near)
    return out


class ReducedState:
    """The particles of a reduced run and one step of the loop (steps 2–3 of the module doc).

    Args:
        positions, velocities: (N, 3) m, m/s (copied). radii, masses: (N,) m, kg.
        bodies: ground and walls (:class:`Bodies`), then the blade box last.
        blade_half: (3,) the blade box's half extents, m; ``tip_offset`` (3,) centre − tip, m.
        grid: the sampling grid; gravity (3,) m/s²; domain_lower/upper (3,) the bed's box (the
            selection grid spans it; particles outside it count as "left").
    """

    def __init__(
        self,
        positions: np.ndarray,
        velocities: np.ndarray,
        radii: np.ndarray,
        masses: np.ndarray,
        bodies: Bodies,
        blade_half: np.ndarray,
        tip_offset: np.ndarray,
        grid: SamplingGrid,
        gravity: np.ndarray,
        settings: ReducedSettings,
        domain_lower: np.ndarray,
        domain_upper: np.ndarray,
    ) -> None:
        self.x = np.array(positions, dtype=np.float64)
        self.v = np.array(velocities, dtype=np.float64)
        self.r = np.ascontiguousarray(radii, dtype=np.float64)
        self.m = np.ascontiguousarray(masses, dtype=np.float64)
        self.bodies = bodies
        self.blade_half = np.asarray(blade_half, dtype=np.float64)
        self.tip_offset = np.asarray(tip_offset, dtype=np.float64)
        self.grid = grid
        self.gravity = np.asarray(gravity, dtype=np.float64)
        self.settings = settings
        self.extent = np.array(grid.bins) * np.array(grid.bin_size)
        rmax = float(self.r.max()) if self.r.size else 0.0
        # Selection cells: one grain diameter plus the largest step a grain takes (half a
        # radius a row), so a grain within contact reach of a mover is in the mover's cell or a
        # neighbour.
        self.cell = 2.0 * rmax + 0.5 * rmax * settings.step_rows
        self.lo = np.asarray(domain_lower, dtype=np.float64) - self.cell
        hi = np.asarray(domain_upper, dtype=np.float64) + self.cell
        self.dims = np.maximum(np.ceil((hi - self.lo) / self.cell).astype(np.int64), 1)
        self.moving = np.linalg.norm(self.v, axis=1) > settings.rest_speed
        self.v[~self.moving] = 0.0
        #: (N, 3) m/s: the velocity the field or the flight gave each grain in the last step; a
        #: grain neither carried nor flying has its velocity (the field model's input, step 4)
        self.flow = self.v.copy()
        self.last: ProjectionStats | None = None
        self.active = 0
        self.beyond_ring = 0  # steps whose statistic needed the whole bed (see _past_ring)

    def _past_ring(self, step: np.ndarray, mover: np.ndarray, movable: np.ndarray) -> np.ndarray:
        """(S,) bool: the projected grains whose ``step`` (S, 3) m went past what the selection
        covers.

        Every grain within one selection cell (2.5 r_max) of a movable grain is projected with
        it, and within two cells of a ``mover`` (S,) bool: a contact at the end of the step lies
        in the projected set while a mover moved less than 2 cells − 2 r_max and another
        ``movable`` (S,) bool grain less than 1 cell − 2 r_max.
        """
        contact = 2.0 * float(self.r.max())
        return _beyond(step, mover, movable, 2.0 * self.cell - contact, self.cell - contact)

    def _whole_bed_overlap(self, sel: np.ndarray, xs: np.ndarray, movable: np.ndarray) -> float:
        """The largest overlap (over the smaller radius) of a pair with a movable grain, over
        the whole bed with the projected grains ``sel`` (S,) at ``xs`` (S, 3) m."""
        whole = self.x.copy()
        whole[sel] = xs
        w = np.zeros(len(whole))
        w[sel[movable]] = 1.0
        return largest_movable_overlap(whole, self.r, w)

    def set_blade(self, tip: np.ndarray) -> None:
        """Place the blade box (the last body) with its tip at ``tip`` (3,) m."""
        self.bodies.centre[-1] = np.asarray(tip) + self.tip_offset

    def step(
        self,
        velocity: np.ndarray,
        density: np.ndarray,
        tip: np.ndarray,
        h: float,
        times: PhaseTimes | None = None,
        correction: np.ndarray | None = None,
    ) -> ProjectionStats:
        """Move the grains over one step of ``h`` s with the field of the new row.

        velocity (Nx,Ny,Nz,3) m/s and density (Nx,Ny,Nz) kg/m³ are the row's fields at the
        blade ``tip`` (3,) m where the step ends; ``correction`` (Nx,Ny,Nz,3) m/s, if given, is
        added, plainly interpolated, to the velocity of the grains the field carries
        (:func:`density_correction`). Raises DozerlabError on divergence.
        """
        times = times if times is not None else PhaseTimes()
        t0 = wallclock.perf_counter()
        s = self.settings
        self.set_blade(tip)
        lower = np.asarray(tip) + np.asarray(self.grid.lower)
        # the field's edge carries the grains just ahead of, beside and above the volume too
        # (never below it or behind the blade): frozen, they would hold back the material
        reach_out = s.advect_margin * np.asarray(self.grid.bin_size)
        # and every grain above it: a pile taller than the volume rides with its top bins (left
        # out, the grains above it came to rest on the rising ones and stayed in the air when the
        # blade moved on: 17.6 % height accuracy with the truth fields on step 1.0/0.12)
        upper = lower + self.extent + reach_out
        upper[2] = np.inf
        centre = self.bodies.centre[-1]
        reach = self.blade_half + float(self.r.max()) * 1.5
        box_lower = lower - reach_out * np.array([0.0, 1.0, 0.0])
        # a grain at rest where the field is slower than the rest speed stays at rest
        vel64 = np.ascontiguousarray(velocity, dtype=np.float64)
        rho64 = np.ascontiguousarray(density, dtype=np.float64)
        bin_size = np.asarray(self.grid.bin_size, dtype=np.float64)
        quiet = _quiet(
            self.x,
            self.moving,
            box_lower,
            upper,
            vel64,
            rho64,
            lower,
            bin_size,
            s.rest_speed * s.rest_speed,
        )
        inside, near_blade, sel, movable = _select(
            self.x,
            self.moving,
            quiet,
            box_lower,
            upper,
            centre,
            reach,
            self.lo,
            self.cell,
            self.dims,
        )
        inside &= ~quiet
        ballistic = self.moving & ~inside
        self.active = int(np.count_nonzero(inside | ballistic | near_blade))
        t0 = times.add("selection", t0)

        top = lower[2] + self.extent[2]
        x0, xs, vs, ins, bal, mover, inv_m = _advect(
            self.x,
            self.v,
            self.m,
            self.moving,
            sel,
            movable,
            inside,
            ballistic,
            near_blade,
            vel64,
            rho64,
            lower,
            np.asarray(self.grid.bin_size, dtype=np.float64),
            top,
            top + s.crest_bins * self.grid.bin_size[2],
            h,
            self.gravity,
        )
        if correction is not None:
            # plainly blended: a grain in a bin the field leaves empty is steered too
            carried = np.flatnonzero(ins)
            dv = interpolate(correction, x0[carried], lower, np.asarray(self.grid.bin_size))
            vs[carried] += dv
            xs[carried] += h * dv
        t0 = times.add("advection", t0)
        radii = self.r[sel]

        def projected(relaxation: float = s.relaxation) -> ProjectionStats:
            return project(
                xs,
                radii,
                inv_m,
                self.bodies,
                iterations=s.iterations,
                method=s.method,
                relaxation=relaxation,
                slop=s.slop,
                tolerance=s.tolerance,
                overlap_limit=s.overlap_limit,
            )

        def projected_again(first: ProjectionStats) -> ProjectionStats:
            again = projected(min(s.relaxation, 1.0))
            again.sweeps += first.sweeps
            again.tests += first.tests
            again.body_depth = max(again.body_depth, first.body_depth)
            return again

        stats = projected()
        if stats.max_overlap > s.overlap_limit:
            # A grain caged by grains that hold still (the bed below the volume) cannot be
            # pushed out through a gap narrower than itself: it goes back to where it started
            # the step, the cage yields with its own mass, and the step is projected again (two
            # rows a step left one grain behind the blade of hill 1.5/0.06 at 0.26 radius with
            # the ridge and one at 0.18 for 30 steps with the unet; BENCHMARKS.md)
            deep = overlapping(xs, radii, inv_m, s.overlap_limit)
            stuck = deep & (inv_m > 0.0)
            xs[stuck], vs[stuck] = x0[stuck], 0.0
            held = deep & movable & (inv_m == 0.0)
            inv_m[held] = 1.0 / self.m[sel[held]]
            stats = projected_again(stats)
        if not np.isfinite(xs).all():
            raise DozerlabError("reduced step produced non-finite positions")
        far = self._past_ring(xs - x0, mover, movable)
        if far.any():
            # a grain moved further than the ring of obstacles reaches: its contacts may lie
            # outside the projected set, so the statistic is taken over the whole bed
            worst = self._whole_bed_overlap(sel, xs, movable)
            if worst > s.overlap_limit:
                # A fast grain landing almost on a held one (centres 6 mm apart) is pushed out
                # along a line as arbitrary as theirs, from held grain to held grain: 0.22 m in
                # one sweep, onto grains the ring does not hold (a persistence loop with
                # reduced.crest_bins 0.5 stopped at 0.81 radius; BENCHMARKS.md). It goes back to
                # where it started the step, without velocity, and the step is projected again.
                xs[far], vs[far] = x0[far], 0.0
                stats = projected_again(stats)
                far = self._past_ring(xs - x0, mover, movable)
                worst = self._whole_bed_overlap(sel, xs, movable) if far.any() else 0.0
            stats.max_overlap = max(stats.max_overlap, worst)
            self.beyond_ring += 1
        if stats.max_overlap > s.divergence_overlap:
            raise DozerlabError(
                f"largest overlap after projection is {stats.max_overlap:.3g} of a radius, above "
                f"reduced.divergence_overlap = {s.divergence_overlap}; raise "
                "reduced.projection.iterations"
            )
        # held up by the bed (not by the blade: a grain on the blade's top would stay in the air
        # where the blade left it), pushed within reduced.support_angle of straight up; on a
        # steeper slope it slides on (resting wherever anything pushed it up, piles stood
        # steeper than NDEM's: 46.1 % mean height accuracy against 47.3 % at 60° with the
        # truth fields on four training points of the default sweep, BENCHMARKS.md). A grain
        # the field or its flight moved falls until something holds it up (landed): left at rest
        # where the field let it go, piles of grains stood in the air behind the blade (17.6 %
        # height accuracy with the truth fields on step 1.0/0.12, BENCHMARKS.md). A grain only
        # the projection nudged rests once slow.
        _settle(
            self.x,
            self.v,
            self.moving,
            self.flow,
            sel,
            x0,
            xs,
            vs,
            ins,
            bal,
            near_blade[sel],
            h,
            np.cos(np.radians(s.support_angle)),
            s.rest_speed,
        )
        self.last = stats
        times.add("projection", t0)
        return stats


def density_correction(
    loop_density: np.ndarray,
    field_density: np.ndarray,
    bin_size: tuple[float, float, float] | np.ndarray,
    h: float,
    gain: float,
    solid_density: float,
) -> np.ndarray:
    """The velocity (Nx,Ny,Nz,3) m/s that steers the grains' density towards the field's.

    ``loop_density`` and ``field_density`` (Nx,Ny,Nz) kg/m³ are the same row's density sampled
    from the grains and given by the evolution model; ``bin_size`` (3,) m; ``h`` s the step.
    With φ = (ρ_loop − ρ_field) / ``solid_density``, a grain moves by −gain·L_a²·∂φ/∂x_a along
    each axis a of bin length L_a over the step: down the excess, out of bins the grains pack
    denser than the field and into those they leave emptier (a diffusion of the excess).
    Advected by NDEM's own velocity alone, the grains of the default sweep's held-out points
    packed denser than NDEM's in front of the blade (the density summed across the blade 11-12 %
    off NDEM's in RMS, 8-10 % steered at gain 0.5) and the force model read a larger push
    (BENCHMARKS.md, "The loop's density steered towards replay's").
    """
    phi = (np.asarray(loop_density, np.float64) - np.asarray(field_density, np.float64)) / float(
        solid_density
    )
    size = np.asarray(bin_size, np.float64)
    out = np.empty((*phi.shape, 3))
    for a in range(3):
        out[..., a] = (-gain * size[a] * size[a] / h) * np.gradient(phi, size[a], axis=a)
    return out


def compile_kernels(grid: SamplingGrid) -> None:
    """Run every numba kernel of a step once on two grains, so compilation (or loading the
    compiled cache) falls in the job's time, not in the stepping loop's."""
    from dozerlab.ndem.bodies import Bodies as NdemBodies

    b = NdemBodies()
    b.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    b.add_box((-1.0, 0.0, 1.0), (0.1, 0.5, 0.5), True, 0.5, None)
    x = np.array([[0.1, 0.0, 0.05], [0.15, 0.0, 0.05]])
    state = ReducedState(
        x,
        np.zeros_like(x),
        np.full(2, 0.03),
        np.ones(2),
        Bodies(b.kind, b.center, b.rotations(), b.half, b.normal),
        b.half[1],
        np.zeros(3),
        grid,
        np.zeros(3),
        ReducedSettings(),
        np.zeros(3),
        np.ones(3),
    )
    state.step(np.zeros((*grid.bins, 3)), np.zeros(grid.bins), np.zeros(3), 0.01)
    # two grains pushed apart further than the contact search's margin: the fresh search too
    deep = np.array([[0.1, 0.0, 0.05], [0.11, 0.0, 0.05]])
    for method in ("gauss_seidel", "jacobi"):
        project(
            deep.copy(), np.full(2, 0.03), np.ones(2), state.bodies, iterations=1, method=method
        )
    # one velocity (NDEM's warm-up rows, and the loops whose model reads its own predictions)
    # and two: compiled in a fresh clone's first loop, the one-velocity pass took 0.7 s of it
    for velocities in ((x,), (x, x)):
        grid.sample_velocities(x, velocities, np.full(2, 0.03), np.ones(2), np.zeros(3))


def bodies_of(world: Any, blade: int) -> Bodies:
    """The world's planes and boxes with the blade box last, as projection reads them."""
    b = world.bodies
    order = [i for i in range(len(b)) if i != blade] + [blade]
    return Bodies(
        np.ascontiguousarray(b.kind[order]),
        np.ascontiguousarray(b.center[order]),
        np.ascontiguousarray(b.rotations()[order]),
        np.ascontiguousarray(b.half[order]),
        np.ascontiguousarray(b.normal[order]),
    )
