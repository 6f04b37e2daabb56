"""Position projection: exact separation, bodies pushed out of, a free pair's centre of mass."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce.compare import body_penetration
from dozerlab.reduce.projection import METHODS, Bodies, project


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


def test_bad_arguments_are_refused():
    x = np.zeros((1, 3))
    with pytest.raises(ValueError, match="projection method"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=1, method="sor")
    with pytest.raises(ValueError, match="iterations"):
        project(x, np.ones(1), np.ones(1), bodies(), iterations=-1)
