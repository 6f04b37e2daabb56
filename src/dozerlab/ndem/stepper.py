"""One SPOOK step of a World: sort, detect, assemble, warm start, solve, report, integrate."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import numba
import numpy as np
from numba import njit

from dozerlab.ndem import broadphase, contacts, solver
from dozerlab.ndem.bodies import Bodies
from dozerlab.ndem.contacts import BOX, _body_test
from dozerlab.ndem.params import METHODS, Parameters
from dozerlab.ndem.state import WorldState
from dozerlab.ndem.stats import DivergenceError, StepStats

# Below this many contacts a sweep is too short to pay for the per-phase thread barriers;
# below this many spheres the rest of a step (detection, assembly, warm start, integration).
PARALLEL_MIN_CONTACTS = 4096
PARALLEL_MIN_SPHERES = 2048


@contextmanager
def _serial_if(small: bool) -> Iterator[None]:
    """Run the block on one numba thread when ``small``, then restore the thread count."""
    threads = numba.get_num_threads()
    if small:
        numba.set_num_threads(1)
    try:
        yield
    finally:
        numba.set_num_threads(threads)


def _sort(
    state: WorldState, p: Parameters
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Re-sort the spheres by grid cell; returns the cell of each slot, cell offsets, dims and
    each slot's reach (:func:`_reach`, the same values as computed after the sort)."""
    reach = _reach(state, p)
    lo, cell, dims = broadphase.grid_layout(state.x, float(reach.max()), max(8 * state.n, 4096))
    cells = broadphase.cell_indices(state.x, lo, cell, dims)
    perm, start = broadphase.counting_sort(cells, int(np.prod(dims)))
    state.reorder(perm)
    return cells[perm], start, dims, reach[perm]


def _reach(state: WorldState, p: Parameters) -> np.ndarray:
    """Contact search radius (N,) m: radius + half the margin + the distance moved this step.

    Pairs that may close their gap within the step get a speculative row; the motion term is
    capped at the largest radius so one fast particle cannot inflate the grid.
    """
    margin = 0.5 * p.contact_margin * float(state.r.min())
    return _reach_of(state.v, state.r, p.dt, p.dt * p.gravity, margin, float(state.r.max()))


@njit(cache=True)
def _reach_of(v, r, h, hg, margin, rmax):
    """:func:`_reach` in one pass: r + margin + min(h·|v + h·g|, rmax), (N,) m."""
    out = np.empty(r.shape[0])
    for i in range(r.shape[0]):
        a, b, c = v[i, 0] + hg[0], v[i, 1] + hg[1], v[i, 2] + hg[2]
        out[i] = r[i] + margin + min(h * np.sqrt(a * a + b * b + c * c), rmax)
    return out


def advance(state: WorldState, bodies: Bodies, p: Parameters) -> StepStats:
    """Advance ``state`` and ``bodies`` by one step of ``p.dt``; returns the step's stats."""
    with _serial_if(state.n < PARALLEL_MIN_SPHERES):
        return _advance(state, bodies, p)


