"""The contact solver: NNCG and over-relaxed PGS reach PGS's answer, the tolerance stop, threads."""

import numba
import numpy as np
import pytest

from dozerlab.ndem import World, contacts, solver

R = 0.05


def _stack() -> World:
    w = World()
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R + 2 * R * k] for k in range(8)], radius=R)
    return w


def _pile() -> World:
    w = World()
    w.add_plane(friction=0.5)
    for x, nx in ((-0.2, 1.0), (0.6, -1.0)):
        w.add_plane(point=(x, 0.0, 0.0), normal=(nx, 0.0, 0.0))
    rng = np.random.default_rng(3)
    k = np.arange(4)
    grid = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) * 2.05 * R
    w.add_spheres(grid + [0.1 + R, -0.15, R + 0.001], radius=R * rng.uniform(0.9, 1.0, len(grid)))
    return w


def _push() -> World:
    w = _pile()
    w.step(40)  # settle
    blade = w.add_box((0.05, 0.0, 0.2), (0.02, 0.3, 0.2), kinematic=True)
    w.set_velocity(blade, (0.5, 0.0, 0.0))
    w.step(10)
    return w


SCENES = {"stack": _stack, "pile": _pile, "push": _push}


def _converged(scene: str, method: str, relaxation: float) -> World:
    """The scene with its next step solved to a residual of 1e-8 m/s (the tolerance stops on
    every row's velocity change, a little apart from the normal rows' residual)."""
    w = SCENES[scene]()
    w.step(5)  # warm contacts
    w.method, w.relaxation, w.iterations, w.tolerance = method, relaxation, 50000, 1e-9
    w.rest_tolerance = 0.0  # the scenes without the blade are at rest
    w.relinearize = 0  # one solve: the sweeps it took are compared
    w.step()
    return w


@pytest.mark.parametrize("scene", sorted(SCENES))
@pytest.mark.parametrize(("method", "relaxation"), [("nncg", 1.0), ("pgs", 1.5)])
def test_faster_methods_converge_to_the_multipliers_of_pgs(scene, method, relaxation):
    pgs, nncg = _converged(scene, "pgs", 1.0), _converged(scene, method, relaxation)
    assert pgs.last_stats.residual <= 1e-8 and nncg.last_stats.residual <= 1e-8
    assert nncg.last_stats.iterations < pgs.last_stats.iterations
    # The normal multipliers are unique (the compliance makes their block positive definite);
    # friction and rolling ones may not be (two contacts can share one sphere's rolling load),
    # so those are compared by what they do: the velocities and the loads on the bodies.
    lam_p, lam_n = pgs.state.warm.lam[:, 0], nncg.state.warm.lam[:, 0]
    assert lam_p.shape == lam_n.shape and lam_p.max() > 0
    np.testing.assert_allclose(lam_n, lam_p, rtol=0, atol=5e-4 * lam_p.max())
    np.testing.assert_allclose(nncg.velocities, pgs.velocities, rtol=0, atol=1e-5)  # m/s
    np.testing.assert_allclose(nncg.angular_velocities, pgs.angular_velocities, rtol=0, atol=1e-4)
    scale = np.abs(pgs.force_on(0)).max()
    for body in range(len(pgs.bodies)):
        np.testing.assert_allclose(nncg.force_on(body), pgs.force_on(body), atol=5e-4 * scale)


@pytest.mark.parametrize("method", ["pgs", "nncg"])
def test_tolerance_stops_the_solve(method):
    w = _push()
    w.method, w.iterations, w.tolerance, w.relinearize = method, 5000, 1e-4, 0
    stats = w.step()
    assert 1 < stats.iterations < 5000
    assert stats.residual <= 1e-4
    w.tolerance = 0.0
    assert w.step().iterations == 5000  # no tolerance: the cap


