"""Physics checks against analytic answers, on scenes of a handful of spheres.

Scenes where no body moves are solved to solver.iterations (``rest_tolerance=0``): the answers
checked are the converged solve's; what the rest tolerance leaves is tested in test_solver.py.
"""

import numba
import numpy as np
import pytest

from dozerlab.ndem import World

G = 9.81
R = 0.05


def _hertz_overlap(weight: float, youngs: float, nu: float, rstar: float) -> float:
    estar = youngs / (2 * (1 - nu**2))
    return (weight / (4 / 3 * estar * np.sqrt(rstar))) ** (2 / 3)


@pytest.mark.parametrize("youngs", [1.0e8, 1.0e6])
def test_resting_sphere_overlap_matches_hertz(youngs):
    w = World(youngs_modulus=youngs, rest_tolerance=0.0)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R]], radius=R)
    w.step(100)
    expected = _hertz_overlap(w.masses[0] * G, youngs, 0.3, R)
    assert R - w.positions[0, 2] == pytest.approx(expected, rel=0.01)
    assert w.last_stats.max_overlap == pytest.approx(expected, rel=0.01)
    np.testing.assert_allclose(w.force_on(0), [0.0, 0.0, -w.masses[0] * G], rtol=1e-6)


def test_stiff_contact_has_no_overlap():
    w = World(youngs_modulus=0.0, rest_tolerance=0.0)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R + 0.02]], radius=R)
    w.step(100)
    assert abs(R - w.positions[0, 2]) < 1e-6 * R
    assert np.abs(w.velocities).max() < 1e-9


def _incline(theta: float, rolling: float, friction: float = 0.8) -> tuple[World, np.ndarray]:
    """A sphere touching a plane tilted by theta about y; returns the world and downhill unit."""
    n = np.array([np.sin(theta), 0.0, np.cos(theta)])
    w = World(rest_tolerance=0.0)
    w.add_plane(normal=n, friction=friction)
    w.add_spheres([R * n], radius=R, rolling_resistance=rolling)
    return w, np.array([np.cos(theta), 0.0, -np.sin(theta)])


def test_sphere_on_incline_below_rolling_threshold_stays_put():
    theta = np.deg2rad(10.0)  # tan θ = 0.176 < μ_r = 0.3
    w, down = _incline(theta, rolling=0.3)
    w.step(20)  # sink to the Hertz overlap
    start = w.positions[0] @ down
    w.step(100)
    assert abs(w.positions[0] @ down - start) < 1e-6
    assert np.abs(w.velocities).max() < 1e-5


@pytest.mark.parametrize("rolling", [0.0, 0.1])
def test_sphere_rolls_down_incline_with_the_analytic_acceleration(rolling):
    theta = np.deg2rad(20.0)  # tan θ = 0.36 > μ_r; μ = 0.8 keeps it rolling without slip
    w, down = _incline(theta, rolling=rolling)
    w.step(50)
    v1 = w.velocities[0] @ down
    w.step(50)
    v2 = w.velocities[0] @ down
    expected = G * (np.sin(theta) - rolling * np.cos(theta)) / 1.4
    assert (v2 - v1) / 0.5 == pytest.approx(expected, rel=0.02)
    omega = w.angular_velocities[0, 1]
    assert omega * R == pytest.approx(v2, rel=0.02)  # rolling without slipping


