import dataclasses

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.ndem import World
from dozerlab.runtime import ConfigError
from dozerlab.scenarios import build
from dozerlab.scenarios.blade import add_blade, start_tip
from dozerlab.scenarios.build import build_bed, make_world
from dozerlab.scenarios.heightfield import height_field

SMALL = {
    "bed": {
        "length": 0.6,
        "width": 0.2,
        "radius": 0.025,
        "iterations": 15,
        "max_settle_time": 8.0,
        "emitter_speed": 2.0,
        "settle_kinetic_energy": 2.0e-4,
    },
    "scenarios": {
        "hill": {
            "base_height": 0.04,
            "peak_height": 0.2,
            "center": 0.5,
            "half_width": 0.3,
            "goal_height": 0.08,
        },
        "step": {"high_height": 0.14, "low_height": 0.04, "edge": 0.5, "goal_height": 0.08},
    },
    "blade": {"width": 0.2, "height": 0.15, "thickness": 0.02},
    "trajectory": {"subdivisions": [60, 4], "end_margin": 0.1},
}


@pytest.fixture(scope="module")
def small_config():
    return load_config(SMALL)


@pytest.fixture(scope="module")
def beds(small_config):
    return {s: build_bed(s, small_config, progress=False) for s in ("hill", "step")}


def profile(bed):
    return height_field(bed.positions, bed.radii, bed.length, bed.width, (12, 4))[1].mean(axis=1)


@pytest.mark.parametrize("scenario", ["hill", "step"])
def test_small_bed_settles_inside_the_domain(beds, small_config, scenario):
    bed = beds[scenario]
    assert 60 < bed.count < 400
    ke = bed.settle_kinetic_energy
    assert bed.kinetic_energy_per_particle() < small_config["bed"]["settle_kinetic_energy"]
    assert ke[-1] < 0.1 * ke.max()
    p, r = bed.positions, bed.radii
    tol = 0.3 * r
    assert np.all(p[:, 0] - r > -tol) and np.all(p[:, 0] + r < bed.length + tol)
    assert np.all(np.abs(p[:, 1]) + r < bed.width / 2 + tol)
    assert np.all(p[:, 2] - r > -tol)
    r0, spread = small_config["bed"]["radius"], small_config["bed"]["radius_dispersion"]
    assert r.min() >= r0 * (1 - spread) and r.max() <= r0 * (1 + spread) and r.std() > 0
    assert bed.settle_contacts[-1] > bed.count


def test_hill_is_higher_in_the_middle_and_step_on_one_side(beds, small_config):
    shape = small_config["scenarios"]
    h = profile(beds["hill"])
    assert 3 <= int(np.argmax(h)) <= 8
    assert h.max() > 1.4 * max(h[:3].mean(), h[-3:].mean())
    # Near the configured heights: the mound slumps somewhat, the rest holds its level.
    assert 0.6 * shape["hill"]["peak_height"] < h.max() < 1.3 * shape["hill"]["peak_height"]
    h = profile(beds["step"])
    assert h[:6].mean() > 1.5 * h[6:].mean()
    assert abs(h[:4].mean() - shape["step"]["high_height"]) < 0.3 * shape["step"]["high_height"]
    assert abs(h[-4:].mean() - shape["step"]["low_height"]) < 0.5 * shape["step"]["low_height"]


def test_build_is_deterministic_for_a_seed():
    tiny = load_config({**SMALL, "bed": {**SMALL["bed"], "length": 0.25, "width": 0.12}})
    first, again = (build_bed("step", tiny, progress=False) for _ in range(2))
    np.testing.assert_array_equal(again.positions, first.positions)
    np.testing.assert_array_equal(again.radii, first.radii)
    other = build_bed("step", {**tiny, "seed": tiny["seed"] + 1}, progress=False)
    assert other.positions.shape != first.positions.shape or not np.array_equal(
        other.positions, first.positions
    )


