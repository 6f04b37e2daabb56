"""Position projection: exact separation, bodies pushed out of, a free pair's centre of mass."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.ndem import broadphase
from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce import projection
from dozerlab.reduce.compare import body_penetration
from dozerlab.reduce.projection import (
    METHODS,
    Bodies,
    largest_movable_overlap,
    project,
    spheres_near,
)


def bodies(*, box: bool = True) -> Bodies:
    """The ground plane z = 0 and, optionally, a box centred at (1, 0, 0.5) of half size 0.1×0.5×0.5."""
    b = NdemBodies()
    b.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    if box:
        b.add_box((1.0, 0.0, 0.5), (0.1, 0.5, 0.5), True, 0.5, None)
    return Bodies(b.kind, b.center, b.rotations(), b.half, b.normal)


@pytest.mark.parametrize("method", METHODS)
def test_two_overlapping_spheres_separate_exactly_and_keep_their_centre_of_mass(method):
    x = np.array([[0.0, 0.0, 0.5], [0.12, 0.05, 0.5]])
    r = np.array([0.1, 0.08])
    inv_m = np.array([1.0, 2.5])
    com = (x / inv_m[:, None]).sum(0) / (1 / inv_m).sum()
    d0 = x[1] - x[0]
    stats = project(x, r, inv_m, bodies(box=False), iterations=1, method=method)
    assert np.linalg.norm(x[1] - x[0]) == pytest.approx(0.18, abs=1e-12)  # touching, no more
    np.testing.assert_allclose(np.cross(x[1] - x[0], d0), 0.0, atol=1e-12)  # along the normal
    np.testing.assert_allclose((x / inv_m[:, None]).sum(0) / (1 / inv_m).sum(), com, atol=1e-12)
    assert stats.max_overlap == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("method", METHODS)
def test_a_frozen_sphere_is_an_obstacle(method):
    x = np.array([[0.0, 0.0, 0.5], [0.15, 0.0, 0.5]])
    project(
        x,
        np.array([0.1, 0.1]),
        np.array([0.0, 1.0]),
        bodies(box=False),
        iterations=1,
        method=method,
    )
    np.testing.assert_allclose(x, [[0.0, 0.0, 0.5], [0.2, 0.0, 0.5]], atol=1e-12)


def test_spheres_pushed_into_the_ground_and_a_box_leave_exactly_as_far_as_needed():
    # into the ground by 0.05, the box's -x face (x = 0.9) by 0.1, its top (z = 1) from inside by 0.15
    x = np.array([[0.3, 0.1, 0.05], [0.85, 0.0, 0.3], [1.0, 0.2, 0.95]])
    r = np.array([0.1, 0.15, 0.1])
    stats = project(x, r, np.ones(3), bodies(), iterations=0)
    np.testing.assert_allclose(x[0], [0.3, 0.1, 0.1], atol=1e-12)
    np.testing.assert_allclose(x[1], [0.75, 0.0, 0.3], atol=1e-12)
    np.testing.assert_allclose(x[2], [1.0, 0.2, 1.1], atol=1e-12)  # centre inside: out the top
    assert stats.body_depth == pytest.approx(0.15)


def test_a_pile_converges_and_nothing_ends_inside_a_body():
    rng = np.random.default_rng(3)
    x = rng.uniform([0.0, -0.3, 0.0], [0.9, 0.3, 0.4], size=(300, 3))
    r = np.full(300, 0.04)
    few = x.copy()
    s_few = project(few, r, np.ones(300), bodies(), iterations=2)
    s_many = project(x, r, np.ones(300), bodies(), iterations=60)
    assert s_many.max_overlap < s_few.max_overlap
    assert s_many.max_overlap < 0.1
    assert body_penetration(x, r, bodies()) <= 1e-12


def test_sweeps_that_run_out_above_the_overlap_limit_are_followed_by_another_round():
    rng = np.random.default_rng(3)
    x = rng.uniform([0.0, -0.3, 0.0], [0.9, 0.3, 0.4], size=(300, 3))
    r = np.full(300, 0.04)
    runs = {}
    for limit in (np.inf, 1.0, 0.1):
        y = x.copy()
        stats = project(
            y, r, np.ones(300), bodies(), iterations=3, relaxation=1.5, overlap_limit=limit
        )
        runs[limit] = y, stats
    (free, s_free), (loose, s_loose), (held, s_held) = runs.values()
    assert s_free.max_overlap > 0.1  # three sweeps a round leave this pile overlapping
    # a limit above what is left changes nothing
    np.testing.assert_array_equal(loose, free)
    assert s_loose == s_free
    assert s_held.sweeps > s_free.sweeps
    assert s_held.max_overlap <= 0.1
    assert largest_movable_overlap(held, r, np.ones(300)) == pytest.approx(s_held.max_overlap)


def test_a_caged_grain_ends_the_rounds_once_they_stop_moving_its_overlap():
    # a grain squeezed between two obstacles 0.1 m apart, its diameter 0.1 m and theirs too
    x = np.array([[0.0, 0.0, 0.5], [0.09, 0.0, 0.5], [-0.09, 0.0, 0.5]])
    r = np.full(3, 0.05)
    stats = project(
        x,
        r,
        np.array([1.0, 0.0, 0.0]),
        bodies(),
        iterations=4,
        relaxation=1.0,
        overlap_limit=0.1,
    )
    assert stats.max_overlap > 0.1  # nothing the sweeps do frees it
    assert stats.sweeps == 2 * 4  # the second round moved nothing: no third


def test_bad_arguments_are_refused():
    x = np.zeros((1, 3))
    with pytest.raises(ValueError, match="projection method"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=1, method="sor")
    with pytest.raises(ValueError, match="iterations"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=-1)
    with pytest.raises(ValueError, match="tolerance"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=1, tolerance=-0.1)
    with pytest.raises(ValueError, match="overlap_limit"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=1, overlap_limit=0.0)


def pile(n: int = 300, seed: int = 3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``n`` grains of 3.5-4.5 cm dropped at random into a 0.9 × 0.6 × 0.4 m box: deep overlaps."""
    rng = np.random.default_rng(seed)
    x = rng.uniform([0.0, -0.3, 0.0], [0.9, 0.3, 0.4], size=(n, 3))
    return x, rng.uniform(0.035, 0.045, n), rng.uniform(0.5, 2.0, n)