def test_fewer_sweeps_with_nncg_or_over_relaxation_for_the_same_residual():
    sweeps = {}
    for method, relaxation in (("pgs", 1.0), ("nncg", 1.0), ("pgs", 1.5)):
        w = _push()
        w.method, w.relaxation, w.iterations, w.tolerance = method, relaxation, 5000, 1e-5
        w.relinearize = 0  # one solve each
        sweeps[method, relaxation] = w.step().iterations
    assert sweeps["nncg", 1.0] < 0.8 * sweeps["pgs", 1.0]
    assert sweeps["pgs", 1.5] < 0.8 * sweeps["pgs", 1.0]


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs NUMBA_NUM_THREADS >= 2")
@pytest.mark.parametrize("method", ["pgs", "nncg"])
def test_thread_count_changes_nothing(monkeypatch, method):
    monkeypatch.setattr("dozerlab.ndem.stepper.PARALLEL_MIN_CONTACTS", 0)  # sweep in parallel
    monkeypatch.setattr("dozerlab.ndem.stepper.PARALLEL_MIN_SPHERES", 0)
    runs = []
    threads = numba.get_num_threads()
    try:
        for n in (1, 2):
            numba.set_num_threads(n)
            w = _pile()
            w.slabs, w.method, w.tolerance, w.iterations = 4, method, 1e-4, 300
            w.relaxation = 1.0 if method == "nncg" else 1.5
            w.step(10)
            blade = w.add_box((0.05, 0.0, 0.2), (0.02, 0.3, 0.2), kinematic=True)
            w.set_velocity(blade, (0.5, 0.0, 0.0))
            runs.append((w.step(15), w.positions, w.force_on(blade)))
    finally:
        numba.set_num_threads(threads)
    (s1, x1, f1), (s2, x2, f2) = runs
    assert s1.iterations == s2.iterations
    np.testing.assert_allclose(x2, x1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(f2, f1, rtol=1e-9)


def test_method_and_tolerance_are_validated():
    with pytest.raises(ValueError, match="method"):
        World(method="cg")
    with pytest.raises(ValueError, match="tolerance"):
        World(tolerance=-1.0)
    with pytest.raises(ValueError, match="rest_tolerance"):
        World(rest_tolerance=-1.0)
    with pytest.raises(ValueError, match="relaxation"):
        World(relaxation=2.0)
    w = World()
    with pytest.raises(ValueError, match="method"):
        w.method = "sor"


def _drop(relinearize: int, above: float = 0.0) -> World:
    """A jittered lattice of 6 × 3 columns of 12 grains (r 2.5 cm ± 10 %, 5.8 cm apart) whose
    lowest layer reaches the ground at 1.5 m/s, the upper ones at up to ~2 m/s, dt 0.01 s;
    ``relinearize`` rounds in the steps where a pair would end deeper than ``above`` radii."""
    w = World(relinearize=relinearize, relinearize_above=above)
    spacing, r = 0.058, 0.025
    w.add_plane()
    for x, nx in ((0.0, 1.0), (6 * spacing + 0.01, -1.0)):
        w.add_plane(point=(x, 0.0, 0.0), normal=(nx, 0.0, 0.0))
    for y, ny in ((-0.005, 1.0), (3 * spacing + 0.005, -1.0)):
        w.add_plane(point=(0.0, y, 0.0), normal=(0.0, ny, 0.0))
    rng = np.random.default_rng(5)
    i, j, k = np.meshgrid(np.arange(6), np.arange(3), np.arange(12), indexing="ij")
    x = np.stack([i, j, k], axis=-1).reshape(-1, 3) * spacing + [0.034, 0.029, 0.0275 + 0.115]
    x += rng.uniform(-0.0015, 0.0015, x.shape)
    w.add_spheres(x, r * rng.uniform(0.9, 1.1, len(x)), density=2600.0, rolling_resistance=0.1)
    return w


def test_a_dropped_lattice_lands_with_overlaps_below_five_percent_of_a_radius():
    w = _drop(relinearize=3)
    worst = 0.0
    for _ in range(60):  # the columns land from step 16 on and crumble
        worst = max(worst, w.step().max_overlap_fraction)
    assert worst <= 0.05
    assert w.positions[:, 2].max() < 0.6  # landed


def test_rounds_past_a_depth_run_only_where_a_pair_would_sink_past_it():
    every, past = _drop(relinearize=3), _drop(relinearize=3, above=0.2)
    rounds = {"every": 0, "past": 0}
    worst = 0.0
    for _ in range(60):
        for name, w in (("every", every), ("past", past)):
            st = w.step()
            rounds[name] += st.iterations > w.iterations  # a round's sweeps come on top
            if name == "past":
                worst = max(worst, st.max_overlap_fraction)
    assert worst <= 0.2  # without rounds the drop sinks 0.4 radius (the test below)
    assert 0 < rounds["past"] < rounds["every"] / 2


def test_deepest_end_is_the_overlap_a_pair_reaches_by_the_end_of_the_step():
    pairs = np.array([0]), np.array([1])
    cd = np.zeros((1, contacts.NCOL))
    cd[0, contacts.N0] = -1.0  # the normal from j to i
    cd[0, contacts.SIG], cd[0, contacts.KN] = 1e-6, 1.0
    gap = np.array([0.015])  # r_i + r_j − distance, m
    v = np.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    r = np.array([0.05, 0.06])
    # approaching at 1 m/s: 1 cm more in 0.01 s, 2.5 cm over the smaller radius 5 cm
    assert solver.deepest_end(*pairs, cd, gap, v, r, 0.01, 1) == pytest.approx(0.5)
    cd[0, contacts.SIG] = 0.0  # a stiff or speculative row is not Hertz's: left out
    assert solver.deepest_end(*pairs, cd, gap, v, r, 0.01, 1) == 0.0


def test_without_relinearising_the_dropped_lattice_sinks_into_itself():
    w = _drop(relinearize=0)
    worst = 0.0
    for _ in range(30):
        worst = max(worst, w.step().max_overlap_fraction)
    assert worst > 0.2  # touching grains taken unloaded sink by a step's travel


@pytest.mark.parametrize(
    "stop", [{"tolerance": 1e-4, "rest_tolerance": 0.0}, {}], ids=["tolerance", "rest_tolerance"]
)
def test_a_tolerance_stop_leaves_a_sphere_on_an_incline_in_place(stop):
    # The stop counts the friction and rolling rows: on the normal row alone it crept (1e-4 m/s).
    theta = np.deg2rad(10.0)  # below the rolling threshold μ_r = 0.3
    n = np.array([np.sin(theta), 0.0, np.cos(theta)])
    w = World(iterations=500, **stop)  # {}: the default rest tolerance, no body moving
    w.add_plane(normal=n, friction=0.8)
    w.add_spheres([R * n], radius=R, rolling_resistance=0.3)
    down = np.array([np.cos(theta), 0.0, -np.sin(theta)])
    w.step(20)
    start = w.positions[0].copy()
    for _ in range(3):
        stats = w.step(100)
        assert stats.iterations < 500  # stopped by the tolerance
        moved = w.positions[0] - start
        assert abs(moved @ down) < 1e-6  # over 3 s: no creep down the slope
        assert abs(moved @ n) < 5e-6  # the contact breathes, by under 6 % of its 87 µm overlap


def test_the_rest_tolerance_stops_the_solve_only_while_no_body_moves():
    assert World().rest_tolerance == 3e-4  # the schema's default
    w = _pile()
    blade = w.add_box((0.05, 0.0, 0.2), (0.02, 0.3, 0.2), kinematic=True)
    w.iterations = 200
    w.step(40)
    assert w.step().iterations < 200  # a bed left to itself: stopped at 3e-4 m/s
    w.set_velocity(blade, (0.5, 0.0, 0.0))
    assert w.step().iterations == 200  # the blade drives it: every sweep
    # and a push is solved bit for bit as without the rest tolerance
    runs = []
    for rest in (3e-4, 0.0):
        w = _pile()
        w.rest_tolerance = rest
        w.set_velocity(w.add_box((0.05, 0.0, 0.2), (0.02, 0.3, 0.2), kinematic=True), (0.5, 0, 0))
        w.step(30)
        runs.append((w.positions, w.velocities, w.force_on(len(w.bodies) - 1)))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