def _advance(state: WorldState, bodies: Bodies, p: Parameters) -> StepStats:
    h = p.dt
    nb = len(bodies)
    bodies.load_center = bodies.center.copy()
    if state.n == 0:
        bodies.force[:] = 0.0
        bodies.torque[:] = 0.0
        bodies.integrate(h)
        state.time += h
        state.step_count += 1
        return StepStats(state.step_count, state.time, 0, 0, 0.0, 0.0, 0.0, active=0)

    if not solver.all_finite(state.x, state.v, state.w):
        _raise_non_finite(state, "before")
    cells, start, dims, reach = _sort(state, p)
    slab_of_column = broadphase.slab_partition(start, dims, p.slabs)
    n_slabs = int(slab_of_column.max()) + 1
    slab = slab_of_column[cells // int(dims[1] * dims[2])]
    body_speed = float(np.sqrt((bodies.vel**2).sum(axis=1)).max(initial=0.0))
    rot = bodies.rotations()
    body_reach = 2.0 * (reach - state.r) + p.dt * body_speed
    zone = np.zeros(0, dtype=np.bool_)
    if not p.active_zone and not state.awake.all():
        # the zone switched off (a bed's pour ends): every sphere is stepped from here on
        state.awake[:] = True
        state.rest[:] = 0.0
    if p.active_zone:
        zone = _wake_zone(
            state.awake,
            state.rest,
            state.x,
            state.v,
            state.w,
            state.r,
            body_reach,
            bodies.kinematic & (bodies.kind == BOX),
            bodies.kind,
            bodies.center,
            rot,
            bodies.half,
            bodies.normal,
            p.zone_margin,
        )
        v0, w0 = state.v.copy(), state.w.copy()
    while True:
        solved = _solve_awake(
            state, bodies, p, cells, start, dims, reach, slab, n_slabs, rot, body_reach
        )
        ci, cj, cd, lam, (frac_max, touching, gap_max), residual, sweeps, rounds, deepest = solved
        if not p.active_zone:
            break
        # A sleeper that the awake grains now load beyond what holds it still wakes. The step
        # is solved again with it only where some pair heads past solver.relinearize_above: a
        # grain jammed between the blade and a rigid sleeper would sink into it by the blade's
        # travel every step. Solved again for every woken sleeper, the pile's push woke them
        # step after step and hill 0.875/0.045 ran 4.7x slower than the full solve (BENCHMARKS.md).
        held = p.wake_load * state.warm.held(state.public(~state.awake))[state.id]
        woke = _wake_loaded(state.awake, state.rest, ci, cj, lam, held)
        if not woke or deepest <= p.relinearize_above:
            break
        state.v[:], state.w[:] = v0, w0
    if p.active_zone:
        state.warm.store(state.id, ci, cj, lam, state.public(~state.awake))
        _wake_touched(state.awake, state.rest, ci, cj, state.v, p.rest_speed)
    else:
        state.warm.store(state.id, ci, cj, lam)
    bodies.force, bodies.torque = contacts.body_loads(
        ci, cj, cd, lam, state.x, bodies.center, nb, h
    )
    if solver.integrate(state.x, state.v, state.w, h):
        _raise_non_finite(state, "after")
    active = state.n
    if p.active_zone:
        active = _settle(
            state.awake, state.rest, zone, state.v, state.w, state.r, h, p.rest_speed, p.rest_time
        )
    bodies.integrate(h)
    state.time += h
    state.step_count += 1
    return StepStats(
        step=state.step_count,
        time=state.time,
        contacts=touching,
        speculative=ci.shape[0] - touching,
        residual=float(residual),
        max_overlap=gap_max,
        max_overlap_fraction=frac_max,
        iterations=int(sweeps),
        active=int(active),
        rounds=rounds,
    )


def rest_stop(p: Parameters, bodies: Bodies) -> float:
    """The largest velocity change at any contact point (m/s) that stops this step's solve:
    ``p.rest_tolerance`` while no body moves, else 0 (no such stop). A moving blade drives the
    bed, and its pushes are solved as they were measured, to ``p.iterations`` (or
    ``p.tolerance``); a bed left to itself settles within a few sweeps a step. The stop is on
    the largest change, not the RMS: an RMS over a settled bed's contacts hides the few grains
    still rolling, and the bed crept (BENCHMARKS.md, "A resting bed solved to a tolerance")."""
    if bodies.vel.any() or bodies.ang.any():
        return 0.0
    return p.rest_tolerance


def _solve_awake(
    state: WorldState,
    bodies: Bodies,
    p: Parameters,
    cells: np.ndarray,
    start: np.ndarray,
    dims: np.ndarray,
    reach: np.ndarray,
    slab: np.ndarray,
    n_slabs: int,
    rot: np.ndarray,
    body_reach: np.ndarray,
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, tuple[float, int, float], float, int, int, float
]:
    """Detect, assemble and solve the contacts of the awake spheres (all of them without the
    active zone), gravity applied to them; velocities updated in place. Returns i, j, the
    contact table, the multipliers, :func:`_check_overlap`'s figures, the residual (m/s), the
    sweeps run, the ``relinearize`` rounds run and, with the active zone, the largest overlap
    over the smaller radius a pair reaches by the end of the step (:func:`solver.deepest_end`;
    0 without it)."""
    h = p.dt
    invm = 1.0 / state.m
    invI = 1.0 / (0.4 * state.m * state.r**2)
    awake = None
    if p.active_zone:
        awake = state.awake
        # a sleeping sphere is a fixed obstacle to the awake ones: infinite mass and inertia
        invm = invm * state.awake
        invI = invI * state.awake
    # pairs of two sleeping spheres, and their contacts with bodies, are left out: neither
    # side moves, so the step has nothing to solve there (the warm start keeps their impulses)
    pairs = broadphase.sphere_pairs(state.x, state.r, reach, cells, start, dims, awake)
    hits = contacts.body_contacts(
        state.x,
        state.r,
        body_reach,
        bodies.kind,
        bodies.center,
        rot,
        bodies.half,
        bodies.normal,
        awake,
    )
    nu = p.poisson_ratio
    estar = p.youngs_modulus / (2.0 * (1.0 - nu * nu))
    soft = p.sleeper_compliance if p.active_zone else 1.0
    upsilon = 1.0 / (1.0 + 4.0 * p.damping_steps)
    ci, cj, cd, gap, gstart = contacts.assemble(
        *pairs,
        *hits,
        slab,
        n_slabs,
        state.awake,
        state.x,
        state.v,
        state.r,
        invm,
        invI,
        state.mu,
        state.mur,
        bodies.center,
        bodies.vel,
        bodies.ang,
        bodies.mu,
        h,
        upsilon,
        estar,
        soft,
    )
    overlap = _check_overlap(state, p, ci, cj, gap)
    if p.active_zone:
        state.v[state.awake] += h * p.gravity
    else:
        state.v += h * p.gravity
    if p.warm_start:
        lam = state.warm.lookup(
            state.id, ci, cj, cd[:, contacts.N0 : contacts.N0 + 3], p.spinning_resistance > 0.0
        )
    else:
        lam = np.zeros((ci.shape[0], 7))
    largest = rest_stop(p, bodies)
    with _serial_if(ci.shape[0] < PARALLEL_MIN_CONTACTS):
        residual, sweeps = solver.solve(
            ci,
            cj,
            cd,
            lam,
            state.v,
            state.w,
            invm,
            invI,
            gstart,
            n_slabs,
            p.iterations,
            p.warm_start,
            METHODS.index(p.method),
            p.tolerance,
            p.relaxation,
            p.spinning_resistance,
            largest,
        )
        swept = int(gstart[2 * n_slabs])
        rounds = p.relinearize if estar > 0.0 else 0
        if rounds and p.relinearize_above > 0.0:
            deepest = solver.deepest_end(ci, cj, cd, gap, state.v, state.r, h, swept)
            rounds = rounds if deepest > p.relinearize_above else 0
        ran = 0
        for _ in range(rounds):
            stiffened = solver.stiffen(
                ci, cj, cd, gap, state.v, state.r, estar, h, upsilon, swept, state.awake, soft
            )
            if stiffened == 0:
                break
            residual, more = solver.solve(
                *(ci, cj, cd, lam, state.v, state.w, invm, invI, gstart, n_slabs, p.iterations),
                *(False, METHODS.index(p.method), p.tolerance, p.relaxation),
                p.spinning_resistance,
                largest,
            )
            sweeps += more
            ran += 1
    # where the active zone's woken sleepers would have the step solved again (_advance)
    deepest = (
        solver.deepest_end(ci, cj, cd, gap, state.v, state.r, h, swept, False)
        if awake is not None
        else 0.0
    )
    return ci, cj, cd, lam, overlap, float(residual), int(sweeps), ran, float(deepest)


@njit(cache=True)
def _wake_zone(awake, rest, x, v, w, r, reach, zone_body, kind, center, rot, half, normal, margin):
    """Wake, in place, the sleeping spheres the zone reaches or whose velocity was set; returns
    which spheres lie in the zone (N,) bool.

    A sphere is in the zone when it lies within ``margin`` (m), or within its body-contact
    ``reach`` (N,) m, of a body with ``zone_body`` (the blade). A sleeping sphere's velocities
    are zero, so a nonzero one was set from outside and wakes it too.
    """
    n = x.shape[0]
    zone = np.zeros(n, dtype=np.bool_)
    for i in range(n):
        for b in range(kind.shape[0]):
            if zone_body[b]:
                m = max(margin, reach[i])
                g = _body_test(x[i], r[i], m, kind[b], center[b], rot[b], half[b], normal[b])[0]
                if g > -m:
                    zone[i] = True
        moved = False
        if not awake[i]:
            for a in range(3):
                moved = moved or v[i, a] != 0.0 or w[i, a] != 0.0
        if zone[i] or moved:
            awake[i] = True
            rest[i] = 0.0
    return zone


@njit(cache=True)
def _wake_loaded(awake, rest, ci, cj, lam, held):
    """Wake, in place, the sleeping spheres whose contacts with awake spheres carry normal
    impulses ``lam[:, 0]`` (N·s) summing to more than ``held`` (N,) N·s, those of its contacts
    with other sleepers and bodies, which hold it still; returns how many woke. At rest the
    awake grains lean on a sleeper no harder than its resting contacts hold it; a pile pushing
    into it, or a grain jammed between it and the blade, outgrows them."""
    n = awake.shape[0]
    pushed = np.zeros(n)
    for k in range(ci.shape[0]):
        i, j = ci[k], cj[k]
        if j >= 0 and awake[i] != awake[j]:
            pushed[j if awake[i] else i] += lam[k, 0]
    count = 0
    for i in range(n):
        if not awake[i] and pushed[i] > held[i]:
            awake[i] = True
            rest[i] = 0.0
            count += 1
    return count


@njit(cache=True)
def _wake_touched(awake, rest, ci, cj, v, speed):
    """Wake, in place, the sleeping spheres that a contact row of this step joins to an awake
    sphere moving faster than ``speed`` (m/s) after the solve; they move from the next step on.
    """
    n = awake.shape[0]
    hit = np.zeros(n, dtype=np.bool_)
    s2 = speed * speed
    for k in range(ci.shape[0]):
        i, j = ci[k], cj[k]
        if j < 0 or awake[i] == awake[j]:
            continue
        a, b = (i, j) if awake[i] else (j, i)
        if v[a, 0] * v[a, 0] + v[a, 1] * v[a, 1] + v[a, 2] * v[a, 2] > s2:
            hit[b] = True
    for i in range(n):
        if hit[i]:
            awake[i] = True
            rest[i] = 0.0


@njit(cache=True)
def _settle(awake, rest, zone, v, w, r, h, speed, rest_time):
    """Put to sleep, in place, the awake spheres outside the ``zone`` that have moved slower
    than ``speed`` (m/s, centre and spin at the surface) for ``rest_time`` (s), their velocities
    zeroed; ``h`` is the step (s). Returns the spheres awake."""
    s2 = speed * speed
    count = 0
    for i in range(awake.shape[0]):
        if not awake[i]:
            continue
        vv = v[i, 0] * v[i, 0] + v[i, 1] * v[i, 1] + v[i, 2] * v[i, 2]
        ww = (w[i, 0] * w[i, 0] + w[i, 1] * w[i, 1] + w[i, 2] * w[i, 2]) * r[i] * r[i]
        if zone[i] or vv > s2 or ww > s2:
            rest[i] = 0.0
        else:
            rest[i] += h
        if rest[i] >= rest_time and rest[i] > 0.0:
            awake[i] = False
            for a in range(3):
                v[i, a] = 0.0
                w[i, a] = 0.0
        else:
            count += 1
    return count


@njit(cache=True)
def _overlaps(r, ci, cj, gap):
    """One pass over the contacts: (first contact with the largest overlap over the smaller
    radius, or -1; that fraction, 0 if none; contacts with gap > 0; largest gap, m, ≥ 0).
    A NaN is the largest (as numpy's max and argmax take it)."""
    k_max, f_max, touching, g_max = -1, 0.0, 0, 0.0
    for k in range(ci.shape[0]):
        i, j, g = ci[k], cj[k], gap[k]
        rmin = min(r[i], r[j]) if j >= 0 else r[i]
        f = np.maximum(g, 0.0) / rmin
        if f_max == f_max and (k_max < 0 or f > f_max or f != f):
            k_max, f_max = k, f
        if g > 0.0:
            touching += 1
        if g_max == g_max and not g <= g_max:
            g_max = g
    return k_max, f_max, touching, g_max


def _check_overlap(
    state: WorldState, p: Parameters, ci: np.ndarray, cj: np.ndarray, gap: np.ndarray
) -> tuple[float, int, float]:
    """The largest overlap over the smaller radius, the touching contacts and the largest
    overlap (m); DivergenceError when an overlap exceeds max_overlap of the smaller radius."""
    k, frac_max, touching, gap_max = _overlaps(state.r, ci, cj, gap)
    if k < 0 or frac_max <= p.max_overlap:
        return float(frac_max), int(touching), float(gap_max)
    other = f"sphere {state.id[cj[k]]}" if cj[k] >= 0 else f"body {-cj[k] - 1}"
    raise DivergenceError(
        f"overlap {gap[k]:.4g} m = {frac_max:.3g} of the smaller radius between sphere "
        f"{state.id[ci[k]]} and {other} exceeds max_overlap = {p.max_overlap} at step "
        f"{state.step_count + 1} (t = {state.time:.6g} s)"
    )


def _raise_non_finite(state: WorldState, when: str) -> None:
    bad = state.id[~np.all(np.isfinite(np.hstack([state.x, state.v, state.w])), axis=1)]
    raise DivergenceError(
        f"non-finite sphere state (NaN or inf) {when} step {state.step_count + 1} "
        f"(t = {state.time:.6g} s): {bad.size} spheres, ids {np.sort(bad)[:10].tolist()}"
    )