@pytest.mark.parametrize("method", METHODS)
def test_a_sweep_that_corrects_nothing_ends_the_sweeps(method):
    x = np.array([[0.0, 0.0, 0.5], [0.15, 0.0, 0.5]])
    stats = project(x, np.full(2, 0.1), np.ones(2), bodies(box=False), iterations=50, method=method)
    # Gauss-Seidel resolves the pair in sweep 1 and finds nothing in sweep 2; Jacobi likewise
    assert stats.sweeps == 2
    assert stats.max_overlap == pytest.approx(0.0, abs=1e-9)


def test_the_tolerance_stops_the_sweeps_early_with_the_overlap_it_allows():
    x, r, w = pile()
    loose, tight = x.copy(), x.copy()
    s_loose = project(loose, r, w, bodies(), iterations=200, tolerance=0.05)
    s_tight = project(tight, r, w, bodies(), iterations=200, tolerance=0.0)
    assert 1 < s_loose.sweeps < s_tight.sweeps
    assert s_tight.max_overlap < s_loose.max_overlap < 0.1
    assert body_penetration(loose, r, bodies()) <= 1e-12


def cell_sorted(
    x: np.ndarray, r: np.ndarray, w: np.ndarray, cell: float, reach: np.ndarray | None = None
) -> tuple[np.ndarray, ...]:
    """``x`` (N, 3), ``r`` and ``w`` (N,) sorted by the cells of edge ``cell`` covering them
    (x-major), as :func:`projection._round` sorts them, and the pairs ``_pairs_sorted`` lists
    within ``reach`` (default r + 0.02 m): (perm, x, r, w, pi, pj), perm new slot → old."""
    lo = x.min(0) - 1e-9
    dims = np.ceil((x.max(0) - lo + 1e-9) / cell).astype(np.int64)
    perm, xs, rs, ws, start, movable = projection._by_cell(x, r, w, lo, cell, dims)
    sorted_reach = rs + 0.02 if reach is None else reach[perm]
    pi, pj = projection._pairs_sorted(xs, sorted_reach, ws, start, movable, dims)
    return perm, xs, rs, ws, pi, pj


