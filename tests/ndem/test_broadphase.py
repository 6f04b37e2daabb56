"""The broad phase: the grid, the counting sort, the pairs and the slabs."""

import numpy as np
import pytest

from dozerlab.ndem.broadphase import (
    bounds,
    cell_indices,
    counting_sort,
    grid_layout,
    pairs_parallel,
    pairs_serial,
    slab_partition,
    sphere_pairs,
)


def test_grid_cells_are_twice_the_reach_until_the_cell_cap():
    pos = np.array([[0.0, 0.0, 0.0], [0.95, 0.45, 0.25]])
    lo, cell, dims = grid_layout(pos, 0.05, 10**6)
    assert cell == 0.1 and dims.tolist() == [10, 5, 3]
    cells = cell_indices(pos, lo, cell, dims)
    assert cells.tolist() == [0, (9 * 5 + 4) * 3 + 2]  # x-major; the far corner in the last cell
    # at most 10 cells: 0.1 m (150 cells) → 0.15 (42) → 0.225 (20) → 0.3375 m (3 × 2 × 1)
    _, coarse, dims = grid_layout(pos, 0.05, 10)
    assert coarse == pytest.approx(0.1 * 1.5**3) and dims.tolist() == [3, 2, 1]


def test_bounds_are_numpys_min_and_max_and_refuse_no_points():
    pos = np.random.default_rng(4).normal(size=(50, 3))
    lo, hi = bounds(pos)
    np.testing.assert_array_equal(lo, pos.min(axis=0))
    np.testing.assert_array_equal(hi, pos.max(axis=0))
    pos[10, 1] = np.nan
    lo, hi = bounds(pos)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and lo[0] == pos[:, 0].min()
    with pytest.raises(ValueError, match="empty"):
        bounds(pos[:0])


def test_counting_sort_is_stable_with_offsets():
    keys = np.array([2, 0, 2, 1, 0], dtype=np.int64)
    perm, start = counting_sort(keys, 4)
    assert perm.tolist() == np.argsort(keys, kind="stable").tolist()
    assert start.tolist() == [0, 2, 3, 5, 5]


def _sorted(pos: np.ndarray, reach: float):
    lo, cell, dims = grid_layout(pos, reach, 10**6)
    cells = cell_indices(pos, lo, cell, dims)
    perm, start = counting_sort(cells, int(np.prod(dims)))
    return pos[perm], cells[perm], start, dims


def test_pairs_are_every_pair_within_reach_once():
    rng = np.random.default_rng(0)
    pos, cells, start, dims = _sorted(rng.uniform(0, 1, (300, 3)), 0.06)
    radii = rng.uniform(0.03, 0.05, 300)
    reach = radii + 0.01
    pi, pj, nrm, gap = sphere_pairs(pos, radii, reach, cells, start, dims)
    d = np.linalg.norm(pos[:, None] - pos[None], axis=-1)
    i, j = np.nonzero(np.triu(d < reach[:, None] + reach[None], k=1))
    assert sorted(zip(pi.tolist(), pj.tolist(), strict=True)) == sorted(
        zip(i.tolist(), j.tolist(), strict=True)
    )
    assert np.all(pj > pi)
    dist = np.linalg.norm(pos[pi] - pos[pj], axis=1)
    np.testing.assert_allclose(gap, radii[pi] + radii[pj] - dist)
    np.testing.assert_allclose(nrm, (pos[pi] - pos[pj]) / dist[:, None])  # from j to i


def test_pairs_of_two_sleeping_spheres_are_skipped():
    rng = np.random.default_rng(2)
    pos, cells, start, dims = _sorted(rng.uniform(0, 1, (300, 3)), 0.06)
    radii = rng.uniform(0.03, 0.05, 300)
    reach = radii + 0.01
    awake = rng.uniform(size=300) < 0.3
    every = sphere_pairs(pos, radii, reach, cells, start, dims)
    some = sphere_pairs(pos, radii, reach, cells, start, dims, awake)
    keep = awake[every[0]] | awake[every[1]]
    assert 0 < keep.sum() < keep.size
    for a, b in zip(some, every, strict=True):
        np.testing.assert_array_equal(a, b[keep])  # the rest, in the same order


@pytest.mark.parametrize("capacity", [1, 7, 10**5])
def test_one_pass_pairs_equal_count_then_fill_whatever_the_first_buffer(capacity):
    # capacity 1 and 7 overflow (the buffers double and the scan restarts), 10**5 does not
    rng = np.random.default_rng(1)
    pos, cells, start, dims = _sorted(rng.uniform(0, 1, (400, 3)), 0.06)
    radii = rng.uniform(0.03, 0.05, 400)
    reach = radii + 0.01
    awake = rng.uniform(size=400) < 0.5
    serial = pairs_serial(pos, radii, reach, cells, start, dims, awake, capacity)
    parallel = pairs_parallel(pos, radii, reach, cells, start, dims, awake)
    assert serial[0].size > 100
    for a, b in zip(serial, parallel, strict=True):
        np.testing.assert_array_equal(a, b)  # same pairs, same order, same bits


def test_slabs_are_consecutive_whole_columns_balancing_particles():
    dims = np.array([6, 1, 1])
    start = np.array([0, 10, 20, 30, 40, 50, 60])  # ten particles per x-column
    assert slab_partition(start, dims, 3).tolist() == [0, 0, 1, 1, 2, 2]
    assert slab_partition(start, dims, 100).tolist() == [0, 1, 2, 3, 4, 5]
    uneven = np.array([0, 0, 0, 30, 30, 60, 60])  # 30 particles in columns 2 and 4 only
    assert slab_partition(uneven, dims, 2).tolist() == [0, 0, 0, 1, 1, 1]  # 30 a slab