@pytest.mark.parametrize("spinning", [0.0, 0.1, 0.3])
def test_spin_about_the_normal_is_free_unless_resisted_and_then_stops_at_the_bounded_rate(spinning):
    """A sphere resting on the ground, set spinning about the vertical: no rolling row touches
    that spin, so without spinning resistance it keeps it; with μ_s the torque is R·μ_s·m·g
    (R* = R against a body), so ω falls at 2.5·μ_s·g / R (I = 0.4 m R²) and stops at zero."""
    w = World(spinning_resistance=spinning, rest_tolerance=0.0)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R]], radius=R)
    w.step(20)  # sink to the Hertz overlap
    omega0 = 5.0
    w.state.w[:, 2] = omega0
    spins = []
    for _ in range(40):
        w.step()
        spins.append(w.angular_velocities[0, 2])
    rate = 2.5 * spinning * G / R
    lever = w.positions[0, 2]  # the contact's lever arm: R less the overlap
    if spinning == 0.0:
        np.testing.assert_array_equal(spins, omega0)
    else:
        assert omega0 - spins[0] == pytest.approx(rate * lever / R * w.dt, rel=1e-3)
        assert abs(spins[-1]) < 1e-12 and min(spins) > -1e-12  # stopped, never turned back
    np.testing.assert_allclose(w.angular_velocities[0, :2], 0.0, atol=1e-12)
    np.testing.assert_allclose(w.velocities[0], 0.0, atol=1e-9)


def test_spin_between_two_grains_is_resisted_with_their_reduced_radius():
    """The top sphere of a two-sphere column spins about the vertical: the pair's torque limit
    is R*·μ_s·m·g with R* = R/2, half the ground's, so it slows at 1.25·μ_s·g / R, and the
    sphere below, held by the ground's larger limit, does not turn."""
    spinning = 0.2
    w = World(spinning_resistance=spinning, rest_tolerance=0.0)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R], [0.0, 0.0, 3 * R]], radius=R)
    w.step(20)
    w.state.w[w.state.id == 1, 2] = 5.0
    w.step()
    bottom, top = w.angular_velocities[:, 2]
    assert (5.0 - top) / w.dt == pytest.approx(1.25 * spinning * G / R, rel=0.01)
    assert abs(bottom) < 1e-9


def test_sliding_box_like_sphere_decelerates_by_coulomb_friction():
    """A spinning-free sphere thrown along flat ground with μ_r large: pure sliding first."""
    w = World(iterations=100)
    w.add_plane(friction=0.2)
    w.add_spheres([[0.0, 0.0, R]], radius=R, rolling_resistance=0.0, velocities=[[2.0, 0.0, 0.0]])
    w.step(5)
    v1 = w.velocities[0, 0]
    w.step(5)
    v2 = w.velocities[0, 0]
    assert (v1 - v2) / 0.05 == pytest.approx(0.2 * G, rel=0.02)


def test_stack_and_pyramid_stay_stacked():
    w = World()
    w.add_plane()
    column = [[0.0, 0.0, R + 2 * R * k] for k in range(5)]
    s = 2 * R
    base = [[1.0, 0.0, R], [1.0 + s, 0.0, R], [1.0 + s / 2, s * np.sqrt(3) / 2, R]]
    top = [[1.0 + s / 2, s * np.sqrt(3) / 6, R + s * np.sqrt(2 / 3)]]
    w.add_spheres(np.array(column + base + top), radius=R)
    start = w.positions
    w.step(200)
    assert np.abs(w.positions[:, :2] - start[:, :2]).max() < 1e-3
    assert np.abs(w.positions[5:, 2] - start[5:, 2]).max() < 0.01 * R
    weight = w.masses[0] * G
    sink = _hertz_overlap(5 * weight, 1.0e8, 0.3, R) + sum(
        _hertz_overlap(k * weight, 1.0e8, 0.3, R / 2) for k in range(1, 5)
    )
    assert start[4, 2] - w.positions[4, 2] == pytest.approx(sink, rel=0.05)
    assert np.abs(w.velocities).max() < 1e-3


