"""Broad phase: a uniform cell grid rebuilt every step, counting sort, sphere–sphere pairs.

Particles are kept sorted by cell (x-major, then y, then z), so neighbours in space are
neighbours in memory and the contact list comes out ordered the same way. The cell edge is at
least the largest contact distance, so every pair lies in the same or an adjacent cell.
"""

from __future__ import annotations

import numba
import numpy as np
from numba import njit, prange


def grid_layout(
    pos: np.ndarray, reach_max: float, max_cells: int
) -> tuple[np.ndarray, float, np.ndarray]:
    """Origin (3,), cell edge (m) and cell counts (3,) of a grid covering ``pos`` (N, 3).

    The edge starts at ``2·reach_max`` (the largest contact distance) and grows until the grid
    has at most ``max_cells`` cells, so one escaped particle cannot blow up the memory.
    """
    lo, hi = bounds(pos)
    lo -= 1e-9
    extent = hi - lo + 1e-9
    cell = max(2.0 * reach_max, 1e-12)
    while True:
        dims = np.maximum(np.ceil(extent / cell).astype(np.int64), 1)
        if int(np.prod(dims)) <= max_cells:
            return lo, cell, dims
        cell *= 1.5


@njit(cache=True)
def bounds(pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Smallest and largest coordinate (3,) each of ``pos`` (N ≥ 1, 3), as numpy's min and max
    along axis 0 (a NaN wins), in one pass over the rows."""
    if pos.shape[0] == 0:
        raise ValueError("bounds of an empty point set")
    lo = pos[0].copy()
    hi = pos[0].copy()
    for i in range(1, pos.shape[0]):
        for a in range(3):
            v = pos[i, a]
            if lo[a] == lo[a] and (v < lo[a] or v != v):
                lo[a] = v
            if hi[a] == hi[a] and (v > hi[a] or v != v):
                hi[a] = v
    return lo, hi


@njit(cache=True)
def cell_indices(pos: np.ndarray, lo: np.ndarray, cell: float, dims: np.ndarray) -> np.ndarray:
    """Linear cell index (x-major) of every particle, (N,) int64."""
    n = pos.shape[0]
    out = np.empty(n, dtype=np.int64)
    for i in range(n):
        ix = min(int((pos[i, 0] - lo[0]) / cell), dims[0] - 1)
        iy = min(int((pos[i, 1] - lo[1]) / cell), dims[1] - 1)
        iz = min(int((pos[i, 2] - lo[2]) / cell), dims[2] - 1)
        out[i] = (ix * dims[1] + iy) * dims[2] + iz
    return out


@njit(cache=True)
def counting_sort(keys: np.ndarray, nkeys: int) -> tuple[np.ndarray, np.ndarray]:
    """Stable counting sort: ``perm`` (new slot → old slot) and ``start`` (nkeys + 1,) offsets."""
    start = np.zeros(nkeys + 1, dtype=np.int64)
    for k in keys:
        start[k + 1] += 1
    for c in range(nkeys):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    perm = np.empty(keys.shape[0], dtype=np.int64)
    for i in range(keys.shape[0]):
        k = keys[i]
        perm[fill[k]] = i
        fill[k] += 1
    return perm, start


@njit(cache=True)
def _scan_neighbours(
    i, pos, radii, reach, cells, start, dims, awake, woke, out_j, out_n, out_g, base
):
    """Count (``base`` < 0) or write the pairs (i, j > i) of particle i; returns the count.

    A pair of two spheres asleep (``awake`` (N,) False; an empty ``awake``: all awake) is
    skipped: neither moves, so the step has nothing to solve between them. ``woke`` (N + 1,)
    counts the awake spheres before each slot (:func:`_awake_before`), so that a sleeping
    sphere skips whole cell ranges without an awake one.

    Writes go to ``base`` onwards and stop at the end of ``out_j`` (the count goes on), so a
    caller whose buffer was too small sees ``base + count > len(out_j)`` and can retry.
    """
    c = cells[i]
    nyz = dims[1] * dims[2]
    ix = c // nyz
    iy = (c // dims[2]) % dims[1]
    iz = c % dims[2]
    # The three z-neighbouring cells of an (x, y) column are consecutive slots: one range per
    # column. Columns before i's own (x-major) hold only cells < c, whose pairs j < i are
    # found from the other side; i's own column starts after i.
    jz0 = max(iz - 1, 0)
    jz1 = min(iz + 1, dims[2] - 1)
    x0, x1, x2, ri = pos[i, 0], pos[i, 1], pos[i, 2], reach[i]
    i_awake = awake.shape[0] == 0 or awake[i]
    count = 0
    for dx in range(2):
        jx = ix + dx
        if jx >= dims[0]:
            continue
        for dy in range(-1, 2):
            jy = iy + dy
            if jy < 0 or jy >= dims[1] or (dx == 0 and dy < 0):
                continue
            col = (jx * dims[1] + jy) * dims[2]
            j0 = i + 1 if dx == 0 and dy == 0 else start[col + jz0]
            j1 = start[col + jz1 + 1]
            if not i_awake and woke[j1] == woke[j0]:
                continue  # asleep, and nothing awake here: most of a poured bed's scan
            for j in range(j0, j1):
                if not (i_awake or awake[j]):
                    continue
                d0 = x0 - pos[j, 0]
                d1 = x1 - pos[j, 1]
                d2 = x2 - pos[j, 2]
                lim = ri + reach[j]
                d2sum = d0 * d0 + d1 * d1 + d2 * d2
                if d2sum >= lim * lim:
                    continue
                k = base + count
                if base >= 0 and k < out_j.shape[0]:
                    dist = np.sqrt(d2sum)
                    out_j[k] = j
                    if dist > 0.0:
                        out_n[k, 0] = d0 / dist
                        out_n[k, 1] = d1 / dist
                        out_n[k, 2] = d2 / dist
                    else:
                        out_n[k, 0] = 0.0
                        out_n[k, 1] = 0.0
                        out_n[k, 2] = 1.0
                    out_g[k] = radii[i] + radii[j] - dist
                count += 1
    return count


@njit(cache=True)
def _awake_before(awake):
    """(N + 1,) int64: the awake spheres among slots 0..k-1 for every k (an empty ``awake``,
    every sphere awake: empty)."""
    if awake.shape[0] == 0:
        return np.zeros(0, dtype=np.int64)
    out = np.empty(awake.shape[0] + 1, dtype=np.int64)
    out[0] = 0
    for k in range(awake.shape[0]):
        out[k + 1] = out[k] + (1 if awake[k] else 0)
    return out


@njit(cache=True)
def hit_buffers(
    counts: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The second pass of a count-then-fill contact search: from ``counts`` (N + 1,), 0 then
    each sphere's hits, the write offsets (N + 1,) and empty arrays for the M hits: sphere
    (M,), other (M,) int64, normal (M, 3) and overlap (M,) m."""
    offsets = np.cumsum(counts)
    m = offsets[-1]
    return (
        offsets,
        np.empty(m, dtype=np.int64),
        np.empty(m, dtype=np.int64),
        np.empty((m, 3)),
        np.empty(m),
    )


def sphere_pairs(
    pos: np.ndarray,
    radii: np.ndarray,
    reach: np.ndarray,
    cells: np.ndarray,
    start: np.ndarray,
    dims: np.ndarray,
    awake: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """All sphere pairs closer than ``reach_i + reach_j`` (reach ≥ radius, m) in sorted slots,
    but those of two spheres asleep (``awake`` (N,) bool False; None: every sphere awake).

    Returns i (M,), j (M,) with j > i, the unit normal (M, 3) pointing from j to i and the
    overlap g (M,) in m (negative: a gap). Pairs come out ordered by i, then by cell of j.
    On one numba thread the grid is scanned once into a growing buffer; on more, twice (count,
    then fill at known offsets) so the threads can write independently. Both give the same
    arrays.
    """
    mask = np.zeros(0, dtype=np.bool_) if awake is None else awake
    if numba.get_num_threads() == 1:
        return pairs_serial(pos, radii, reach, cells, start, dims, mask, 4 * pos.shape[0] + 64)
    return pairs_parallel(pos, radii, reach, cells, start, dims, mask)


@njit(cache=True)
def pairs_serial(pos, radii, reach, cells, start, dims, awake, capacity):
    """:func:`sphere_pairs` in one pass into buffers of ``capacity`` (≥ 1) pairs, doubled and
    rescanned from the start on the rare overflow."""
    woke = _awake_before(awake)
    while True:
        pi = np.empty(capacity, dtype=np.int64)
        pj = np.empty(capacity, dtype=np.int64)
        nrm = np.empty((capacity, 3))
        gap = np.empty(capacity)
        m = _fill_pairs(pos, radii, reach, cells, start, dims, awake, woke, pi, pj, nrm, gap)
        if m >= 0:
            return pi[:m], pj[:m], nrm[:m], gap[:m]
        capacity *= 2


@njit(cache=True)
def _fill_pairs(pos, radii, reach, cells, start, dims, awake, woke, pi, pj, nrm, gap):
    """Write all pairs into the buffers; returns their number, or -1 if they did not fit."""
    m = 0
    for i in range(pos.shape[0]):
        count = _scan_neighbours(
            i, pos, radii, reach, cells, start, dims, awake, woke, pj, nrm, gap, m
        )
        if m + count > pj.shape[0]:
            return -1
        pi[m : m + count] = i
        m += count
    return m


@njit(parallel=True, cache=True)
def pairs_parallel(pos, radii, reach, cells, start, dims, awake):
    """:func:`sphere_pairs` by count, then fill, each pass over the spheres in parallel."""
    n = pos.shape[0]
    woke = _awake_before(awake)
    dummy_j = np.empty(0, dtype=np.int64)
    dummy_n = np.empty((0, 3))
    dummy_g = np.empty(0)
    counts = np.empty(n + 1, dtype=np.int64)
    counts[0] = 0
    for i in prange(n):
        counts[i + 1] = _scan_neighbours(
            i, pos, radii, reach, cells, start, dims, awake, woke, dummy_j, dummy_n, dummy_g, -1
        )
    offsets, pi, pj, nrm, gap = hit_buffers(counts)
    for i in prange(n):
        _scan_neighbours(
            i, pos, radii, reach, cells, start, dims, awake, woke, pj, nrm, gap, offsets[i]
        )
        for k in range(offsets[i], offsets[i + 1]):
            pi[k] = i
    return pi, pj, nrm, gap


def slab_partition(start: np.ndarray, dims: np.ndarray, n_slabs: int) -> np.ndarray:
    """Slab (0..S-1) of every cell x-column, balancing particle counts; (dims[0],) int64.

    Each slab spans whole x-columns, so a contact joins particles of one slab or of two
    neighbouring slabs — the basis of the parallel sweep.
    """
    nx = int(dims[0])
    per_column = np.diff(start[:: int(dims[1] * dims[2])]) if nx > 0 else np.zeros(0)
    s = max(1, min(n_slabs, nx))
    cum = np.cumsum(per_column)
    total = max(int(cum[-1]), 1)
    slab = np.minimum((cum - per_column) * s // total, s - 1).astype(np.int64)
    # Strictly consecutive slab numbers keep "neighbouring slabs" meaning adjacent columns.
    _, slab = np.unique(slab, return_inverse=True)
    return slab.astype(np.int64)
