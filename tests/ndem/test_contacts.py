"""The narrow phase against planes and boxes, and the loads the particles put on the bodies."""

import numpy as np
import pytest

from dozerlab.ndem.bodies import Bodies
from dozerlab.ndem.contacts import (
    N0,
    NCOL,
    RI,
    body_contacts,
    body_contacts_parallel,
    body_contacts_serial,
    body_loads,
)

R = 0.1


def _contacts(bodies: Bodies, centres, margin: float = 0.0):
    pos = np.array(centres, dtype=float)
    n = len(pos)
    return body_contacts(
        pos,
        np.full(n, R),
        np.full(n, margin),
        bodies.kind,
        bodies.center,
        bodies.rotations(),
        bodies.half,
        bodies.normal,
    )


def test_plane_overlap_is_the_radius_minus_the_height_within_the_margin():
    b = Bodies()
    b.add_plane((0, 0, 1.0), (0, 0, 1), 0.5)
    si, sb, nrm, gap = _contacts(b, [[0, 0, 1.08], [5, 0, 1.5], [0, 0, 1.105]], margin=0.01)
    assert si.tolist() == [0, 2] and sb.tolist() == [0, 0]  # the far sphere has none
    np.testing.assert_allclose(gap, [0.02, -0.005])  # the second a speculative gap
    np.testing.assert_array_equal(nrm, [[0, 0, 1], [0, 0, 1]])


def test_box_face_edge_and_inside_overlaps():
    b = Bodies()
    b.add_box((0, 0, 0), (0.5, 0.5, 0.5), False, 0.5, None)
    _, _, nrm, gap = _contacts(b, [[0.55, 0, 0], [0.55, 0.55, 0], [0, 0, -0.45]])
    # a face: 0.05 m in; an edge: 0.05·√2 m from it; a centre inside leaves by the nearest face
    np.testing.assert_allclose(gap, [R - 0.05, R - 0.05 * np.sqrt(2), R + 0.05])
    np.testing.assert_allclose(nrm, [[1, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], [0, 0, -1]])


def test_a_turned_box_is_tested_in_its_own_axes():
    b = Bodies()
    c = np.cos(np.pi / 4)
    b.add_box((0, 0, 0), (0.5, 0.2, 0.5), False, 0.5, (c, 0, 0, c))  # its y along world x
    _, _, nrm, gap = _contacts(b, [[0.25, 0, 0]])
    assert gap[0] == pytest.approx(R - 0.05)
    np.testing.assert_allclose(nrm[0], [1, 0, 0], atol=1e-12)


def test_loads_are_the_impulses_over_the_step_with_their_moments():
    h, lam = 0.01, 0.01  # a normal impulse of 0.01 N·s over 0.01 s: 1 N
    cd = np.zeros((1, NCOL))
    cd[0, N0 : N0 + 3] = [0, 0, 1]
    cd[0, RI] = R
    multipliers = np.zeros((1, 7))
    multipliers[0, 0] = lam
    pos = np.array([[0.3, 0.0, R]])
    force, torque = body_loads(
        np.array([0]), np.array([-2]), cd, multipliers, pos, np.zeros((2, 3)), 2, h
    )
    np.testing.assert_allclose(force, [[0, 0, 0], [0, 0, -1.0]])  # body 1 (cj = -2) pushed down
    # about body 1's centre: the contact point (0.3, 0, 0) × (0, 0, -1) N
    np.testing.assert_allclose(torque, [[0, 0, 0], [0, 0.3, 0]])


def test_one_pass_body_contacts_equal_count_then_fill():
    b = Bodies()
    b.add_plane((0, 0, 0.0), (0, 0, 1), 0.5)
    b.add_plane((1.0, 0, 0), (-1, 0, 0), 0.5)
    b.add_box((0.5, 0.5, 0.3), (0.2, 0.1, 0.3), False, 0.5, None)
    rng = np.random.default_rng(2)
    n = 2000
    args = (
        rng.uniform(0, 1, (n, 3)),
        rng.uniform(0.02, 0.05, n),
        rng.uniform(0.0, 0.02, n),
        b.kind,
        b.center,
        b.rotations(),
        b.half,
        b.normal,
        rng.uniform(size=n) < 0.5,
    )
    serial = body_contacts_serial(*args)
    parallel = body_contacts_parallel(*args)
    assert set(serial[1].tolist()) == {0, 1, 2}  # every body has hits
    assert np.all(args[-1][serial[0]])  # of the spheres awake only
    for x, y in zip(serial, parallel, strict=True):
        np.testing.assert_array_equal(x, y)