def test_restricted_sweeps_give_the_full_sweeps_result_with_fewer_tests():
    # a pile of deep overlaps beside a resting layer (a lattice 0.1 m apart: candidates, no
    # overlap) that only the first sweep needs to test
    x, r, w = pile(200, seed=5)
    g = np.arange(10) * 0.1
    layer = np.stack(np.meshgrid(1.2 + g, g - 0.45, [0.05], indexing="ij"), -1).reshape(-1, 3)
    x = np.vstack([x, layer])
    r, w = np.concatenate([r, np.full(100, 0.045)]), np.concatenate([w, np.ones(100)])
    _, x, r, w, pi, pj = cell_sorted(x, r, w, 0.2)
    b = bodies()
    bi, bb = projection._body_candidates(
        x, r, w, 0.1, b.kind, b.centre, b.rotation, b.half, b.normal
    )
    assert pi.size > 200 and bi.size > 10
    args = (bi, bb, b.kind, b.centre, b.rotation, b.half, b.normal, 30, True, 1.0, 0.05, 0.0)
    full, restricted = x.copy(), x.copy()
    sweeps_full, tests_full = projection._iterate(full, r, w, pi, pj, *args, False, 0.0)
    sweeps_r, tests_r = projection._iterate(restricted, r, w, pi, pj, *args, True, 0.0)
    np.testing.assert_allclose(restricted, full, rtol=0, atol=1e-12)
    assert sweeps_r == sweeps_full
    assert tests_r < 0.8 * tests_full


def test_ripples_below_the_quiet_share_wake_no_contacts_and_the_pile_still_converges():
    # a settled pile pushed 1 cm at one end, over-relaxed as the loop sweeps: with the quiet
    # share, the sweeps' tiny ripples stop sending whole neighbourhoods to be tested again
    x, r, w = pile(600, seed=3)
    project(x, r, w, bodies(), iterations=500, slop=0.05)
    x[x[:, 0] < 0.3, 0] += 0.01
    _, x, r, w, pi, pj = cell_sorted(x, r, w, 0.2)
    b = bodies()
    bi, bb = projection._body_candidates(
        x, r, w, 0.1, b.kind, b.centre, b.rotation, b.half, b.normal
    )
    tolerance = 0.02
    args = (bi, bb, b.kind, b.centre, b.rotation, b.half, b.normal, 96, True, 1.5, 0.05, tolerance)
    every, quiet = x.copy(), x.copy()
    _, tests_every = projection._iterate(every, r, w, pi, pj, *args, True, 0.0)
    _, tests_quiet = projection._iterate(
        quiet, r, w, pi, pj, *args, True, projection.QUIET * tolerance
    )
    assert tests_quiet < 0.75 * tests_every
    left_every = projection._largest_overlap(every, r, pi, pj)
    left_quiet = projection._largest_overlap(quiet, r, pi, pj)
    assert left_quiet < 0.05 + 2 * tolerance
    assert left_quiet == pytest.approx(left_every, abs=tolerance)


@pytest.mark.parametrize(
    "obstacles", ["every third", "the lower half", "none, heaped", "every third, heaped"]
)
def test_pairs_sorted_finds_every_pair_within_reach_but_those_of_two_obstacles(obstacles):
    # obstacles scattered, or filling whole cells (as the ring around a step's movers does),
    # whose pairs with each other the scan skips cell by cell and sphere by sphere; or grains
    # heaped into each other, more pairs than the first list has room for
    x, r, _ = pile(150, seed=7)
    if obstacles.endswith("heaped"):
        x = x[0] + 0.15 * (x - x[0])
    if obstacles.startswith("every third"):
        w = np.where(np.arange(150) % 3 == 0, 0.0, 1.0)
    elif obstacles == "the lower half":
        w = np.where(x[:, 2] < np.median(x[:, 2]), 0.0, 1.0)
    else:
        w = np.ones(150)
    reach = r + 0.01
    d = np.linalg.norm(x[:, None] - x[None], axis=2)
    want = {
        (a, b)
        for a, b in zip(*np.nonzero(d < reach[:, None] + reach[None]), strict=True)
        if a < b and (w[a] > 0 or w[b] > 0)
    }
    perm, *_, pa, pb = cell_sorted(x, r, w, 0.11, reach)  # cells >= the largest reach sum
    got = {tuple(sorted((int(perm[a]), int(perm[b])))) for a, b in zip(pa, pb, strict=True)}
    assert got == want and len(pa) == len(want)
    assert (len(want) > 8 * 150 + 16) == obstacles.endswith("heaped")
    # in memory order, as the sweeps walk them: by the first sphere's slot, each after the other
    assert np.all(np.diff(pa) >= 0) and np.all(pb > pa)