def test_collision_conserves_momentum_and_loses_energy():
    w = World(gravity=(0.0, 0.0, 0.0))
    w.add_spheres(
        [[0.0, 0.0, 0.0], [0.3, 0.02, 0.0]],
        radius=[0.05, 0.07],
        velocities=[[1.0, 0.0, 0.0], [-0.5, 0.0, 0.0]],
    )
    m = w.masses
    inertia = 0.4 * m * w.radii**2

    def momentum():
        return (m[:, None] * w.velocities).sum(axis=0)

    def energy():
        spin = inertia * (w.angular_velocities**2).sum(1)
        return 0.5 * (m * (w.velocities**2).sum(1) + spin).sum()

    p0, e0 = momentum(), energy()
    met = 0
    for _ in range(40):
        stats = w.step()
        met += stats.contacts + stats.speculative
    assert met > 0
    np.testing.assert_allclose(momentum(), p0, atol=1e-12)
    assert energy() <= e0 * (1 + 1e-9)
    # No longer approaching: the closing speed (1.5 m/s) is gone.
    d = w.positions[1] - w.positions[0]
    assert (w.velocities[1] - w.velocities[0]) @ d / np.linalg.norm(d) > -1e-9


def _pile(n_side: int = 4) -> tuple[World, int]:
    w = World()
    w.add_plane(friction=0.5)
    k = np.arange(n_side)
    grid = np.stack(np.meshgrid(k, k, k, indexing="ij"), -1).reshape(-1, 3) * 2.05 * R
    w.add_spheres(grid + [0.2, -0.15, R + 0.001], radius=R)
    blade = w.add_box((0.05, 0.0, 0.2), (0.02, 0.3, 0.2), kinematic=True)
    return w, blade


def test_blade_pushing_a_pile_feels_a_resisting_force():
    w, blade = _pile()
    w.step(30)  # settle
    w.set_velocity(blade, (0.5, 0.0, 0.0))
    fx = []
    for _ in range(40):
        w.step()
        fx.append(w.force_on(blade)[0])
    weight = w.masses.sum() * G
    push = -np.mean(fx[-20:])
    assert 0.05 * weight < push < 5.0 * weight
    assert np.all(w.positions[:, 0] > w.body_position(blade)[0])


def test_more_iterations_reduce_the_residual():
    res = []
    for iterations in (5, 80):
        w, _ = _pile()
        w.iterations = iterations
        w.warm_start = False
        res.append(w.step(10).residual)
    assert res[1] < 0.5 * res[0]


def test_runs_are_deterministic():
    runs = []
    for _ in range(2):
        w, blade = _pile(3)
        w.set_velocity(blade, (0.5, 0.0, 0.0))
        w.step(20)
        runs.append((w.positions, w.force_on(blade)))
    np.testing.assert_array_equal(runs[0][0], runs[1][0])
    np.testing.assert_array_equal(runs[0][1], runs[1][1])


@pytest.mark.skipif(numba.config.NUMBA_NUM_THREADS < 2, reason="needs NUMBA_NUM_THREADS >= 2")
def test_result_does_not_depend_on_thread_count(monkeypatch):
    monkeypatch.setattr("dozerlab.ndem.stepper.PARALLEL_MIN_CONTACTS", 0)  # sweep in parallel
    runs = []
    for threads in (1, 2):
        numba.set_num_threads(threads)
        w, blade = _pile(4)
        w.slabs = 4
        w.set_velocity(blade, (0.5, 0.0, 0.0))
        w.step(10)
        runs.append(w.positions)
    np.testing.assert_array_equal(runs[0], runs[1])


def test_emitted_bed_settles_with_the_workflow_defaults():
    """Batches of polydisperse spheres dropped into a walled box come to rest, no blow-up."""
    w = World()  # dt 0.01 s, 50 iterations, E = 1e8 Pa, τ = 3 dt: the workflow's regime
    w.add_plane()
    for x, nx in ((0.0, 1.0), (1.2, -1.0)):
        w.add_plane(point=(x, 0.0, 0.0), normal=(nx, 0.0, 0.0))
    for y, ny in ((-0.3, 1.0), (0.3, -1.0)):
        w.add_plane(point=(0.0, y, 0.0), normal=(0.0, ny, 0.0))
    rng = np.random.default_rng(3)
    grid = np.stack(np.meshgrid(np.arange(10), np.arange(5), indexing="ij"), -1).reshape(-1, 2)
    layer = grid * 0.115 + [0.08, -0.23]
    for batch in range(6):
        pos = np.column_stack([layer, np.full(len(layer), 0.15 + 0.12 * batch)])
        w.add_spheres(
            pos + rng.uniform(-0.003, 0.003, pos.shape), radius=R * rng.uniform(0.9, 1.1, len(pos))
        )
        w.step(30)
    w.step(150)
    kinetic = 0.5 * (w.masses * (w.velocities**2).sum(1)).sum() / w.n_spheres
    assert w.n_spheres == 300
    assert kinetic < 1e-4
    assert w.last_stats.max_overlap_fraction < 0.05
    assert w.positions[:, 2].min() > 0.9 * R * 0.9


