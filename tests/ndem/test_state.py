"""A World's state: spheres in slot order, mapped to and from sphere ids."""

import numpy as np
import pytest

from dozerlab.ndem.state import SPHERE_FIELDS, WorldState


def _three() -> WorldState:
    s = WorldState()
    n = 3
    s.append(
        x=np.arange(9.0).reshape(3, 3),
        v=np.zeros((n, 3)),
        w=np.zeros((n, 3)),
        r=np.array([0.1, 0.2, 0.3]),
        m=np.ones(n),
        mu=np.full(n, 0.5),
        mur=np.zeros(n),
        id=np.arange(n, dtype=np.int64),
    )
    return s


def test_reordering_keeps_ids_with_their_spheres():
    s = _three()
    assert s.n == 3 and s.time == 0.0 and s.step_count == 0
    s.reorder(np.array([2, 0, 1]))
    assert s.id.tolist() == [2, 0, 1] and s.r.tolist() == [0.3, 0.1, 0.2]
    assert s.slots().tolist() == [1, 2, 0]  # sphere 0 is in slot 1, …
    np.testing.assert_array_equal(s.public(s.r), [0.1, 0.2, 0.3])
    np.testing.assert_array_equal(s.public(s.x), np.arange(9.0).reshape(3, 3))
    assert all(getattr(s, f).flags.c_contiguous for f in SPHERE_FIELDS)


def test_a_mask_drops_slots_and_append_adds_at_the_end():
    s = _three()
    s.reorder(np.array([True, False, True]))
    assert s.id.tolist() == [0, 2] and s.x.shape == (2, 3)
    s.append(**{f: getattr(s, f)[:1] for f in SPHERE_FIELDS})
    assert s.n == 3 and s.r.tolist() == [0.1, 0.3, 0.1]


def test_the_one_pass_gather_is_numpy_fancy_indexing_and_checks_the_slots():
    s = _three()
    ref = {f: getattr(s, f)[[1, 2, 0]] for f in SPHERE_FIELDS}
    s.reorder(np.array([1, 2, 0]))
    for f in SPHERE_FIELDS:
        np.testing.assert_array_equal(getattr(s, f), ref[f])
        assert getattr(s, f).dtype == ref[f].dtype
    with pytest.raises(IndexError, match="slot out of range"):
        s.reorder(np.array([0, 1, 3]))