def test_make_world_restores_the_bed_and_takes_the_blade(beds, small_config):
    bed = beds["step"]
    world, ids = make_world(bed, small_config)
    assert set(ids) == {"ground", "wall_start", "wall_end", "wall_left", "wall_right"}
    np.testing.assert_array_equal(world.positions, bed.positions)
    np.testing.assert_array_equal(world.velocities, bed.velocities)
    np.testing.assert_allclose(world.masses, bed.masses)
    tip = start_tip(bed, small_config)
    blade = add_blade(world, tip, small_config)
    world.set_velocity(blade, [0.5, 0.0, 0.0])
    world.step(5)
    # The bed stays in place (it only creeps) while the blade travels behind the start wall.
    assert np.abs(world.positions - bed.positions).max() < 0.5 * bed.radii.min()
    g = small_config["blade"]
    np.testing.assert_allclose(
        world.body_position(blade),
        tip + [5 * 0.005 - g["thickness"] / 2, 0.0, g["height"] / 2],
        atol=1e-12,
    )


def test_make_world_counts_the_settled_bed_as_rested(beds, small_config):
    # with the zone, the bed beyond the zone around the blade sleeps after the first step
    # rather than after solver.active_zone.rest_time (0.1 s: 20 steps here) of whole solves;
    # a grain still moving stays awake, as one spinning about the vertical does: on the floor
    # nothing brakes that spin, and a pour can leave one so (the bed of this test did, on
    # one processor of two)
    zone = {"enabled": True, "margin": 0.05}
    config = load_config({**SMALL, "solver": {"dt": 0.005, "active_zone": zone}})
    bed = beds["hill"]
    rest_speed = config["solver"]["active_zone"]["rest_speed"]
    x = bed.positions[:, 0]
    spin = np.flatnonzero(x > 0.3)[0]
    w = bed.angular_velocities.copy()
    w[spin] = [0.0, 0.0, 4 * rest_speed / bed.radii[spin]]
    bed = dataclasses.replace(bed, angular_velocities=w)
    speed = np.maximum(
        np.linalg.norm(bed.velocities, axis=1), np.linalg.norm(w, axis=1) * bed.radii
    )
    still = speed <= rest_speed
    world, _ = make_world(bed, config)
    add_blade(world, start_tip(bed, config), config)
    world.step(1)
    far = x > 0.2  # beyond the blade's zone
    awake = world.state.public(world.state.awake)
    assert (far & still).sum() > 0.3 * bed.count
    assert not awake[far & still].any()
    assert awake[~still].all() and not still[spin]
    assert world.last_stats.active < 0.5 * bed.count


def test_unknown_scenario_is_refused(small_config):
    with pytest.raises(ConfigError, match="scenario 'dune' is not defined"):
        build_bed("dune", small_config, progress=False)


#: A bed of the user's terrain, as small as a test builds in seconds: a ridge by a profile and a
#: slope across the width by a heightmap (rows along x, columns along y).
TERRAIN = {
    "bed": {**SMALL["bed"], "length": 0.4, "width": 0.2},
    "scenarios": {
        "ridge": {
            "kind": "profile",
            "points": [[0.0, 0.05], [0.2, 0.16], [0.4, 0.05]],
            "goal_height": 0.05,
        },
        "bank": {"kind": "heightmap", "goal_height": 0.05},
    },
}


@pytest.fixture(scope="module")
def terrain_beds(tmp_path_factory):
    folder = tmp_path_factory.mktemp("terrain")
    np.save(folder / "bank.npy", np.array([[0.05, 0.16]] * 3))
    doc = {**TERRAIN, "scenarios": {**TERRAIN["scenarios"]}}
    doc["scenarios"]["bank"] = {**doc["scenarios"]["bank"], "file": str(folder / "bank.npy")}
    cfg = load_config(doc)
    return {s: build_bed(s, cfg, progress=False) for s in ("ridge", "bank")}