def test_advance_without_spheres_moves_the_bodies_and_the_clock():
    from dozerlab.ndem.bodies import Bodies
    from dozerlab.ndem.params import Parameters
    from dozerlab.ndem.state import WorldState
    from dozerlab.ndem.stepper import advance

    bodies = Bodies()
    blade = bodies.add_box((0, 0, 0), (0.1, 0.1, 0.1), True, 0.5, None)
    bodies.vel[blade] = [0.5, 0.0, 0.0]
    bodies.force[blade] = [3.0, 0.0, 0.0]  # last step's load, cleared
    state = WorldState()
    stats = advance(state, bodies, Parameters(dt=0.02))
    assert (stats.step, stats.time, stats.contacts, stats.iterations) == (1, 0.02, 0, 0)
    assert (state.step_count, state.time) == (1, 0.02)
    np.testing.assert_allclose(bodies.center[blade], [0.01, 0.0, 0.0])
    np.testing.assert_array_equal(bodies.force, np.zeros((1, 3)))


def test_overlap_pass_matches_numpy_on_pairs_bodies_and_nan():
    from dozerlab.ndem.stepper import _overlaps

    rng = np.random.default_rng(3)
    r = rng.uniform(0.02, 0.05, 50)
    ci = rng.integers(0, 50, 400)
    cj = np.where(rng.random(400) < 0.3, -rng.integers(1, 4, 400), rng.integers(0, 50, 400))
    gap = rng.uniform(-0.01, 0.01, 400)
    rmin = np.where(cj >= 0, np.minimum(r[ci], r[np.maximum(cj, 0)]), r[ci])
    frac = np.maximum(gap, 0.0) / rmin
    k, f, touching, g = _overlaps(r, ci, cj, gap)
    assert (k, f) == (frac.argmax(), frac.max())  # the first largest, bit for bit
    assert touching == int((gap > 0).sum()) and g == gap.max()
    assert _overlaps(r, ci[:0], cj[:0], gap[:0]) == (-1, 0.0, 0, 0.0)
    gap[[7, 9]] = np.nan  # a NaN wins, the first one, as in numpy
    k, f, _, g = _overlaps(r, ci, cj, gap)
    assert k == 7 and np.isnan(f) and np.isnan(g)


def _row_and_blade(**params) -> tuple[World, int]:
    """Spheres in a row on the ground along x (gaps of one radius), a blade box behind the
    first moving +x at 0.5 m/s."""
    w = World(**params)
    w.add_plane()
    x = 0.3 + 3.0 * R * np.arange(24)
    w.add_spheres(np.stack([x, np.zeros_like(x), np.full_like(x, R)], axis=1), radius=R)
    blade = w.add_box((0.2, 0.0, 0.1), (0.05, 0.2, 0.1), kinematic=True)
    w.set_velocity(blade, (0.5, 0.0, 0.0))
    return w, blade


