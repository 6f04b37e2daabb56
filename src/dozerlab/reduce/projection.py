"""Position projection (position-based dynamics): push overlapping spheres apart and out of the bodies.

A contact is a sphere pair (i, j) or a sphere and a static/kinematic body (plane or box). Each
iteration moves the spheres so that every overlapping contact is resolved exactly along its
normal (less an allowed ``slop``, see :func:`project`), split by inverse mass: Δx_i = +g w_i/(w_i + w_j) n, Δx_j = −g w_j/(w_i + w_j) n, so a
pair's centre of mass does not move; a body takes nothing (infinite mass). A sphere with inverse
mass 0 (a frozen grain) is an obstacle like a body.

Two schemes: ``gauss_seidel`` applies each correction at once (serial, converges fastest);
``jacobi`` gathers every sphere's corrections, then moves it by their average times the
relaxation factor (Macklin et al. 2014's "local" averaging: order-free and robust). The spheres
are sorted by cell and the candidate contacts found once per call with a margin (a serial cell
grid; :func:`dozerlab.ndem.contacts._body_test` for the bodies). Gauss-Seidel re-tests only the
contacts of spheres that moved since their last test, and the sweeps stop early once the largest
correction is within ``tolerance`` (see :func:`project`): most of a step's contacts are a settled
bed's, resolved in the first sweep. A last pass pushes every sphere fully out of the bodies, so
no sphere ends inside the ground, a wall or the blade whatever the iteration count. The largest
overlap reported is every pair's: the list holds every contact while no sphere has moved more
than the margin since it was made, and past that a search around the spheres that did (on the
list's own cell grid) checks, and projects again.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from dozerlab.ndem import broadphase
from dozerlab.ndem.contacts import PLANE, _body_test

METHODS = ("jacobi", "gauss_seidel")


@dataclass(frozen=True)
class Bodies:
    """Planes and boxes as the narrow phase reads them (``dozerlab.ndem.bodies.Bodies`` arrays).

    kind (B,) int64 (0 plane, 1 box); centre (B, 3) m; rotation (B, 3, 3); half extents (B, 3) m;
    plane normal (B, 3).
    """

    kind: np.ndarray
    centre: np.ndarray
    rotation: np.ndarray
    half: np.ndarray
    normal: np.ndarray


@njit(cache=True)
def _pair_overlap(x, radii, i, j):  # pragma: no cover - compiled
    """r_i + r_j − |x_i − x_j| (m) of spheres ``i`` and ``j`` where they overlap, else 0: the
    square root only for the few listed pairs that touch (it was most of the statistic's time)."""
    d0 = x[i, 0] - x[j, 0]
    d1 = x[i, 1] - x[j, 1]
    d2 = x[i, 2] - x[j, 2]
    dd = d0 * d0 + d1 * d1 + d2 * d2
    s = radii[i] + radii[j]
    if dd >= s * s:
        return 0.0
    return s - np.sqrt(dd)


@njit(cache=True)
def _scan_pairs(x, reach, inv_m, start, movable, dims, nxt, pa, pb):  # pragma: no cover - compiled
    """Count the pairs (a, b), a < b, closer than reach_a + reach_b and not both obstacles
    (``inv_m`` 0: the projection leaves such a pair alone), and write them into ``pa``/``pb``
    while the candidates of a run fit: returns the count and whether every pair was written.

    Cell by cell: each cell meets itself and the 13 neighbours after it in x-major order (the
    slots of ``x`` are sorted by cell, so b > a holds across cells by the order itself). Those
    neighbours lie in five runs of slots, three cells along z each (the cell's own run from
    itself up), so a sphere meets each run in one loop: a loop per cell took 14-17 % longer
    (BENCHMARKS.md, "The projection's contact list, cheaper"). Every candidate is written and
    the count advances only for a pair (no branch on the one test in eight that finds one). An obstacle meets no run without a movable sphere (``movable``
    (cells,) counts them): the ring of obstacles is about half of a reduced step's spheres, and
    skipping its cells saved 6-22 % of the scan (BENCHMARKS.md, "... the ring's cells left out
    of the contact search"). In a run with some, an obstacle meets its movable spheres alone,
    from each to the next by ``nxt`` (N + 1,) (the first movable slot at or after each): the
    obstacle-obstacle candidates were 23 % of the trench's, and skipping them took the scan
    of its captured projections from 0.85-0.88 to 0.64-0.71 ms (BENCHMARKS.md, "The loop's
    passes over the grains, lighter").
    """
    k = 0
    complete = True
    nz = dims[2]
    lo_b = np.empty(5, np.int64)
    hi_b = np.empty(5, np.int64)
    mv = np.empty(5, np.int64)
    for cx in range(dims[0]):
        for cy in range(dims[1]):
            row = (cx * dims[1] + cy) * nz
            for cz in range(nz):
                c = row + cz
                if start[c] == start[c + 1]:
                    continue
                z0, z1 = max(cz - 1, 0), min(cz + 1, nz - 1)
                lo_b[0], hi_b[0] = start[c], start[row + z1 + 1]
                mv[0] = movable[c] + (movable[c + 1] if z1 > cz else 0)
                runs = 1
                any_movable = mv[0] > 0
                for ix in range(cx, min(cx + 2, dims[0])):
                    for iy in range(max(cy - 1, 0), min(cy + 2, dims[1])):
                        if ix == cx and iy <= cy:
                            continue
                        r2 = (ix * dims[1] + iy) * nz
                        lo_b[runs], hi_b[runs] = start[r2 + z0], start[r2 + z1 + 1]
                        m = 0
                        for z in range(z0, z1 + 1):
                            m += movable[r2 + z]
                        mv[runs] = m
                        any_movable = any_movable or m > 0
                        runs += 1
                if movable[c] == 0 and not any_movable:
                    continue
                for a in range(start[c], start[c + 1]):
                    xa0, xa1, xa2, ra = x[a, 0], x[a, 1], x[a, 2], reach[a]
                    if inv_m[a] > 0.0:
                        for t in range(runs):
                            b0, b1 = max(lo_b[t], a + 1), hi_b[t]
                            room = k + (b1 - b0) <= pa.size
                            complete = complete and room
                            for b in range(b0, b1):
                                d0 = xa0 - x[b, 0]
                                d1 = xa1 - x[b, 1]
                                d2 = xa2 - x[b, 2]
                                s = ra + reach[b]
                                if room:
                                    pa[k], pb[k] = a, b
                                k += d0 * d0 + d1 * d1 + d2 * d2 < s * s
                        continue
                    for t in range(runs):
                        if mv[t] == 0:
                            continue
                        b1 = hi_b[t]
                        b = nxt[max(lo_b[t], a + 1)]
                        while b < b1:
                            d0 = xa0 - x[b, 0]
                            d1 = xa1 - x[b, 1]
                            d2 = xa2 - x[b, 2]
                            s = ra + reach[b]
                            if d0 * d0 + d1 * d1 + d2 * d2 < s * s:
                                if k < pa.size:
                                    pa[k], pb[k] = a, b
                                else:
                                    complete = False
                                k += 1
                            b = nxt[b + 1]
    return k, complete


@njit(cache=True)
def _next_movable(inv_m):  # pragma: no cover - compiled
    """(N + 1,) for ``inv_m`` (N,): the first slot at or after each whose inverse mass is
    above 0 (N where none is)."""
    n = inv_m.shape[0]
    nxt = np.empty(n + 1, np.int64)
    nxt[n] = n
    for a in range(n - 1, -1, -1):
        nxt[a] = a if inv_m[a] > 0.0 else nxt[a + 1]
    return nxt


@njit(cache=True)
def _by_cell(x, radii, inv_m, lo, cell, dims):  # pragma: no cover - compiled
    """The spheres sorted by cell (x-major, stable) on the grid (lo, cell, dims), in one pass:
    ``perm`` (N,) new slot → old, their positions (N, 3), radii and inverse masses in that order,
    ``start`` (cells + 1,) each cell's first slot and ``movable`` (cells,) the movable spheres
    (``inv_m`` > 0) each cell holds. One compiled pass for what NumPy's gathers and the search's
    own count of the cells did apart."""
    n = x.shape[0]
    cells = broadphase.cell_indices(x, lo, cell, dims)
    perm, start = broadphase.counting_sort(cells, dims[0] * dims[1] * dims[2])
    xs = np.empty((n, 3))
    rs = np.empty(n)
    ws = np.empty(n)
    movable = np.zeros(start.size - 1, np.int64)
    for a in range(n):
        p = perm[a]
        xs[a, 0], xs[a, 1], xs[a, 2] = x[p, 0], x[p, 1], x[p, 2]
        rs[a], ws[a] = radii[p], inv_m[p]
        if inv_m[p] > 0.0:
            movable[cells[p]] += 1
    return perm, xs, rs, ws, start, movable


@njit(cache=True)
def _pairs_sorted(x, reach, inv_m, start, movable, dims):  # pragma: no cover - compiled
    """Pairs (a, b), a < b, of spheres closer than reach_a + reach_b (m), not both obstacles
    (``inv_m`` (N,) 0), in one serial pass.

    ``x`` (N, 3) is sorted by cell (x-major) on a grid of ``dims`` cells, ``start`` and
    ``movable`` as :func:`_by_cell` gives them, so the pairs come out in memory order and a
    Gauss-Seidel sweep over them walks the arrays forward.
    """
    nxt = _next_movable(inv_m)
    pa = np.empty(8 * x.shape[0] + 16, np.int64)
    pb = np.empty_like(pa)
    k, complete = _scan_pairs(x, reach, inv_m, start, movable, dims, nxt, pa, pb)
    if not complete:
        # a packing denser than 8 pairs a sphere (overlapping grains): again, with room for
        # them and for any run's candidates after them
        pa = np.empty(k + x.shape[0], np.int64)
        pb = np.empty_like(pa)
        k, _ = _scan_pairs(x, reach, inv_m, start, movable, dims, nxt, pa, pb)
    return pa[:k], pb[:k]


@njit(cache=True)
def _scatter(x, perm, xs):  # pragma: no cover - compiled
    """x[perm] = xs for ``x`` (N, 3), in one pass."""
    for a in range(perm.shape[0]):
        p = perm[a]
        x[p, 0], x[p, 1], x[p, 2] = xs[a, 0], xs[a, 1], xs[a, 2]


@njit(cache=True)
def _body_candidates(x, radii, inv_m, margin, kind, bpos, brot, bext, bnormal):  # pragma: no cover
    """(sphere, body) pairs of movable spheres within ``margin`` (m) of a body, serial.

    Planes are tested inline (a dot product), boxes only within their bounding sphere.
    """
    n, nb = x.shape[0], kind.shape[0]
    si = np.empty(n * nb, np.int64)
    sb = np.empty(n * nb, np.int64)
    bound = np.zeros(nb)
    for b in range(nb):
        e = bext[b]
        bound[b] = np.sqrt(e[0] * e[0] + e[1] * e[1] + e[2] * e[2])
    k = 0
    for i in range(n):
        if inv_m[i] <= 0.0:
            continue
        x0, x1, x2, ri = x[i, 0], x[i, 1], x[i, 2], radii[i]
        for b in range(nb):
            d0, d1, d2 = x0 - bpos[b, 0], x1 - bpos[b, 1], x2 - bpos[b, 2]
            if kind[b] == PLANE:
                near = ri - (d0 * bnormal[b, 0] + d1 * bnormal[b, 1] + d2 * bnormal[b, 2]) > -margin
            else:
                reach = ri + margin + bound[b]
                near = d0 * d0 + d1 * d1 + d2 * d2 <= reach * reach
                if near:
                    g, _, _, _ = _body_test(
                        x[i], ri, margin, kind[b], bpos[b], brot[b], bext[b], bnormal[b]
                    )
                    near = g > -margin
            if near:
                si[k], sb[k] = i, b
                k += 1
    return si[:k], sb[:k]


def _iterate(
    x: np.ndarray,
    radii: np.ndarray,
    inv_m: np.ndarray,
    pi: np.ndarray,
    pj: np.ndarray,
    bi: np.ndarray,
    bb: np.ndarray,
    kind: np.ndarray,
    bpos: np.ndarray,
    brot: np.ndarray,
    bext: np.ndarray,
    bnormal: np.ndarray,
    iterations: int,
    gauss_seidel: bool,
    relaxation: float,
    slop: float,
    tolerance: float,
    restrict: bool,
    quiet: float,
) -> tuple[int, int]:
    """Up to ``iterations`` sweeps over the candidate contacts (pairs ``pi``/``pj``, body
    contacts ``bi``/``bb``), moving ``x`` (N, 3) m in place.

    Stops after the first sweep whose largest correction is at most ``tolerance`` times the
    smaller radius (a sweep that moves nothing always stops). Gauss-Seidel moves the spheres at
    once, each correction times ``relaxation``; with ``restrict`` it tests a contact only if one
    of its spheres moved since the contact was last tested by a correction larger than
    ``quiet`` times the contact's smaller radius (the sphere's own for a body contact): the
    others are where the last test left them, resolved to the slop, so with ``quiet`` 0
    skipping them gives the full sweep's result to round-off at a fraction of the cost, and
    above 0 the over-relaxed sweeps' ever smaller ripples stop waking whole neighbourhoods.
    Jacobi averages each sphere's corrections of a sweep and applies them times
    ``relaxation``; it tests every contact (its averages depend on every contact's count).
    Returns the sweeps run and the contact tests made.
    """
    bodies = (bi, bb, kind, bpos, brot, bext, bnormal)
    if gauss_seidel:
        return _gauss_seidel(
            x,
            radii,
            inv_m,
            pi,
            pj,
            *bodies,
            iterations,
            relaxation,
            slop,
            tolerance,
            restrict,
            quiet,
        )
    return _jacobi(x, radii, inv_m, pi, pj, *bodies, iterations, relaxation, slop, tolerance)


@njit(cache=True)
def _gauss_seidel(
    x,
    radii,
    inv_m,
    pi,
    pj,
    bi,
    bb,
    kind,
    bpos,
    brot,
    bext,
    bnormal,
    iterations,
    relaxation,
    slop,
    tolerance,
    restrict,
    quiet,
):  # pragma: no cover - compiled
    """:func:`_iterate`'s Gauss-Seidel sweeps, in a loop of their own: the Jacobi branches
    in a shared one, with a call for each body contact, cost 10 % of a sweep's time."""
    n = x.shape[0]
    # the sweep that last moved a sphere; sweep s tests contacts with one stamped >= s - 1
    stamp = np.zeros(n, np.int64)
    sweeps = 0
    tests = 0
    for s in range(1, iterations + 1):
        sweeps = s
        worst = 0.0
        recent = s - 1 if restrict else 0
        for k in range(pi.shape[0]):
            i, j = pi[k], pj[k]
            if stamp[i] < recent and stamp[j] < recent:
                continue
            wsum = inv_m[i] + inv_m[j]
            if wsum <= 0.0:
                continue
            tests += 1
            rmin = min(radii[i], radii[j])
            reach = radii[i] + radii[j] - slop * rmin
            d0 = x[i, 0] - x[j, 0]
            d1 = x[i, 1] - x[j, 1]
            d2 = x[i, 2] - x[j, 2]
            dd = d0 * d0 + d1 * d1 + d2 * d2
            if dd >= reach * reach:  # most tests: apart, no square root needed
                continue
            dist = np.sqrt(dd)
            g = reach - dist
            if dist > 0.0:
                n0, n1, n2 = d0 / dist, d1 / dist, d2 / dist
            else:
                n0, n1, n2 = 0.0, 0.0, 1.0
            worst = max(worst, g / rmin)
            f = relaxation * g / wsum
            si, sj = f * inv_m[i], f * inv_m[j]
            x[i, 0] += si * n0
            x[i, 1] += si * n1
            x[i, 2] += si * n2
            x[j, 0] -= sj * n0
            x[j, 1] -= sj * n1
            x[j, 2] -= sj * n2
            # both, if either moved: the lighter one's ripple alone left 0.097-0.099 radius on
            # two held-out points of the default sweep, stamping both 0.071-0.087
            if max(si, sj) > quiet * rmin:
                if inv_m[i] > 0.0:
                    stamp[i] = s
                if inv_m[j] > 0.0:
                    stamp[j] = s
        for k in range(bi.shape[0]):
            i, b = bi[k], bb[k]
            if inv_m[i] <= 0.0 or stamp[i] < recent:
                continue
            tests += 1
            if kind[b] == PLANE:  # inline (a call here cost the sweeps 10 %): most contacts
                n0, n1, n2 = bnormal[b, 0], bnormal[b, 1], bnormal[b, 2]
                g = radii[i] - (
                    (x[i, 0] - bpos[b, 0]) * n0
                    + (x[i, 1] - bpos[b, 1]) * n1
                    + (x[i, 2] - bpos[b, 2]) * n2
                )
            else:
                g, n0, n1, n2 = _body_test(
                    x[i], radii[i], 0.0, kind[b], bpos[b], brot[b], bext[b], bnormal[b]
                )
            if g <= 0.0:
                continue
            worst = max(worst, g / radii[i])
            x[i, 0] += g * n0
            x[i, 1] += g * n1
            x[i, 2] += g * n2
            if g > quiet * radii[i]:
                stamp[i] = s
        if worst <= tolerance:
            break
    return sweeps, tests


@njit(cache=True)
def _jacobi(
    x,
    radii,
    inv_m,
    pi,
    pj,
    bi,
    bb,
    kind,
    bpos,
    brot,
    bext,
    bnormal,
    iterations,
    relaxation,
    slop,
    tolerance,
):  # pragma: no cover - compiled
    """:func:`_iterate`'s Jacobi sweeps."""
    n = x.shape[0]
    dx = np.zeros((n, 3))
    count = np.zeros(n)
    sweeps = 0
    tests = 0
    for s in range(1, iterations + 1):
        sweeps = s
        worst = 0.0
        dx[:] = 0.0
        count[:] = 0.0
        for k in range(pi.shape[0]):
            i, j = pi[k], pj[k]
            wsum = inv_m[i] + inv_m[j]
            if wsum <= 0.0:
                continue
            tests += 1
            rmin = min(radii[i], radii[j])
            reach = radii[i] + radii[j] - slop * rmin
            d0 = x[i, 0] - x[j, 0]
            d1 = x[i, 1] - x[j, 1]
            d2 = x[i, 2] - x[j, 2]
            dd = d0 * d0 + d1 * d1 + d2 * d2
            if dd >= reach * reach:
                continue
            dist = np.sqrt(dd)
            g = reach - dist
            if dist > 0.0:
                n0, n1, n2 = d0 / dist, d1 / dist, d2 / dist
            else:
                n0, n1, n2 = 0.0, 0.0, 1.0
            worst = max(worst, g / rmin)
            f = g / wsum
            si, sj = f * inv_m[i], f * inv_m[j]
            dx[i, 0] += si * n0
            dx[i, 1] += si * n1
            dx[i, 2] += si * n2
            dx[j, 0] -= sj * n0
            dx[j, 1] -= sj * n1
            dx[j, 2] -= sj * n2
            count[i] += 1.0
            count[j] += 1.0
        for k in range(bi.shape[0]):
            i, b = bi[k], bb[k]
            if inv_m[i] <= 0.0:
                continue
            tests += 1
            if kind[b] == PLANE:  # inline: the ground and walls, most body contacts
                n0, n1, n2 = bnormal[b, 0], bnormal[b, 1], bnormal[b, 2]
                g = radii[i] - (
                    (x[i, 0] - bpos[b, 0]) * n0
                    + (x[i, 1] - bpos[b, 1]) * n1
                    + (x[i, 2] - bpos[b, 2]) * n2
                )
            else:
                g, n0, n1, n2 = _body_test(
                    x[i], radii[i], 0.0, kind[b], bpos[b], brot[b], bext[b], bnormal[b]
                )
            if g <= 0.0:
                continue
            worst = max(worst, g / radii[i])
            dx[i, 0] += g * n0
            dx[i, 1] += g * n1
            dx[i, 2] += g * n2
            count[i] += 1.0
        for i in range(n):
            if count[i] > 0.0:
                c = relaxation / count[i]
                x[i, 0] += c * dx[i, 0]
                x[i, 1] += c * dx[i, 1]
                x[i, 2] += c * dx[i, 2]
        if worst <= tolerance:
            break
    return sweeps, tests


@njit(cache=True)
def _push_out_of_bodies(x, radii, bi, bb, kind, bpos, brot, bext, bnormal):  # pragma: no cover
    """Move each listed sphere fully out of its bodies (a few rounds for corners).

    Returns the deepest penetration (m) the iterations had left.
    """
    zero = 0.0
    first = 0.0
    for rnd in range(4):
        worst = 0.0
        for k in range(bi.shape[0]):
            i, b = bi[k], bb[k]
            g, n0, n1, n2 = _body_test(
                x[i], radii[i], zero, kind[b], bpos[b], brot[b], bext[b], bnormal[b]
            )
            if g > 0.0:
                worst = max(worst, g)
                x[i, 0] += g * n0
                x[i, 1] += g * n1
                x[i, 2] += g * n2
        if rnd == 0:
            first = worst
        if worst == 0.0:
            break
    return first


@njit(cache=True)
def _largest_overlap(x, radii, pi, pj):  # pragma: no cover - compiled
    """Largest overlap over the smaller radius of the pairs ``pi``/``pj`` (0 if none overlaps).

    Every pair's gap is taken, touching or not, and the largest kept: after the sweeps about
    half of the listed pairs touch (at the slop), and a branch on it cost 3.4 times as long
    (BENCHMARKS.md, "The projection's contact list, cheaper").
    """
    worst = 0.0
    for k in range(pi.shape[0]):
        i, j = pi[k], pj[k]
        d0 = x[i, 0] - x[j, 0]
        d1 = x[i, 1] - x[j, 1]
        d2 = x[i, 2] - x[j, 2]
        ri, rj = radii[i], radii[j]
        worst = max(worst, (ri + rj - np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)) / min(ri, rj))
    return worst


