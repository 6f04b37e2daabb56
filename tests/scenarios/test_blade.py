"""The blade: its geometry about the tip, its box in a world, and where it starts."""

import dataclasses

import numpy as np
import pytest

from dozerlab.ndem import World
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.blade import (
    BladeGeometry,
    add_blade,
    centre_to_tip,
    start_tip,
    tip_to_centre,
)


def test_geometry_from_config_and_tip_centre_conversion(config):
    g = BladeGeometry.from_config(config)
    b = config["blade"]
    assert (g.width, g.height, g.thickness, g.start_gap) == (
        b["width"],
        b["height"],
        b["thickness"],
        b["start_gap"],
    )
    tips = np.array([[0.3, 0.0, 0.2], [1.0, 0.1, 0.0]])
    centres = tip_to_centre(tips, g)
    np.testing.assert_allclose(centres, tips + [-g.thickness / 2, 0.0, g.height / 2])
    np.testing.assert_allclose(centre_to_tip(centres, g), tips)
    np.testing.assert_allclose(g.half_extents, [g.thickness / 2, g.width / 2, g.height / 2])
    np.testing.assert_allclose(g.tip_offset, centres[0] - tips[0])


def test_blade_is_a_kinematic_box_that_moves_as_driven(config):
    world = World.from_config(config)
    tip = np.array([0.2, 0.0, 0.3])
    blade = add_blade(world, tip, config)
    g = BladeGeometry.from_config(config)
    np.testing.assert_allclose(centre_to_tip(world.body_position(blade), g), tip)
    v = np.array([1.0, 0.0, -0.2])
    world.set_velocity(blade, v)
    world.step(5)  # kinematic: gravity and contacts do not move it
    dt = config["solver"]["dt"]
    np.testing.assert_allclose(
        centre_to_tip(world.body_position(blade), g), tip + 5 * dt * v, atol=1e-12
    )


def test_a_grain_resting_on_the_blade_loads_it_with_its_weight(config):
    # the converged static load: the blade stands, so this is a rest step, solved in full here
    cfg = {
        **config,
        "solver": {**config["solver"], "dt": 0.005, "iterations": 50, "rest_tolerance": 0.0},
    }
    world = World.from_config(cfg)
    g = BladeGeometry.from_config(cfg)
    tip = np.array([0.0, 0.0, 0.5])
    blade = add_blade(world, tip, cfg)
    r, y0 = 0.05, 0.1
    on_top = tip + [-g.thickness / 2, y0, g.height + r]
    world.add_spheres(on_top[None, :], np.array([r]))
    world.step(200)
    mass = cfg["material"]["density"] * 4 / 3 * np.pi * r**3
    weight = mass * 9.81
    np.testing.assert_allclose(world.force_on(blade), [0.0, 0.0, -weight], atol=1e-3 * weight)
    # about the tip, the weight on the top face at lateral offset y0 acts with lever (−t/2, y0, h)
    torque = world.torque_on(blade, about=tip)
    np.testing.assert_allclose(
        torque, [-y0 * weight, -g.thickness / 2 * weight, 0.0], atol=2e-3 * weight
    )


def _bed(positions, radius=0.05):
    n = len(positions)
    return Bed(
        "step",
        2.0,
        1.0,
        np.asarray(positions, dtype=np.float64).reshape(n, 3),
        np.full(n, radius),
        np.ones(n),
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        {"density": 2600.0},
        0,
    )


def test_start_tip_behind_an_empty_bed_is_on_the_ground(config):
    gap = config["blade"]["start_gap"]
    np.testing.assert_allclose(start_tip(_bed([]), config), [-gap, 0.0, 0.0])


def test_start_tip_is_level_with_the_front_face_and_behind_the_rearmost_grain(config):
    gap = config["blade"]["start_gap"]
    # a 0.45 m high column at the front, a taller one further back than one diameter
    front = [[0.05, 0.0, z] for z in (0.05, 0.15, 0.25, 0.35)]
    bed = _bed([*front, [0.5, 0.0, 0.95]])
    np.testing.assert_allclose(start_tip(bed, config), [-gap, 0.0, 0.4])
    behind = dataclasses.replace(bed, positions=bed.positions - [0.1, 0.0, 0.0])
    np.testing.assert_allclose(start_tip(behind, config), [-0.1 - gap, 0.0, 0.4])


@pytest.mark.parametrize("gap", [0.0, 0.25])
def test_start_gap_is_the_clearance_to_the_bed(config, gap):
    cfg = {**config, "blade": {**config["blade"], "start_gap": gap}}
    tip = start_tip(_bed([[0.05, 0.0, 0.05]]), cfg)
    assert tip[0] == pytest.approx(-gap)
