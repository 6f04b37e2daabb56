"""Planes and boxes: their table, rotations and the kinematic boxes' motion."""

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies, nonnegative, quat_to_matrix, vec3
from dozerlab.ndem.contacts import BOX, PLANE


def test_a_quarter_turn_about_z_maps_x_to_y():
    c = np.cos(np.pi / 4)
    rot = quat_to_matrix(np.array([[c, 0.0, 0.0, c], [1.0, 0.0, 0.0, 0.0]]))
    np.testing.assert_allclose(rot[0], [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-15)
    np.testing.assert_array_equal(rot[1], np.eye(3))


def test_bodies_share_one_numbering_and_planes_get_unit_normals():
    b = Bodies()
    ground = b.add_plane((0, 0, 0), (0, 0, 2.0), 0.4)
    box = b.add_box((1, 0, 0.5), (0.1, 0.2, 0.3), True, 0.6, (2.0, 0, 0, 0))
    assert (ground, box, len(b)) == (0, 1, 2)
    assert b.kind.tolist() == [PLANE, BOX] and b.kinematic.tolist() == [False, True]
    np.testing.assert_array_equal(b.normal[0], [0, 0, 1])
    np.testing.assert_array_equal(b.quat[1], [1, 0, 0, 0])  # normalised
    assert b.force.shape == b.torque.shape == (2, 3)
    assert b.check_kinematic(1) == 1
    with pytest.raises(ValueError, match="body 0 is static"):
        b.check_kinematic(0)
    with pytest.raises(ValueError, match=r"body must be a body id in \[0, 1\], got 2"):
        b.check(2)


def test_a_kinematic_box_moves_and_turns_by_its_velocities():
    b = Bodies()
    b.add_plane((0, 0, 0), (0, 0, 1), 0.4)
    box = b.add_box((0, 0, 0), (0.1, 0.1, 0.1), True, 0.5, None)
    b.vel[box] = [1.0, 0.0, -0.5]
    b.ang[box] = [0.0, 0.0, 0.2]
    for _ in range(1000):
        b.integrate(0.001)
    np.testing.assert_allclose(b.center[box], [1.0, 0.0, -0.5], atol=1e-12)
    np.testing.assert_array_equal(b.center[0], [0, 0, 0])  # static: left alone
    q = b.quat[box]
    assert 2 * np.arctan2(q[3], q[0]) == pytest.approx(0.2, rel=1e-6)  # ω t about z
    assert np.linalg.norm(q) == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda b: b.add_plane((0, 0, 0), (0, 0, 0), 0.5), "normal must be a non-zero vector"),
        (lambda b: b.add_plane((0, 0), (0, 0, 1), 0.5), "point must be 3 finite numbers"),
        (lambda b: b.add_plane((0, 0, 0), (0, 0, 1), -0.1), "friction must be a finite number"),
        (lambda b: b.add_box((0, 0, 0), (1, 0, 1), True, 0.5, None), "half_extents must be > 0"),
        (
            lambda b: b.add_box((0, 0, 0), (1, 1, 1), True, 0.5, (0, 0, 0, 0)),
            "orientation must be a non-zero quaternion",
        ),
    ],
)
def test_bad_bodies_are_refused_by_name(call, message):
    b = Bodies()
    with pytest.raises(ValueError, match=message):
        call(b)
    assert len(b) == 0


def test_vectors_and_nonnegative_numbers():
    assert vec3("v", [1, 2, 3]).dtype == np.float64
    assert nonnegative("mu", 0) == 0.0
    with pytest.raises(ValueError, match="mu must be a finite number >= 0, got -1"):
        nonnegative("mu", -1)