def candidate_pairs(x: np.ndarray, radii: np.ndarray, margin: float) -> tuple[np.ndarray, ...]:
    """Sphere pairs (i, j), i < j indices into ``x`` (N, 3), closer than r_i + r_j + 2·margin (m)."""
    n = x.shape[0]
    if n < 2:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    reach = radii + margin
    lo, cell, dims = broadphase.grid_layout(x, float(reach.max()), max(8 * n, 4096))
    cells = broadphase.cell_indices(x, lo, cell, dims)
    perm, start = broadphase.counting_sort(cells, int(np.prod(dims)))
    pi, pj, _, _ = broadphase.sphere_pairs(
        np.ascontiguousarray(x[perm]), radii[perm], reach[perm], cells[perm], start, dims
    )
    return perm[pi], perm[pj]


@dataclass
class ProjectionStats:
    """What a projection left: largest pair overlap over the smaller radius, deepest body
    penetration before the last push-out (m), the contact counts, the sweeps run (at most the
    iterations asked for) and the contact tests they made."""

    max_overlap: float
    body_depth: float
    pairs: int
    body_contacts: int
    sweeps: int = 0
    tests: int = 0


def project(
    x: np.ndarray,
    radii: np.ndarray,
    inv_mass: np.ndarray,
    bodies: Bodies,
    *,
    iterations: int,
    method: str = "gauss_seidel",
    relaxation: float = 1.0,
    slop: float = 0.0,
    tolerance: float = 0.0,
    overlap_limit: float = np.inf,
    margin: float | None = None,
) -> ProjectionStats:
    """Project positions ``x`` (N, 3) m out of overlap in place.

    Args:
        radii: (N,) m. inv_mass: (N,) 1/kg; 0 keeps a sphere in place (an obstacle).
        bodies: the planes and boxes to keep the spheres out of.
        iterations: the most sweeps over the contacts (>= 0); the final push out of the bodies
            always runs.
        method: ``gauss_seidel`` or ``jacobi`` (averaged corrections times ``relaxation``).
        relaxation: the factor on each correction (Jacobi: on the averaged ones; Gauss-Seidel:
            on the pair corrections, over-relaxation above 1).
        slop: pair overlap left alone, as a fraction of the smaller radius (>= 0): a bed settled
            by compliant NDEM contacts holds such overlaps, and undoing it would push it apart.
        tolerance: the sweeps stop after one whose largest correction is at most this fraction
            of the smaller radius (>= 0; 0: only once a sweep corrects nothing); a sphere moved
            by less than ``QUIET`` times it does not send its contacts to be tested again.
        overlap_limit: a round whose sweeps leave a larger overlap (fraction of the smaller
            radius; they ran out of ``iterations``) is followed by another, up to ``ROUNDS``.
        margin: contact search margin, m (default: ``MARGIN`` times the smallest radius):
            contacts that close during the projection are caught if they start within it; a
            sphere moved further sends the projection to a search around it (and to another
            round, up to ``ROUNDS``, where that finds a deeper overlap).

    Returns the stats; ``max_overlap`` covers every pair with a movable sphere.
    """
    if method not in METHODS:
        raise ValueError(f"projection method must be one of {METHODS}, got {method!r}")
    if iterations < 0:
        raise ValueError(f"projection iterations must be >= 0, got {iterations}")
    if tolerance < 0:
        raise ValueError(f"projection tolerance must be >= 0, got {tolerance}")
    if not overlap_limit > 0:
        raise ValueError(f"projection overlap_limit must be > 0, got {overlap_limit}")
    if x.shape[0] == 0:
        return ProjectionStats(0.0, 0.0, 0, 0)
    r0 = np.asarray(radii, dtype=np.float64)
    w0 = np.asarray(inv_mass, dtype=np.float64)
    m = MARGIN * float(r0.min()) if margin is None else float(margin)
    settings = (int(iterations), method == "gauss_seidel", float(relaxation), float(slop))
    total = ProjectionStats(0.0, 0.0, 0, 0)
    previous = np.inf
    for _ in range(ROUNDS):
        start = np.array(x, dtype=np.float64)
        total.max_overlap, st, grid = _round(x, r0, w0, m, bodies, *settings, float(tolerance))
        total.body_depth = max(total.body_depth, st.body_depth)
        total.pairs, total.body_contacts = st.pairs, st.body_contacts
        total.sweeps += st.sweeps
        total.tests += st.tests
        # The list holds every pair closer than r_i + r_j + 2·margin when it was made: a pair
        # left out of it can have closed since (sweeps and push-out) only if one of its spheres
        # moved more than the margin. Search afresh around those, and project again if a
        # contact closed unlisted (searching around every sphere cost 19 % of the projection
        # at 1.5 m/s, where some sphere moved that far in nearly every step; BENCHMARKS.md).
        far = _moved_beyond(x, start, m)
        if far.size:
            fresh = _largest_overlap_around(x, r0, w0, far, grid)
            if fresh > total.max_overlap:
                total.max_overlap = fresh
                continue
        if total.max_overlap <= overlap_limit:
            break
        if total.max_overlap > STALLED * previous:
            # This round left the overlap above the limit where the last round had: a grain
            # caged by obstacles stays caged, whatever the rounds, and the caller handles it (on hill 1.5 / 0.06 a third round of each of four such steps
            # left 0.10-0.53 radius as the second had, 4-6 ms a round; BENCHMARKS.md, "A
            # caged grain's projection ends after two rounds").
            break
        previous = total.max_overlap
    return total


