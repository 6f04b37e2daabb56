"""The warm start: last step's multipliers found again after the spatial re-sort."""

import numpy as np

from dozerlab.ndem.warmstart import WarmStart


def _lam(normal: float, friction, rolling) -> list[float]:
    return [normal, *friction, *rolling]


def test_contacts_are_found_by_sphere_ids_after_the_slots_moved():
    warm = WarmStart()
    ids = np.array([0, 1, 2], dtype=np.int64)
    # sphere 0 on sphere 1 (slots 0, 1) and sphere 2 on body 0 (j = -1)
    ci, cj = np.array([0, 2]), np.array([1, -1])
    lam = np.array(
        [_lam(0.5, (0.1, 0.2, 0.0), (0.0, 0.3, 0.0)), _lam(0.7, (0.0, 0.4, 0.0), (0,) * 3)]
    )
    warm.store(ids, ci, cj, lam)

    moved = np.array([2, 1, 0], dtype=np.int64)  # the re-sort reversed the slots
    # the pair now comes as sphere 1 (slot 1) on sphere 0 (slot 2): its normal flipped; sphere 2
    # (slot 0) still meets body 0; sphere 1 meets body 0 for the first time
    ci2, cj2 = np.array([1, 0, 1]), np.array([2, -1, -1])
    normals = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    got = warm.lookup(moved, ci2, cj2, normals)
    np.testing.assert_allclose(got[0], _lam(0.5, (-0.1, -0.2, 0.0), (0.0, -0.3, 0.0)))
    np.testing.assert_allclose(got[1], lam[1])
    np.testing.assert_array_equal(got[2], np.zeros(7))


def test_vectors_are_projected_onto_the_new_tangent_plane():
    warm = WarmStart()
    ids = np.array([0], dtype=np.int64)
    warm.store(
        ids, np.array([0]), np.array([-1]), np.array([_lam(1.0, (0.1, 0.2, 0.0), (0.3, 0, 0))])
    )
    got = warm.lookup(ids, np.array([0]), np.array([-1]), np.array([[1.0, 0.0, 0.0]]))
    np.testing.assert_allclose(got[0], _lam(1.0, (0.0, 0.2, 0.0), (0.0, 0.0, 0.0)))


def test_the_spinning_rows_impulse_is_kept_only_with_spinning_resistance():
    warm = WarmStart()
    ids = np.array([0, 1], dtype=np.int64)
    # sphere 0 on sphere 1 along z, the rolling impulse with a part along the normal (spin)
    lam = np.array([_lam(1.0, (0.1, 0.0, 0.0), (0.0, 0.3, 0.2))])
    warm.store(ids, np.array([0]), np.array([1]), lam)
    up = np.array([[0.0, 0.0, 1.0]])
    free = warm.lookup(ids, np.array([0]), np.array([1]), up)
    np.testing.assert_allclose(free[0], _lam(1.0, (0.1, 0.0, 0.0), (0.0, 0.3, 0.0)))
    kept = warm.lookup(ids, np.array([0]), np.array([1]), up, spin=True)
    np.testing.assert_allclose(kept[0], lam[0])
    # the slots swapped: the impulse flips with the normal, so the spin about it is the same
    swapped = warm.lookup(ids, np.array([1]), np.array([0]), -up, spin=True)
    np.testing.assert_allclose(swapped[0], _lam(1.0, (-0.1, 0.0, 0.0), (0.0, -0.3, -0.2)))
    assert swapped[0, 4:] @ -up[0] == kept[0, 4:] @ up[0]


def test_loaded_contacts_among_sleeping_spheres_are_carried_until_one_wakes():
    warm = WarmStart()
    ids = np.array([0, 1, 2, 3], dtype=np.int64)
    # 0–1 loaded, 2–3 unloaded (speculative), 1 on body 0
    ci, cj = np.array([0, 2, 1]), np.array([1, 3, -1])
    lam = np.array(
        [
            _lam(0.5, (0, 0.1, 0), (0,) * 3),
            _lam(0.0, (0,) * 3, (0,) * 3),
            _lam(0.9, (0, 0.2, 0), (0,) * 3),
        ]
    )
    warm.store(ids, ci, cj, lam)
    # every sphere asleep: the step has no contacts, the loaded ones are kept
    nothing = np.zeros(0, dtype=np.int64)
    warm.store(ids, nothing, nothing, np.zeros((0, 7)), np.ones(4, dtype=np.bool_))
    normals = np.array([[1.0, 0, 0], [1.0, 0, 0], [0, 0, 1.0]])
    got = warm.lookup(ids, ci, cj, normals)
    np.testing.assert_array_equal(got[0], lam[0])
    np.testing.assert_array_equal(got[1], np.zeros(7))  # unloaded: dropped
    np.testing.assert_array_equal(got[2], lam[2])
    # sphere 0 wakes, and its contact with 1 is not in this step's list: dropped
    warm.store(ids, nothing, nothing, np.zeros((0, 7)), np.array([False, True, True, True]))
    got = warm.lookup(ids, ci, cj, normals)
    np.testing.assert_array_equal(got[0], np.zeros(7))
    np.testing.assert_array_equal(got[2], lam[2])


def test_held_sums_the_normal_impulses_a_step_leaves_out():
    warm = WarmStart()
    ids = np.array([0, 1, 2], dtype=np.int64)
    # 0–1 and 1–2 loaded, 2 on body 0
    ci, cj = np.array([0, 1, 2]), np.array([1, 2, -1])
    lam = np.array(
        [_lam(0.5, (0,) * 3, (0,) * 3), _lam(0.25, (0,) * 3, (0,) * 3)] * 1
        + [_lam(2.0, (0,) * 3, (0,) * 3)]
    )
    warm.store(ids, ci, cj, lam)
    # 0 awake: its contact is solved by the step, not held
    np.testing.assert_allclose(warm.held(np.array([False, True, True])), [0.0, 0.25, 2.25])
