"""One SPOOK step of a World: sort, detect, assemble, warm start, solve, report, integrate."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np

from dozerlab.ndem import broadphase, contacts, solver
from dozerlab.ndem.stats import DivergenceError, StepStats

if TYPE_CHECKING:
    from dozerlab.ndem.world import World

SORTED_FIELDS = ("_x", "_v", "_w", "_r", "_m", "_mu", "_mur", "_id")
# Below this many contacts a sweep is too short to pay for the per-phase thread barriers.
PARALLEL_MIN_CONTACTS = 4096


def _sort(world: World) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Re-sort the spheres by grid cell; returns the cell of each slot, cell offsets and dims."""
    reach = _reach(world)
    lo, cell, dims = broadphase.grid_layout(
        world._x, float(reach.max()), max(8 * world.n_spheres, 4096)
    )
    cells = broadphase.cell_indices(world._x, lo, cell, dims)
    perm, start = broadphase.counting_sort(cells, int(np.prod(dims)))
    for f in SORTED_FIELDS:
        setattr(world, f, np.ascontiguousarray(getattr(world, f)[perm]))
    return cells[perm], start, dims


def _reach(world: World) -> np.ndarray:
    """Contact search radius (N,) m: radius + half the margin + the distance moved this step.

    Pairs that may close their gap within the step get a speculative row; the motion term is
    capped at the largest radius so one fast particle cannot inflate the grid.
    """
    h = world.dt
    speed = np.sqrt(((world._v + h * world.gravity) ** 2).sum(axis=1))
    rmax = float(world._r.max())
    return (
        world._r + 0.5 * world.contact_margin * float(world._r.min()) + np.minimum(h * speed, rmax)
    )


def advance(world: World) -> StepStats:
    """Advance ``world`` by one step of ``world.dt``; returns the step's stats."""
    h = world.dt
    bodies = world.bodies
    nb = len(bodies)
    bodies.load_center = bodies.center.copy()
    if world.n_spheres == 0:
        bodies.force[:] = 0.0
        bodies.torque[:] = 0.0
        bodies.integrate(h)
        world.time += h
        world.step_count += 1
        return StepStats(world.step_count, world.time, 0, 0, 0.0, 0.0, 0.0)

    if not solver.all_finite(world._x, world._v, world._w):
        _raise_non_finite(world, "before")
    cells, start, dims = _sort(world)
    slab_of_column = broadphase.slab_partition(start, dims, world.slabs)
    n_slabs = int(slab_of_column.max()) + 1
    slab = slab_of_column[cells // int(dims[1] * dims[2])]
    reach = _reach(world)
    pi, pj, pn, pg = broadphase.sphere_pairs(world._x, world._r, reach, cells, start, dims)
    body_speed = float(np.sqrt((bodies.vel**2).sum(axis=1)).max(initial=0.0))
    bi, bb, bn, bg = contacts.body_contacts(
        world._x,
        world._r,
        2.0 * (reach - world._r) + world.dt * body_speed,
        bodies.kind,
        bodies.center,
        bodies.rotations(),
        bodies.half,
        bodies.normal,
    )
    invm = 1.0 / world._m
    invI = 1.0 / (0.4 * world._m * world._r**2)
    nu = world.poisson_ratio
    estar = world.youngs_modulus / (2.0 * (1.0 - nu * nu))
    upsilon = 1.0 / (1.0 + 4.0 * world.damping_steps)
    ci, cj, cd, gap, gstart = contacts.assemble(
        pi,
        pj,
        pn,
        pg,
        bi,
        bb,
        bn,
        bg,
        slab,
        n_slabs,
        world._x,
        world._v,
        world._r,
        invm,
        invI,
        world._mu,
        world._mur,
        bodies.center,
        bodies.vel,
        bodies.ang,
        bodies.mu,
        h,
        upsilon,
        estar,
    )
    frac = _check_overlap(world, ci, cj, gap)

    world._v += h * world.gravity
    if world.warm_start:
        lam = world._warm.lookup(world._id, ci, cj, cd[:, contacts.N0 : contacts.N0 + 3])
    else:
        lam = np.zeros((ci.shape[0], 7))
    threads = numba.get_num_threads()
    if ci.shape[0] < PARALLEL_MIN_CONTACTS:
        numba.set_num_threads(1)
    try:
        residual = solver.pgs(
            ci,
            cj,
            cd,
            lam,
            world._v,
            world._w,
            invm,
            invI,
            gstart,
            n_slabs,
            world.iterations,
            world.warm_start,
        )
    finally:
        numba.set_num_threads(threads)
    world._warm.store(world._id, ci, cj, lam)
    bodies.force, bodies.torque = contacts.body_loads(
        ci, cj, cd, lam, world._x, bodies.center, nb, h
    )
    if solver.integrate(world._x, world._v, world._w, h):
        _raise_non_finite(world, "after")
    bodies.integrate(h)
    world.time += h
    world.step_count += 1
    touching = gap > 0.0
    return StepStats(
        step=world.step_count,
        time=world.time,
        contacts=int(touching.sum()),
        speculative=int((~touching).sum()),
        residual=float(residual),
        max_overlap=float(gap.max(initial=0.0)),
        max_overlap_fraction=float(frac.max(initial=0.0)),
    )


def _check_overlap(world: World, ci: np.ndarray, cj: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """Overlaps over the smaller radius (Nc,); DivergenceError when one exceeds max_overlap."""
    rmin = np.where(cj >= 0, np.minimum(world._r[ci], world._r[np.maximum(cj, 0)]), world._r[ci])
    frac = np.maximum(gap, 0.0) / rmin
    if frac.size == 0 or frac.max() <= world.max_overlap:
        return frac
    k = int(frac.argmax())
    other = f"sphere {world._id[cj[k]]}" if cj[k] >= 0 else f"body {-cj[k] - 1}"
    raise DivergenceError(
        f"overlap {gap[k]:.4g} m = {frac[k]:.3g} of the smaller radius between sphere "
        f"{world._id[ci[k]]} and {other} exceeds max_overlap = {world.max_overlap} at step "
        f"{world.step_count + 1} (t = {world.time:.6g} s)"
    )


def _raise_non_finite(world: World, when: str) -> None:
    bad = world._id[~np.all(np.isfinite(np.hstack([world._x, world._v, world._w])), axis=1)]
    raise DivergenceError(
        f"non-finite sphere state (NaN or inf) {when} step {world.step_count + 1} "
        f"(t = {world.time:.6g} s): {bad.size} spheres, ids {np.sort(bad)[:10].tolist()}"
    )