@njit(cache=True)
def _moved_beyond(x, start, distance):  # pragma: no cover - compiled
    """Indices (K,) of the rows of ``x`` (N, 3) more than ``distance`` (m) from ``start``."""
    d2 = distance * distance
    out = np.empty(x.shape[0], np.int64)
    k = 0
    for i in range(x.shape[0]):
        d0, d1, d2i = x[i, 0] - start[i, 0], x[i, 1] - start[i, 1], x[i, 2] - start[i, 2]
        if d0 * d0 + d1 * d1 + d2i * d2i > d2:
            out[k] = i
            k += 1
    return out[:k]


@njit(cache=True)
def _overlap_around(x, radii, inv_m, which, lo, cell, dims, order, start):  # pragma: no cover
    """Largest overlap over the smaller radius of the pairs of a sphere of ``which`` with any
    other, at least one of the two movable: the others from the 27 cells around its cell of
    the grid (``lo``, ``cell``, ``dims``; ``order``/``start`` the spheres by cell, placed where
    they were when it was made), those of ``which`` each with each."""
    worst = 0.0
    for s in range(which.size):
        a = which[s]
        ca = np.empty(3, np.int64)
        for d in range(3):
            ca[d] = min(max(int((x[a, d] - lo[d]) / cell), 0), dims[d] - 1)
        for ix in range(max(ca[0] - 1, 0), min(ca[0] + 2, dims[0])):
            for iy in range(max(ca[1] - 1, 0), min(ca[1] + 2, dims[1])):
                for iz in range(max(ca[2] - 1, 0), min(ca[2] + 2, dims[2])):
                    c = (ix * dims[1] + iy) * dims[2] + iz
                    for t in range(start[c], start[c + 1]):
                        b = order[t]
                        if b == a or (inv_m[a] <= 0.0 and inv_m[b] <= 0.0):
                            continue
                        g = _pair_overlap(x, radii, a, b)
                        if g > 0.0:
                            worst = max(worst, g / min(radii[a], radii[b]))
        for t in range(s + 1, which.size):
            b = which[t]
            if inv_m[a] <= 0.0 and inv_m[b] <= 0.0:
                continue
            g = _pair_overlap(x, radii, a, b)
            if g > 0.0:
                worst = max(worst, g / min(radii[a], radii[b]))
    return worst


