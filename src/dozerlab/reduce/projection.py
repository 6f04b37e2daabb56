"""Position projection (PBD, SPEC §9): push overlapping spheres apart and out of the bodies.

A contact is a sphere pair (i, j) or a sphere and a static/kinematic body (plane or box). Each
iteration moves the spheres so that every overlapping contact is resolved exactly along its
normal (less an allowed ``slop``, see :func:`project`), split by inverse mass: Δx_i = +g w_i/(w_i + w_j) n, Δx_j = −g w_j/(w_i + w_j) n, so a
pair's centre of mass does not move; a body takes nothing (infinite mass). A sphere with inverse
mass 0 (a frozen grain) is an obstacle like a body.

Two schemes: ``gauss_seidel`` applies each correction at once (serial, converges fastest);
``jacobi`` gathers every sphere's corrections, then moves it by their average times the
relaxation factor (Macklin et al. 2014's "local" averaging: order-free and robust). Candidate
contacts come once per call from the NDEM broad phase and narrow phase
(:mod:`dozerlab.ndem.broadphase`, :func:`dozerlab.ndem.contacts.body_contacts`) with a margin,
and are re-tested every iteration. A last pass pushes every sphere fully out of the bodies, so no
sphere ends inside the ground, a wall or the blade whatever the iteration count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from dozerlab.ndem import broadphase
from dozerlab.ndem.contacts import _body_test, body_contacts

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
def _pair_gap(x, radii, i, j):  # pragma: no cover - compiled
    d0 = x[i, 0] - x[j, 0]
    d1 = x[i, 1] - x[j, 1]
    d2 = x[i, 2] - x[j, 2]
    dist = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    if dist > 0.0:
        return radii[i] + radii[j] - dist, d0 / dist, d1 / dist, d2 / dist
    return radii[i] + radii[j], 0.0, 0.0, 1.0


@njit(cache=True)
def _iterate(
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
    gauss_seidel,
    relaxation,
    slop,
):  # pragma: no cover - compiled
    """``iterations`` sweeps over the candidate contacts, moving ``x`` (N, 3) in place."""
    n = x.shape[0]
    dx = np.zeros((n, 3))
    count = np.zeros(n)
    zero = np.zeros(n)
    for _ in range(iterations):
        if not gauss_seidel:
            dx[:] = 0.0
            count[:] = 0.0
        for k in range(pi.shape[0]):
            i, j = pi[k], pj[k]
            wsum = inv_m[i] + inv_m[j]
            if wsum <= 0.0:
                continue
            g, n0, n1, n2 = _pair_gap(x, radii, i, j)
            g -= slop * min(radii[i], radii[j])
            if g <= 0.0:
                continue
            si, sj = g * inv_m[i] / wsum, g * inv_m[j] / wsum
            # Gauss-Seidel moves the spheres at once, Jacobi gathers the corrections
            out = x if gauss_seidel else dx
            out[i, 0] += si * n0
            out[i, 1] += si * n1
            out[i, 2] += si * n2
            out[j, 0] -= sj * n0
            out[j, 1] -= sj * n1
            out[j, 2] -= sj * n2
            count[i] += 1.0
            count[j] += 1.0
        for k in range(bi.shape[0]):
            i, b = bi[k], bb[k]
            if inv_m[i] <= 0.0:
                continue
            g, n0, n1, n2 = _body_test(
                x[i], radii[i], zero[i], kind[b], bpos[b], brot[b], bext[b], bnormal[b]
            )
            if g <= 0.0:
                continue
            out = x if gauss_seidel else dx
            out[i, 0] += g * n0
            out[i, 1] += g * n1
            out[i, 2] += g * n2
            count[i] += 1.0
        if not gauss_seidel:
            for i in range(n):
                if count[i] > 0.0:
                    s = relaxation / count[i]
                    x[i, 0] += s * dx[i, 0]
                    x[i, 1] += s * dx[i, 1]
                    x[i, 2] += s * dx[i, 2]


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
    """Largest pair overlap over the smaller radius (0 when none overlap)."""
    worst = 0.0
    for k in range(pi.shape[0]):
        g, _, _, _ = _pair_gap(x, radii, pi[k], pj[k])
        if g > 0.0:
            worst = max(worst, g / min(radii[pi[k]], radii[pj[k]]))
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
    penetration before the last push-out (m), and the contact counts."""

    max_overlap: float
    body_depth: float
    pairs: int
    body_contacts: int


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
    margin: float | None = None,
) -> ProjectionStats:
    """Project positions ``x`` (N, 3) m out of overlap in place.

    Args:
        radii: (N,) m. inv_mass: (N,) 1/kg; 0 keeps a sphere in place (an obstacle).
        bodies: the planes and boxes to keep the spheres out of.
        iterations: sweeps over the contacts (>= 0); the final push out of the bodies always runs.
        method: ``gauss_seidel`` or ``jacobi`` (averaged corrections times ``relaxation``).
        slop: pair overlap left alone, as a fraction of the smaller radius (>= 0): a bed settled
            by compliant NDEM contacts holds such overlaps, and undoing them would push it apart.
        margin: contact search margin, m (default: half the smallest radius): contacts that
            close during the projection are caught if they start within it.
    """
    if method not in METHODS:
        raise ValueError(f"projection method must be one of {METHODS}, got {method!r}")
    if iterations < 0:
        raise ValueError(f"projection iterations must be >= 0, got {iterations}")
    x_ = np.ascontiguousarray(x, dtype=np.float64)
    r = np.ascontiguousarray(radii, dtype=np.float64)
    w = np.ascontiguousarray(inv_mass, dtype=np.float64)
    if x_.shape[0] == 0:
        return ProjectionStats(0.0, 0.0, 0, 0)
    m = 0.5 * float(r.min()) if margin is None else float(margin)
    pi, pj = candidate_pairs(x_, r, m)
    movable = np.ascontiguousarray(np.flatnonzero(w > 0.0))
    body_args = (bodies.kind, bodies.centre, bodies.rotation, bodies.half, bodies.normal)
    # bodies are few: a whole radius of margin is cheap and catches grains pushed towards them
    bi, bb, _, _ = body_contacts(x_[movable], r[movable], r[movable] + m, *body_args)
    bi = movable[bi]
    _iterate(
        x_,
        r,
        w,
        pi,
        pj,
        bi,
        bb,
        *body_args,
        int(iterations),
        method == "gauss_seidel",
        float(relaxation),
        float(slop),
    )
    # afresh: the pair corrections may have pushed a sphere into a body it was not near before
    fi, fb, _, _ = body_contacts(x_[movable], r[movable], np.zeros(movable.size), *body_args)
    depth = _push_out_of_bodies(x_, r, movable[fi], fb, *body_args)
    if x_ is not x:
        x[:] = x_
    return ProjectionStats(float(_largest_overlap(x_, r, pi, pj)), float(depth), pi.size, bi.size)
