import numpy as np
import pytest

from dozerlab.scenarios.filters import gated_average, moving_average, moving_std, smooth_height


@pytest.mark.parametrize("width", [1, 2, 4, 8, 64])
def test_flat_signal_stays_flat(width):
    flat = np.full(200, 0.37)
    np.testing.assert_allclose(moving_average(flat, width), flat, atol=1e-14)
    np.testing.assert_allclose(moving_std(flat, width), 0.0, atol=1e-7)


def test_full_chain_keeps_flat_and_linear_signals():
    np.testing.assert_allclose(smooth_height(np.full(300, 0.5)), 0.5, atol=1e-12)
    ramp = np.linspace(0.1, 0.9, 300)
    # Centred windows do not shift a ramp away from its ends.
    np.testing.assert_allclose(smooth_height(ramp)[70:230], ramp[70:230], atol=1e-9)


def test_step_keeps_its_edge():
    step = np.r_[np.full(150, 0.6), np.full(150, 0.15)]
    out = smooth_height(step)
    # Exact far from the edge (beyond the widest window), within 1 cm up to 8 points from it.
    np.testing.assert_allclose(out[:100], 0.6, atol=1e-12)
    np.testing.assert_allclose(out[200:], 0.15, atol=1e-12)
    np.testing.assert_allclose(out[:142], 0.6, atol=0.01)
    np.testing.assert_allclose(out[158:], 0.15, atol=0.01)
    # The drop stays sharp: from 90 % to 10 % of its height within a few points.
    above = np.flatnonzero(out > 0.15 + 0.9 * 0.45)
    below = np.flatnonzero(out < 0.15 + 0.1 * 0.45)
    assert below[0] - above[-1] <= 6


def test_noise_is_reduced_and_mean_kept():
    rng = np.random.default_rng(1)
    noisy = 0.3 + 0.02 * rng.standard_normal(400)
    out = smooth_height(noisy)
    assert out.std() < 0.25 * noisy.std()
    assert abs(out.mean() - noisy.mean()) < 0.005


def test_gate_leaves_steep_regions_alone():
    slope = np.r_[np.zeros(50), np.linspace(0, 1, 20), np.ones(50)]
    out = gated_average(slope, 8, 0.1)
    np.testing.assert_array_equal(out[55:65], slope[55:65])


@pytest.mark.parametrize("bad", [np.zeros((3, 3)), np.zeros(0)])
def test_bad_profiles_are_refused(bad):
    with pytest.raises(ValueError, match="1-D"):
        moving_average(bad, 2)


def test_bad_width_and_threshold_are_refused():
    with pytest.raises(ValueError, match="width"):
        moving_average(np.ones(5), 0)
    with pytest.raises(ValueError, match="threshold"):
        gated_average(np.ones(5), 8, 0.0)