@dataclass(frozen=True)
class CellGrid:
    """Spheres sorted by the cells of a grid where they stood: origin ``lo`` (3,) m, cell edge
    ``cell`` m, cell counts ``dims`` (3,), ``order`` (N,) slot → sphere, ``start`` (cells + 1,)
    each cell's first slot."""

    lo: np.ndarray
    cell: float
    dims: np.ndarray
    order: np.ndarray
    start: np.ndarray


def _largest_overlap_around(
    x: np.ndarray, radii: np.ndarray, inv_mass: np.ndarray, which: np.ndarray, grid: CellGrid
) -> float:
    """:func:`largest_movable_overlap` over the pairs with a sphere of ``which`` (K,) indices
    into ``x`` (N, 3) m, searched around those spheres alone (0 when none overlap).

    ``grid`` sorts the spheres where they stood before they moved; every sphere but those of
    ``which`` has moved at most cell/2 − max radius since, so a sphere touching one of
    ``which`` now stood within a cell of it (the projection's round grid, cells of twice the
    largest radius plus margin, and its margin: a fresh grid of every sphere cost as much as
    the rest of the search; BENCHMARKS.md, "The projection's contact list, cheaper").
    """
    return float(
        _overlap_around(
            x, radii, inv_mass, which, grid.lo, grid.cell, grid.dims, grid.order, grid.start
        )
    )


