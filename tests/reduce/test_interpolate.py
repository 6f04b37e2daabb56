"""Trilinear interpolation of a bin-centred field at particle positions."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.reduce.interpolate import interpolate

LOWER = np.array([0.0, -0.3, -0.1])
SIZE = np.array([0.1, 0.1, 0.05])
BINS = (5, 6, 4)


def centres():
    return np.meshgrid(
        *[lo + (np.arange(n) + 0.5) * s for lo, n, s in zip(LOWER, BINS, SIZE, strict=True)],
        indexing="ij",
    )


def inside_points(n=500, margin=0.5):
    """Points between the first and last bin centres (the trilinear interior)."""
    rng = np.random.default_rng(0)
    lo = LOWER + margin * SIZE
    hi = LOWER + (np.array(BINS) - margin) * SIZE
    return rng.uniform(lo, hi, size=(n, 3))


@pytest.mark.parametrize("weighted", [False, True])
def test_a_uniform_field_comes_back_exactly_everywhere(weighted):
    field = np.broadcast_to(np.array([0.3, -0.2, 0.05]), (*BINS, 3))
    rho = np.random.default_rng(1).uniform(0, 2600, BINS) if weighted else None
    pts = np.random.default_rng(2).uniform(LOWER - 0.2, LOWER + 0.8, size=(400, 3))
    out = interpolate(field, pts, LOWER, SIZE, weight=rho)
    np.testing.assert_array_equal(out, np.broadcast_to([0.3, -0.2, 0.05], out.shape))


def test_a_linear_field_to_round_off_between_centres_and_clamped_outside():
    cx, cy, cz = centres()
    a = np.array([[1.0, -2.0, 0.5], [0.3, 0.0, 4.0], [-1.5, 0.7, 2.0]])
    field = np.stack([a[c, 0] * cx + a[c, 1] * cy + a[c, 2] * cz + c for c in range(3)], -1)
    pts = inside_points()
    expected = pts @ a.T + np.arange(3)
    np.testing.assert_allclose(interpolate(field, pts, LOWER, SIZE), expected, atol=1e-12)
    # with a uniform weight the mass-weighted blend is the same
    np.testing.assert_allclose(
        interpolate(field, pts, LOWER, SIZE, weight=np.full(BINS, 1500.0)), expected, atol=1e-12
    )
    # a point beyond the last centre along x takes that centre's value along x
    edge = np.array([[LOWER[0] + 4.9 * SIZE[0], 0.0, 0.0]])
    clamped = edge.copy()
    clamped[0, 0] = LOWER[0] + 4.5 * SIZE[0]
    np.testing.assert_allclose(
        interpolate(field[..., 0], edge, LOWER, SIZE),
        interpolate(field[..., 0], clamped, LOWER, SIZE),
    )


def test_empty_bins_do_not_slow_the_surface_with_a_density_weight():
    field = np.zeros((*BINS, 3))
    field[:, :, :2, 0] = 1.0  # material moving at 1 m/s in the lower two layers
    rho = np.zeros(BINS)
    rho[:, :, :2] = 2000.0
    z_between = LOWER[2] + 2.0 * SIZE[2]  # halfway between layer 1 (full) and layer 2 (empty)
    pt = np.array([[0.25, 0.0, z_between]])
    assert interpolate(field, pt, LOWER, SIZE)[0, 0] == pytest.approx(0.5)
    assert interpolate(field, pt, LOWER, SIZE, weight=rho)[0, 0] == pytest.approx(1.0)


def test_shapes_are_checked():
    with pytest.raises(ValueError, match="field must be"):
        interpolate(np.zeros((2, 2)), np.zeros((1, 3)), LOWER, SIZE)
    with pytest.raises(ValueError, match="weight must have shape"):
        interpolate(np.zeros((*BINS, 3)), np.zeros((1, 3)), LOWER, SIZE, weight=np.ones((2, 2, 2)))


@pytest.mark.parametrize("channels", [1, 2, 4, 7])
@pytest.mark.parametrize("weighted", [False, True])
def test_each_channel_is_blended_alone_whatever_their_count(channels, weighted):
    # the blend runs three channels at a time: any other count gives each channel what it
    # gives alone, to the bit
    rng = np.random.default_rng(channels)
    field = rng.normal(size=(*BINS, channels))
    rho = rng.uniform(0, 2600, BINS) if weighted else None
    pts = rng.uniform(LOWER - 0.1, LOWER + 0.6, size=(300, 3))
    out = interpolate(field, pts, LOWER, SIZE, weight=rho)
    assert out.shape == (300, channels)
    for c in range(channels):
        np.testing.assert_array_equal(out[:, c], interpolate(field[..., c], pts, LOWER, SIZE, rho))
