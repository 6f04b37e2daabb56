"""Field sampling: algorithm-1 weights, mass conservation, uniform velocity."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.fields.sampling import SamplingGrid

GRID = SamplingGrid(bins=(4, 3, 2), bin_size=(0.1, 0.2, 0.25), lower=(0.0, -0.3, -0.1))
TIP = np.array([1.0, 0.5, 0.2])


def test_particle_inside_one_bin_has_weight_one():
    # bin (2, 1, 0) has centre tip + (0.25, 0.0, 0.025); a radius-0.03 sphere there fits inside it
    w = GRID.weights(TIP + [0.25, 0.01, 0.02], [0.03], TIP)
    assert w[2, 1, 0] == pytest.approx(1.0)
    assert w.sum() == pytest.approx(1.0)
    assert np.count_nonzero(w) == 1


def test_particle_straddling_bins_has_weights_summing_to_one():
    # on the edge between x bins 1|2 (x = 0.2) and z bins 0|1 (z = 0.15): split 50/50 in x, 40/60 in z
    w = GRID.weights(TIP + [0.2, 0.0, 0.152], [0.01], TIP)
    assert w.sum() == pytest.approx(1.0)
    assert np.count_nonzero(w) == 4
    assert w[1, 1, 0] == pytest.approx(0.5 * 0.4)
    assert w[2, 1, 1] == pytest.approx(0.5 * 0.6)


def test_particle_wider_than_bins_keeps_unit_weight():
    w = GRID.weights(TIP + [0.2, 0.0, 0.15], [0.12], TIP)
    assert w.sum() == pytest.approx(1.0)


def test_particle_outside_has_zero_weight():
    assert GRID.weights(TIP + [-0.2, 0.0, 0.1], [0.05], TIP).sum() == 0.0
    assert GRID.weights(TIP + [0.2, 0.0, -0.16], [0.05], TIP).sum() == 0.0  # just below the volume


def _bed(n: int, rng: np.random.Generator, lo, hi, r: float):
    pos = rng.uniform(lo, hi, size=(n, 3))
    radii = rng.uniform(0.7 * r, r, size=n)
    return pos, radii, 2600 * 4 / 3 * np.pi * radii**3


def test_density_conserves_mass_inside_volume():
    grid = SamplingGrid.from_config(load_config({"sampling": {"bins": [12, 10, 6]}}))
    tip = np.array([0.5, 0.0, 0.2])
    rng = np.random.default_rng(1)
    r = 0.04
    extent = np.array(grid.bins) * grid.bin_size
    lo = tip + grid.lower
    pos, radii, masses = _bed(3000, rng, lo + r, lo + extent - r, r)  # wholly inside
    _, rho = grid.sample(pos, np.zeros_like(pos), radii, masses, tip)
    assert float(rho.sum(dtype=np.float64)) * grid.bin_volume == pytest.approx(
        masses.sum(), rel=1e-5
    )
    # particles wholly outside add nothing
    out, r_out, m_out = _bed(500, rng, lo + extent + r, lo + extent + 1.0, r)
    _, rho2 = grid.sample(
        np.vstack([pos, out]), np.zeros((3500, 3)), np.r_[radii, r_out], np.r_[masses, m_out], tip
    )
    np.testing.assert_array_equal(rho2, rho)


def test_uniform_velocity_is_recovered_in_every_occupied_bin():
    grid = SamplingGrid.from_config(load_config({"sampling": {"bins": [8, 6, 4]}}))
    tip = np.zeros(3)
    rng = np.random.default_rng(2)
    lo = tip + grid.lower
    pos, radii, masses = _bed(
        800, rng, lo - 0.1, lo + np.array(grid.bins) * grid.bin_size + 0.1, 0.05
    )
    v = np.array([0.9, -0.2, 0.05])
    vel, rho = grid.sample(pos, np.tile(v, (len(pos), 1)), radii, masses, tip)
    occupied = rho > 0
    assert occupied.sum() > 0.9 * occupied.size
    np.testing.assert_allclose(vel[occupied], np.broadcast_to(v, vel[occupied].shape), rtol=1e-5)
    assert not vel[~occupied].any()


def test_several_velocities_in_one_pass_are_each_sampled_bit_for_bit():
    # the reduced loop samples a grain's velocity and its flow together
    rng = np.random.default_rng(4)
    lo = TIP + GRID.lower
    pos, radii, masses = _bed(300, rng, lo - 0.1, lo + np.array(GRID.bins) * GRID.bin_size, 0.04)
    v, w = rng.normal(size=(2, len(pos), 3))
    (vel_v, vel_w), rho = GRID.sample_velocities(pos, (v, w), radii, masses, TIP)
    for field, one in ((vel_v, v), (vel_w, w)):
        alone, rho_alone = GRID.sample(pos, one, radii, masses, TIP)
        np.testing.assert_array_equal(field, alone)
        np.testing.assert_array_equal(rho, rho_alone)


def test_config_grid_spans_blade_and_below_edge():
    cfg = load_config(
        {
            "bed": {"width": 1.6},
            "blade": {"width": 1.0, "height": 0.5},
            "sampling": {"length": 1.2, "below_edge": 0.1, "bins": [24, 20, 12]},
        }
    )
    grid = SamplingGrid.from_config(cfg)
    x, y, z = grid.centres()
    assert (x[0], x[-1]) == pytest.approx((0.025, 1.175))
    assert (y[0] + y[-1], y[-1] - y[0]) == pytest.approx((0.0, 0.95))
    assert z[0] - grid.bin_size[2] / 2 == pytest.approx(-0.1)
    assert z[-1] + grid.bin_size[2] / 2 == pytest.approx(0.5)


def test_behind_side_and_above_bins_extend_the_volume_around_the_blade_part():
    cfg = load_config(
        {
            "blade": {"width": 0.7, "height": 0.4},
            "sampling": {
                "length": 0.8,
                "below_edge": 0.1,
                "bins": [16, 12, 8],
                "behind_bins": 8,
                "side_bins": 3,
                "above_bins": 2,
            },
        }
    )
    grid = SamplingGrid.from_config(cfg)
    assert grid.bins == (24, 18, 10) and grid.blade_part == (8, 3, 15, 8)
    assert grid.bin_size == pytest.approx((0.05, 0.7 / 12, 0.5 / 8))
    x, y, z = grid.centres()
    x0, y0, y1, z1 = grid.blade_part
    # the blade part is the grid without those bins: in front of the face, across the blade
    assert (x[0] - 0.025, x[x0] - 0.025, x[-1] + 0.025) == pytest.approx((-0.4, 0.0, 0.8))
    assert (y[y0] - grid.bin_size[1] / 2, y[y1 - 1] + grid.bin_size[1] / 2) == pytest.approx(
        (-0.35, 0.35)
    )
    assert z[z1 - 1] + grid.bin_size[2] / 2 == pytest.approx(0.4)
    assert y[0] - grid.bin_size[1] / 2 == pytest.approx(-0.35 - 3 * 0.7 / 12)
    assert z[-1] + grid.bin_size[2] / 2 == pytest.approx(0.4 + 2 * 0.5 / 8)
    assert grid.attrs() == {
        "bins": [24, 18, 10],
        "bin_size": list(grid.bin_size),
        "blade_part": [8, 3, 15, 8],
    }
    plain = SamplingGrid.from_config(load_config({"sampling": {"bins": [16, 12, 8]}}))
    assert plain.blade_part == (0, 0, 12, 8)
    with pytest.raises(ValueError, match="blade part"):
        SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0), side_bins=2)


def test_bad_shapes_are_refused():
    with pytest.raises(ValueError, match="positions must be"):
        GRID.sample(np.zeros((3, 2)), np.zeros((3, 3)), np.ones(3), np.ones(3), TIP)