def test_active_zone_holds_still_what_the_blade_has_not_reached():
    w, _ = _row_and_blade(active_zone=True, zone_margin=0.2, rest_time=0.05)
    w.step(12)
    asleep = ~w.state.public(w.state.awake)
    far = w.positions[:, 0] > 1.5
    assert asleep[far].all() and not asleep[w.positions[:, 0] < 0.5].any()
    held = w.positions[far]
    w.step(30)
    np.testing.assert_array_equal(w.positions[far], held)  # never stepped, bit for bit
    assert w.last_stats.active < w.n_spheres
    assert w.last_stats.active == int(w.state.awake.sum())
    assert w.positions[0, 0] > 0.4  # the blade pushed the first one along


def test_active_zone_wakes_a_sleeping_grain_that_a_moving_one_reaches():
    w = World(active_zone=True, rest_time=0.05, friction=0.0, rolling_resistance=0.0)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R], [0.3, 0.0, R]], radius=R)
    w.step(10)
    assert not w.state.awake.any() and w.last_stats.active == 0
    v = np.zeros((2, 3))
    v[0, 0] = 1.0
    w.velocities = v  # a velocity set from outside wakes the sphere
    w.step(1)
    awake = w.state.public(w.state.awake)
    assert awake[0] and not awake[1]
    x1 = w.positions[1, 0]
    w.step(40)
    assert w.positions[1, 0] > x1 + 0.03  # hit, woken and pushed on


def test_active_zone_solves_a_jam_again_with_the_sleeper_it_wakes():
    # the blade (no margin) drives a grain at 2 m/s into a sleeping one: held rigid, it would
    # take 0.4 radius of overlap in one step; loaded, it wakes and, the step heading past
    # relinearize_above, the step is solved again with it, so both are pushed along
    w = World(active_zone=True, zone_margin=0.0, rest_time=0.05)
    w.add_plane()
    w.add_spheres([[0.3, 0.0, R], [0.3 + 2 * R, 0.0, R]], radius=R)
    blade = w.add_box((0.3 - R - 0.05, 0.0, 0.1), (0.05, 0.2, 0.1), kinematic=True)
    w.step(15)
    assert w.state.public(w.state.awake).tolist() == [True, False]
    w.set_velocity(blade, (2.0, 0.0, 0.0))
    worst = 0.0
    for _ in range(10):
        w.step(1)
        worst = max(worst, w.last_stats.max_overlap_fraction)
    assert worst < 0.1
    assert w.positions[1, 0] > 0.3 + 2 * R + 0.15  # the sleeper woke and was pushed on


@pytest.mark.parametrize(
    ("density", "wake_load", "wakes"), [(1.5, 1.0, True), (1.5, 2.0, False), (3.0, 2.0, True)]
)
def test_active_zone_wakes_a_sleeper_whose_load_passes_wake_load_times_what_holds_it(
    density, wake_load, wakes
):
    # a grain set down at rest on a sleeper loads it with its own weight, ``density`` times
    # the sleeper's, which its contact with the ground carried alone
    w = World(active_zone=True, rest_time=0.05, wake_load=wake_load)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R]], radius=R)
    w.step(10)
    assert not w.state.awake.any()
    w.add_spheres([[0.0, 0.0, 3 * R]], radius=R, density=density * w.density)
    w.step(1)
    assert w.state.public(w.state.awake).tolist() == [wakes, True]


@pytest.mark.parametrize("relinearize_above", [0.3, 0.0])
def test_a_grain_on_a_sleeper_rests_on_a_contact_sleeper_compliance_times_as_compliant(
    relinearize_above,
):
    # Hertz under the same weight: k·δ^(3/2) = W, with the compliance c times as large
    # δ grows by c^(2/3); the step's relinearisation rounds (every step at 0) keep the factor
    def overlap(compliance: float) -> float:
        w = World(
            active_zone=True,
            rest_time=0.05,
            rest_tolerance=0.0,
            sleeper_compliance=compliance,
            relinearize=1,
            relinearize_above=relinearize_above,
        )
        w.add_plane()
        w.add_spheres([[0.0, 0.0, R]], radius=R)
        w.step(10)
        assert not w.state.awake.any()
        w.rest_time = 10.0  # the grain set on it stays awake while it settles
        w.add_spheres([[0.0, 0.0, 3 * R]], radius=R)
        w.step(100)
        assert w.state.public(w.state.awake).tolist() == [False, True]
        return 2 * R - float(w.positions[1, 2] - w.positions[0, 2])

    rigid = overlap(1.0)
    expected = _hertz_overlap(World().density * 4 / 3 * np.pi * R**3 * G, 1.0e8, 0.3, R / 2)
    assert rigid == pytest.approx(expected, rel=0.02)
    assert overlap(3.0) == pytest.approx(3.0 ** (2 / 3) * rigid, rel=0.02)