#: A correction smaller than this share of ``tolerance`` (times the radius) does not send a
#: sphere's contacts to be tested again: the over-relaxed sweeps' ripples that small made about
#: half of a step's contact tests on the default sweep's held-out points (BENCHMARKS.md,
#: "Contacts left alone after a ripple"). A tolerance of 0 tests after every move.
QUIET = 0.1

#: The contact search's margin, as a share of the smallest radius (see :func:`project`): with
#: 0.35 the ridge's loop projected in 0.85-1.02 of the time it took with 0.5 (fewer pairs to
#: list and to test in the first sweep), with 0.3 in 0.89-1.09 (more rounds); BENCHMARKS.md,
#: "The projection's contact list, cheaper".
MARGIN = 0.35

#: Projection rounds at most (each a contact search, sweeps and push-out): a round more runs
#: only when a fresh search finds a contact overlapping more than the last round's list holds,
#: or when the sweeps ran out with an overlap above ``overlap_limit`` and below ``STALLED``
#: times the round's before.
ROUNDS = 3

#: A round whose sweeps run out above ``overlap_limit`` with the largest overlap above this
#: share of the last round's ends the projection: the rounds no longer move it.
STALLED = 0.95


def _round(
    x: np.ndarray,
    r0: np.ndarray,
    w0: np.ndarray,
    m: float,
    bodies: Bodies,
    iterations: int,
    gauss_seidel: bool,
    relaxation: float,
    slop: float,
    tolerance: float,
) -> tuple[float, ProjectionStats, CellGrid]:
    """One contact search, the sweeps and the push out of the bodies on ``x`` in place.

    Returns the largest overlap over the listed pairs, the round's stats and its grid (the
    spheres where the round found them).
    """
    body_args = (bodies.kind, bodies.centre, bodies.rotation, bodies.half, bodies.normal)
    # sorted by cell: the sweeps walk memory forward (spatial order keeps the sweeps in cache)
    lo, cell, dims = broadphase.grid_layout(x, float(r0.max()) + m, max(8 * x.shape[0], 4096))
    perm, x_, r, w, start, movable = _by_cell(x, r0, w0, lo, cell, dims)
    pi, pj = _pairs_sorted(x_, r + m, w, start, movable, dims)
    # bodies are few: a whole radius of margin is cheap and catches grains pushed towards them
    bi, bb = _body_candidates(x_, r, w, float(r.max()) + m, *body_args)
    sweeps, tests = _iterate(
        x_,
        r,
        w,
        pi,
        pj,
        bi,
        bb,
        *body_args,
        iterations,
        gauss_seidel,
        relaxation,
        slop,
        tolerance,
        True,
        QUIET * tolerance,
    )
    # afresh: the pair corrections may have pushed a sphere into a body it was not near before
    fi, fb = _body_candidates(x_, r, w, 0.0, *body_args)
    depth = _push_out_of_bodies(x_, r, fi, fb, *body_args)
    _scatter(x, perm, x_)
    # the list holds no pair of two obstacles (their overlaps are not the projection's)
    listed = float(_largest_overlap(x_, r, pi, pj))
    stats = ProjectionStats(listed, float(depth), pi.size, bi.size, sweeps, tests)
    return listed, stats, CellGrid(lo, cell, dims, perm, start)