def test_a_profile_and_a_heightmap_are_built_to_their_shapes(terrain_beds):
    ridge, bank = terrain_beds["ridge"], terrain_beds["bank"]
    assert ridge.scenario == "ridge" and 60 < ridge.count < 400 and 60 < bank.count < 400
    _, h = height_field(ridge.positions, ridge.radii, ridge.length, ridge.width, (8, 4))
    along = h.mean(axis=1)
    assert along[3:5].mean() > 1.4 * max(along[0], along[-1])  # the ridge stands in the middle
    _, h = height_field(bank.positions, bank.radii, bank.length, bank.width, (4, 4))
    across = h.mean(axis=0)
    assert across[-1] > 1.4 * across[0]  # the heightmap's slope runs across the width, to +y
    assert len(bank.info["heightmap_sha256"]) == 64 and "heightmap_sha256" not in ridge.info


def test_a_bed_poured_with_the_zone_steps_fewer_contacts_and_settles_whole(beds, small_config):
    zoned = beds["hill"]  # bed.active_zone is on by default
    whole = build_bed(
        "hill",
        load_config({**SMALL, "bed": {**SMALL["bed"], "active_zone": False}}),
        progress=False,
    )
    pour = zoned.settle_time <= zoned.info["emission_time"]
    same = whole.settle_time <= zoned.info["emission_time"]
    # the grains at rest away from the strip sleep, their contacts left out of the solve
    assert zoned.settle_contacts[pour].sum() < 0.8 * whole.settle_contacts[same].sum()
    # after the last layer every grain is stepped for bed.awake_settle_time at least
    settle = small_config["bed"]["awake_settle_time"]
    assert zoned.info["time"] >= zoned.info["emission_time"] + settle
    assert abs(zoned.count - whole.count) < 0.1 * whole.count
    assert zoned.kinetic_energy_per_particle() < small_config["bed"]["settle_kinetic_energy"]


def test_the_pour_steps_with_every_solver_and_material_setting_of_the_config(monkeypatch):
    """The bed's job is given every solver setting but the blade's zone and the rest stop (the
    workflow reruns it when one changes): each must reach the world it pours with, the bed's
    own step, sweeps and zone switch in place of the solver's, and no rest stop."""
    given = {
        "solver": {
            "rest_tolerance": 5e-4,
            "relinearize": 0,
            "relinearize_above": 0.2,
            "tolerance": 2e-4,
            "relaxation": 0.9,
            "damping_steps": 3.0,
            "max_overlap": 0.4,
            "active_zone": {
                "enabled": False,
                "rest_speed": 0.03,
                "rest_time": 0.3,
                "wake_load": 3.0,
                "sleeper_compliance": 5.0,
            },
        },
        "material": {"friction": 0.5, "rolling_resistance": 0.05},
    }
    config = load_config({**SMALL, **given, "bed": {**SMALL["bed"], "active_zone": True}})
    stepped = []

    class Recording(World):
        def step(self, n=1):
            stepped.append(self.params)
            raise StopIteration  # the parameters are all this test needs

    monkeypatch.setattr(build, "World", Recording)
    with pytest.raises(StopIteration):
        build_bed("hill", config, progress=False)
    params = stepped[0]
    for key, value in given["solver"].items():
        if key not in ("active_zone", "rest_tolerance"):
            assert getattr(params, key) == value, key
    assert params.rest_tolerance == 0.0  # the pour runs its bed.iterations sweeps every step
    for key in ("rest_speed", "rest_time", "wake_load"):
        assert getattr(params, key) == given["solver"]["active_zone"][key], key
    for key, value in given["material"].items():
        assert getattr(params, key) == value, key
    assert params.active_zone  # bed.active_zone, not the blade's
    assert params.sleeper_compliance == 1.0  # the pour's sleepers stay rigid
    assert (params.dt, params.iterations) == (config["bed"]["dt"], config["bed"]["iterations"])