def test_switching_the_active_zone_off_wakes_every_sleeper():
    w = World(active_zone=True, rest_time=0.05)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R], [0.5, 0.0, R]], radius=R)
    w.step(10)
    assert w.last_stats.active == 0
    w.active_zone = False
    w.step(1)
    assert w.last_stats.active == 2 and w.state.awake.all() and not w.state.rest.any()


def test_active_zone_lets_a_grain_sleep_only_after_rest_time_at_rest_outside_it():
    w = World(active_zone=True, zone_margin=0.2, rest_time=0.1)
    w.add_plane()
    w.add_spheres([[0.0, 0.0, R], [2.0, 0.0, R]], radius=R)
    w.add_box((-0.2, 0.0, 0.1), (0.05, 0.2, 0.1), kinematic=True)  # a blade standing still
    w.step(8)
    assert w.state.public(w.state.awake).tolist() == [True, True]  # both at rest < 0.1 s
    w.step(12)
    # the far one slept after 0.1 s at rest; the one in the zone never does
    assert w.state.public(w.state.awake).tolist() == [True, False]
    assert w.last_stats.active == 1


@pytest.mark.parametrize("counted", [True, False])
def test_a_grain_counted_as_rested_sleeps_after_the_first_step_outside_the_zone(counted):
    # three grains settled on the ground far from a standing blade, then one set rolling along
    # at 0.1 m/s and one spinning in place with its surface at 0.1 m/s: only the first is at
    # rest when the zone begins
    w = World(rest_time=0.1, rolling_resistance=0.0)
    w.add_plane()
    w.add_spheres([[2.0, 0.0, R], [3.0, 0.0, R], [4.0, 0.0, R]], radius=R)
    w.add_box((-0.2, 0.0, 0.1), (0.05, 0.2, 0.1), kinematic=True)
    w.step(20)
    w.velocities = [[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.0, 0.0]]
    w.angular_velocities = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.1 / R]]
    assert (w.count_as_rested() if counted else 0) == (1 if counted else 0)
    w.active_zone, w.zone_margin = True, 0.2
    w.step(1)
    assert w.state.public(w.state.awake).tolist() == [not counted, True, True]
    assert w.last_stats.active == (2 if counted else 3)


def test_active_zone_covering_every_grain_changes_nothing():
    full, _ = _row_and_blade()
    zoned, _ = _row_and_blade(active_zone=True, zone_margin=100.0)
    full.step(30)
    zoned.step(30)
    np.testing.assert_array_equal(zoned.positions, full.positions)
    np.testing.assert_array_equal(zoned.force_on(1), full.force_on(1))
    assert zoned.last_stats.active == full.last_stats.active == full.n_spheres


def test_active_zone_reads_its_config_section():
    from dozerlab.config import load_config
    from dozerlab.ndem.params import Parameters

    zone = {"enabled": True, "margin": 0.5, "rest_speed": 0.01, "rest_time": 0.2, "wake_load": 3}
    p = Parameters.from_config(
        load_config({"solver": {"active_zone": zone | {"sleeper_compliance": 2}}})
    )
    assert (p.active_zone, p.zone_margin, p.rest_speed, p.rest_time) == (True, 0.5, 0.01, 0.2)
    assert (p.wake_load, p.sleeper_compliance) == (3.0, 2.0)
    assert Parameters().active_zone is False  # off by default: the full solve
