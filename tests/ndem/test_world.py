"""The World's public API: ids and ordering, bodies, state access, save/load, argument errors."""

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.ndem import DivergenceError, StepStats, World
from dozerlab.runtime import DozerlabError, OutputExistsError


def _grid(n: int, r: float = 0.05, z0: float = 0.06) -> np.ndarray:
    """n sphere centres on a loose grid above the ground."""
    k = int(np.ceil(n ** (1 / 3)))
    idx = np.stack(np.unravel_index(np.arange(n), (k, k, k)), axis=1)
    return idx * 2.2 * r + np.array([0.0, 0.0, z0])


def test_public_arrays_stay_in_id_order_after_the_spatial_sort():
    w = World()
    w.add_plane()
    rng = np.random.default_rng(1)
    pos = _grid(27)[rng.permutation(27)]
    radii = np.linspace(0.045, 0.055, 27)
    a = w.add_spheres(pos[:10], radius=radii[:10])
    b = w.add_spheres(pos[10:], radius=radii[10:])
    assert a.tolist() == list(range(10)) and b.tolist() == list(range(10, 27))
    stats = w.step()
    assert isinstance(stats, StepStats) and w.last_stats is stats
    np.testing.assert_allclose(w.radii, radii)
    np.testing.assert_allclose(w.masses, 2600.0 * 4 / 3 * np.pi * radii**3)
    # After one step from rest each sphere moved by at most g·dt² plus contact corrections.
    assert np.abs(w.positions - pos).max() < 2e-3


def test_state_setters_and_removal_renumber_ids():
    w = World(gravity=(0.0, 0.0, 0.0))
    w.add_spheres(_grid(8, z0=1.0), radius=0.05)
    w.step()
    v = np.arange(24, dtype=float).reshape(8, 3) * 0.01
    w.velocities = v
    np.testing.assert_array_equal(w.velocities, v)
    w.set_sphere_state([3], positions=[[5.0, 5.0, 5.0]], angular_velocities=[[1.0, 2.0, 3.0]])
    np.testing.assert_array_equal(w.positions[3], [5.0, 5.0, 5.0])
    np.testing.assert_array_equal(w.angular_velocities[3], [1.0, 2.0, 3.0])
    before = w.positions
    kept = w.remove_spheres([0, 3])
    assert kept.tolist() == [1, 2, 4, 5, 6, 7]
    np.testing.assert_array_equal(w.positions, before[kept])
    mask = np.zeros(6, dtype=bool)
    mask[-1] = True
    w.remove_spheres(mask)
    assert w.n_spheres == 5
    w.step()


