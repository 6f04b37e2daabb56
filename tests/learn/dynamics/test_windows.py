import numpy as np
import pytest

from dozerlab.learn.data import split_train_validation
from dozerlab.learn.dynamics.windows import frame_of, windows
from dozerlab.runtime import DozerlabError

from .helpers import translating


def test_windows_never_cross_stores_and_have_their_targets():
    stores = [translating(i, rows=30 + 5 * i) for i in range(3)]
    w = windows(stores, history=3, horizon=2)
    starts = np.cumsum([0] + [s.density.shape[0] for s in stores])
    for idx, k in zip(w.index, w.store_of, strict=True):
        assert starts[k] <= idx - 2 and idx + 2 < starts[k + 1]
    # every window that fits is there: rows - history - horizon + 1 per store
    assert len(w) == sum(s.density.shape[0] - 3 - 2 + 1 for s in stores)


def test_validation_blocks_and_training_windows_are_disjoint():
    stores = [translating(i, rows=120) for i in range(2)]
    train, val = split_train_validation(windows(stores, 2, 1), 0.2, 10)
    assert len(val) and len(train)
    assert not set(train.index) & set(val.index)


def test_too_short_store_and_mismatched_frame_are_refused():
    with pytest.raises(DozerlabError, match="fewer than history"):
        windows([translating(0, rows=4)], history=3, horizon=2)
    a, b = translating(0), translating(1)
    b.row_dt = 0.02
    with pytest.raises(DozerlabError, match="differ from"):
        frame_of([a, b])
    b.row_dt = 0.0
    with pytest.raises(DozerlabError, match="lacks its row interval"):
        frame_of([a, b])
