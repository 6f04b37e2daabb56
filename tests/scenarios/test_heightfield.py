"""The bed's height field: the covering spheres' surface above each cell centre."""

import numpy as np
import pytest

from dozerlab.scenarios.heightfield import height_field


def test_one_sphere_gives_its_cap_over_the_cells_it_covers_and_ground_elsewhere():
    # 1 m × 0.4 m in 10 × 4 cells of 0.1 m: centres at x = 0.05, 0.15, …; y = -0.15, …, 0.15
    x, h = height_field(np.array([[0.45, 0.05, 0.3]]), np.array([0.12]), 1.0, 0.4, (10, 4))
    np.testing.assert_allclose(x, np.arange(10) * 0.1 + 0.05)
    expect = np.zeros((10, 4))
    for i, cx in enumerate(x):
        for j, cy in enumerate(np.arange(4) * 0.1 - 0.15):
            q = 0.12**2 - (cx - 0.45) ** 2 - (cy - 0.05) ** 2
            if q >= 0:
                expect[i, j] = 0.3 + np.sqrt(q)
    np.testing.assert_allclose(h, expect, atol=1e-12)
    assert h[4, 2] == pytest.approx(0.3 + 0.12)  # the cell right under the centre: the top
    assert np.count_nonzero(h) == 5  # its own cell and the four 0.1 m away (diagonals: 0.14 m)


def test_the_highest_surface_wins_and_an_empty_bed_is_flat():
    pos = np.array([[0.05, 0.0, 0.1], [0.05, 0.0, 0.25]])
    _, h = height_field(pos, np.array([0.05, 0.05]), 0.1, 0.1, (1, 1))
    assert h[0, 0] == pytest.approx(0.3)
    _, flat = height_field(np.zeros((0, 3)), np.zeros(0), 1.0, 1.0, (3, 2))
    np.testing.assert_array_equal(flat, np.zeros((3, 2)))


@pytest.mark.parametrize(
    ("size", "subdivisions", "message"),
    [
        ((1.0, 1.0), (0, 4), r"trajectory.subdivisions must be >= 1 in both directions"),
        ((1.0, 0.0), (4, 4), r"bed length and width must be > 0 m, got 1.0, 0.0"),
    ],
)
def test_bad_grids_are_refused(size, subdivisions, message):
    with pytest.raises(ValueError, match=message):
        height_field(np.zeros((1, 3)), np.ones(1), *size, subdivisions)