@pytest.mark.parametrize("method", METHODS)
def test_a_contact_closed_beyond_the_margin_is_found_and_resolved(method):
    # B is pushed 1.75 radii by the obstacle A into C, which began beyond the contact list's
    # reach (r_B + r_C + 2·margin = 0.06 m): a fresh search finds it and a second round separates
    x = np.array([[0.0, 0.0, 0.5], [0.005, 0.0, 0.5], [0.067, 0.0, 0.5]])
    r = np.full(3, 0.02)
    stats = project(
        x, r, np.array([0.0, 1.0, 1.0]), bodies(box=False), iterations=50, method=method
    )
    gaps = [np.linalg.norm(x[1] - x[0]) - 0.04, np.linalg.norm(x[2] - x[1]) - 0.04]
    assert min(gaps) > -1e-3 * 0.02
    assert stats.max_overlap == pytest.approx(max(0.0, -min(gaps) / 0.02), abs=1e-9)


def test_spheres_near_lists_those_within_the_margin_of_a_body():
    # the box's -x face is at x = 0.9: surfaces 0.05 and 0.02 away, one inside, one 0.3 away
    x = np.array([[0.75, 0.0, 0.5], [0.78, 0.0, 0.5], [0.95, 0.0, 0.5], [0.5, 0.0, 0.5]])
    r = np.full(4, 0.1)
    box = bodies()
    only_box = Bodies(*(a[1:] for a in (box.kind, box.centre, box.rotation, box.half, box.normal)))
    np.testing.assert_array_equal(spheres_near(x, r, only_box, 0.03), [1, 2])
    np.testing.assert_array_equal(spheres_near(x, r, only_box, 0.06), [0, 1, 2])
    np.testing.assert_array_equal(spheres_near(x, r, box, 0.0), [2])  # none on the ground


def test_the_search_around_moved_spheres_finds_what_a_search_of_every_pair_finds():
    # the grid sorts the spheres where they stood; since, every sphere moved up to the margin
    # and those of ``which`` anywhere (into each other too): the search on the old grid finds
    # what a search of every pair at the new positions finds
    rng = np.random.default_rng(11)
    n, margin = 400, 0.01
    start = rng.uniform([0.0, -0.3, 0.0], [0.6, 0.3, 0.3], size=(n, 3))
    r = rng.uniform(0.02, 0.03, n)
    inv_m = (rng.uniform(size=n) < 0.7).astype(float)
    which = rng.choice(n, 40, replace=False)
    step = rng.normal(size=(n, 3))
    x = start + margin * rng.uniform(size=(n, 1)) * step / np.linalg.norm(step, axis=1)[:, None]
    x[which] = rng.uniform([0.0, -0.3, 0.0], [0.6, 0.3, 0.3], size=(40, 3))
    # two far movers touching each other above the rest: they stood nowhere near
    x[which[0]], x[which[1]] = [0.3, 0.0, 0.5], [0.33, 0.0, 0.5]
    inv_m[which[:2]] = 1.0
    lo, cell, dims = broadphase.grid_layout(start, float(r.max()) + margin, 8 * n)
    perm, *_, cells, _ = projection._by_cell(start, r, inv_m, lo, cell, dims)
    grid = projection.CellGrid(lo, cell, dims, perm, cells)
    i, j = np.triu_indices(n, 1)
    movable = (inv_m[i] > 0) | (inv_m[j] > 0)
    gap = r[i] + r[j] - np.linalg.norm(x[i] - x[j], axis=1)
    share = gap / np.minimum(r[i], r[j])

    def want(around: np.ndarray) -> float:
        keep = around & movable & (gap > 0)
        return float(share[keep].max()) if keep.any() else 0.0

    every = want(np.isin(i, which) | np.isin(j, which))
    pair = want((i == min(which[:2])) & (j == max(which[:2])))
    assert every > 0 and pair > 0.4
    assert projection._largest_overlap_around(x, r, inv_m, which, grid) == pytest.approx(
        every, rel=1e-12
    )
    assert projection._largest_overlap_around(x, r, inv_m, which[:2], grid) == pytest.approx(
        pair, rel=1e-12
    )
    for a in which[2:]:  # each mover alone: its contacts across the cells as well as in its own
        got = projection._largest_overlap_around(x, r, inv_m, np.array([a]), grid)
        assert got == pytest.approx(want((i == a) | (j == a)), rel=1e-12, abs=1e-15)
    assert projection._largest_overlap_around(x, r, inv_m, which[:0], grid) == 0.0