def test_kinematic_box_moves_and_reports_loads(tmp_path):
    w = World(gravity=(0.0, 0.0, 0.0))
    blade = w.add_box(center=(0.0, 0.0, 0.5), half_extents=(0.05, 0.3, 0.2), kinematic=True)
    w.set_velocity(blade, (0.5, 0.0, 0.0), angular=(0.0, 0.0, 0.1))
    w.step(10)
    np.testing.assert_allclose(w.body_position(blade), [0.05, 0.0, 0.5], atol=1e-12)
    np.testing.assert_allclose(w.body_velocity(blade), [0.5, 0.0, 0.0])
    q = w.body_orientation(blade)
    assert np.isclose(2 * np.arctan2(q[3], q[0]), 0.1 * 0.1)
    np.testing.assert_array_equal(w.force_on(blade), np.zeros(3))
    assert w.time == pytest.approx(0.1) and w.contact_count == 0
    with pytest.raises(ValueError, match="static"):
        w.set_velocity(w.add_plane(), (1.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="body"):
        w.force_on(7)


def test_torque_about_a_point_adds_the_force_moment():
    w = World(rest_tolerance=0.0)  # the converged static load
    w.add_plane()
    box = w.add_box(center=(0.0, 0.0, 0.05), half_extents=(0.2, 0.2, 0.05), kinematic=True)
    w.add_spheres([[0.1, 0.0, 0.1499]], radius=0.05)
    w.step(5)
    f = w.force_on(box)
    assert f[2] == pytest.approx(-w.masses[0] * 9.81, rel=1e-3)
    tip = np.array([0.3, 0.0, 0.0])
    expected = w.torque_on(box) + np.cross(w.body_position(box) - tip, f)
    np.testing.assert_allclose(w.torque_on(box, about=tip), expected)
    # The sphere sits 0.1 m off the centre along x, so τ_y = -0.1 m · F_z.
    assert w.torque_on(box)[1] == pytest.approx(-0.1 * f[2], rel=1e-2)


def test_save_and_load_round_trip(tmp_path):
    w = World(iterations=20)
    w.add_plane(friction=0.3)
    blade = w.add_box((0.5, 0.0, 0.2), (0.02, 0.2, 0.2), kinematic=True)
    w.set_velocity(blade, (-0.2, 0.0, 0.0))
    w.add_spheres(_grid(20), radius=0.05)
    w.step(5)
    path = tmp_path / "bed.npz"
    w.save(path)
    v = World.load(path)
    assert v.iterations == 20 and v.time == w.time and v.n_spheres == 20
    np.testing.assert_array_equal(v.positions, w.positions)
    np.testing.assert_array_equal(v.force_on(blade), w.force_on(blade))
    w.step(3)
    v.step(3)
    np.testing.assert_array_equal(v.positions, w.positions)
    np.testing.assert_array_equal(v.body_position(blade), w.body_position(blade))


def test_save_replaces_a_world_file_and_refuses_anything_else(tmp_path):
    w = World(iterations=20)
    w.add_spheres(_grid(8), radius=0.05)
    path, other = tmp_path / "state.npz", tmp_path / "notes.npz"
    w.save(path)
    w.step(2)
    w.save(path)  # its own earlier file (persist.WORLD_FILE) is replaced
    assert World.load(path).time == w.time
    other.write_text("a user's file")
    with pytest.raises(OutputExistsError, match="not a dozerlab World file"):
        w.save(other)
    assert other.read_text() == "a user's file"


def test_from_config_reads_solver_and_material():
    cfg = load_config(
        {
            "solver": {"dt": 0.005, "iterations": 30, "damping_steps": 2.0},
            "material": {"youngs_modulus": 0.0, "friction": 0.7, "spinning_resistance": 0.2},
        }
    )
    w = World.from_config(cfg)
    assert (w.dt, w.iterations, w.damping_steps, w.youngs_modulus, w.friction) == (
        0.005,
        30,
        2.0,
        0.0,
        0.7,
    )
    assert w.spinning_resistance == 0.2
    assert World.from_config(load_config(None)).spinning_resistance == 0.0  # off by default
    assert w.max_overlap == cfg["solver"]["max_overlap"]
    assert w.density == cfg["material"]["density"]


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"dt": 0.0}, "dt"),
        ({"dt": -1.0}, "dt"),
        ({"iterations": 0}, "iterations"),
        ({"damping_steps": 0.0}, "damping_steps"),
        ({"poisson_ratio": 0.5}, "poisson_ratio"),
        ({"youngs_modulus": -1.0}, "youngs_modulus"),
        ({"spinning_resistance": -0.1}, "spinning_resistance"),
        ({"gravity": (0, 0)}, "gravity"),
    ],
)
def test_invalid_world_arguments(kwargs, match):
    with pytest.raises(ValueError, match=match):
        World(**kwargs)


def test_invalid_sphere_and_body_arguments():
    w = World()
    with pytest.raises(ValueError, match="radius"):
        w.add_spheres([[0.0, 0.0, 0.0]], radius=-0.1)
    with pytest.raises(ValueError, match="radius"):
        w.add_spheres(np.zeros((3, 3)), radius=[0.1, 0.1])
    with pytest.raises(ValueError, match="positions"):
        w.add_spheres([[0.0, np.nan, 0.0]])
    with pytest.raises(ValueError, match="positions"):
        w.add_spheres(np.zeros((2, 2)))
    with pytest.raises(ValueError, match="density"):
        w.add_spheres([[0.0, 0.0, 0.0]], density=0.0)
    with pytest.raises(ValueError, match="friction"):
        w.add_plane(friction=-1.0)
    with pytest.raises(ValueError, match="normal"):
        w.add_plane(normal=(0, 0, 0))
    with pytest.raises(ValueError, match="half_extents"):
        w.add_box((0, 0, 0), (0.1, 0.0, 0.1))
    with pytest.raises(ValueError, match="n must"):
        w.step(0)
    assert w.n_spheres == 0


def test_divergence_errors_name_what_diverged():
    w = World(gravity=(0.0, 0.0, 0.0), max_overlap=0.3)
    w.add_spheres([[0.0, 0.0, 0.0], [0.06, 0.0, 0.0]], radius=0.05)
    with pytest.raises(DivergenceError, match=r"overlap .* exceeds max_overlap = 0.3 at step 1"):
        w.step()
    w = World(gravity=(0.0, 0.0, 0.0))
    w.add_spheres([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]], radius=0.05)
    w.state.v[w.state.id == 1, 0] = np.nan  # the public setters refuse NaN, so corrupt the storage
    with pytest.raises(DivergenceError, match=r"non-finite .* ids \[1\]") as info:
        w.step()
    assert isinstance(info.value, DozerlabError) and isinstance(info.value, RuntimeError)