def spheres_near(x: np.ndarray, radii: np.ndarray, bodies: Bodies, margin: float) -> np.ndarray:
    """Indices (K,) ascending of the spheres of ``x`` (N, 3) m, ``radii`` (N,) m whose surface
    lies within ``margin`` (m) of any of ``bodies``."""
    n = x.shape[0]
    si, _ = _body_candidates(
        np.ascontiguousarray(x, dtype=np.float64),
        np.ascontiguousarray(radii, dtype=np.float64),
        np.ones(n),
        float(margin),
        bodies.kind,
        bodies.centre,
        bodies.rotation,
        bodies.half,
        bodies.normal,
    )
    return np.unique(si)


def overlapping(x: np.ndarray, radii: np.ndarray, inv_mass: np.ndarray, limit: float) -> np.ndarray:
    """(N,) bool: the spheres of ``x`` (N, 3) m, ``radii`` (N,) m in a pair with a movable
    sphere (``inv_mass`` (N,) > 0) that overlaps by more than ``limit`` times the smaller
    radius (a fresh contact search): both of the pair."""
    pi, pj = candidate_pairs(x, radii, 0.0)
    gap = radii[pi] + radii[pj] - np.linalg.norm(x[pi] - x[pj], axis=1)
    deep = (gap > limit * np.minimum(radii[pi], radii[pj])) & (
        (inv_mass[pi] > 0.0) | (inv_mass[pj] > 0.0)
    )
    out = np.zeros(x.shape[0], bool)
    out[pi[deep]] = True
    out[pj[deep]] = True
    return out


def largest_movable_overlap(x: np.ndarray, radii: np.ndarray, inv_mass: np.ndarray) -> float:
    """Largest overlap over the smaller radius of the pairs of ``x`` (N, 3) m with a movable
    sphere (inv_mass > 0), by a fresh contact search (0 when none overlap). Pairs of two
    obstacles are left out: the projection cannot change them."""
    pi, pj = candidate_pairs(x, radii, 0.0)
    keep = (inv_mass[pi] > 0.0) | (inv_mass[pj] > 0.0)
    pi, pj = pi[keep], pj[keep]
    if pi.size == 0:
        return 0.0
    gap = radii[pi] + radii[pj] - np.linalg.norm(x[pi] - x[pj], axis=1)
    return float(max(0.0, (gap / np.minimum(radii[pi], radii[pj])).max()))
