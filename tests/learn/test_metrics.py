"""Per-component error metrics of force/torque predictions."""

import numpy as np
import pytest

from dozerlab.learn.data import TARGET_NAMES
from dozerlab.learn.metrics import component_metrics, flat


def test_known_errors_give_known_rmse_relative_rmse_and_r2():
    true = np.tile(np.array([[1.0], [-1.0], [1.0], [-1.0]]), (1, 6))  # RMS 1, mean 0, SST 4
    pred = true + 0.5
    m = component_metrics(pred, true)
    assert list(m) == list(TARGET_NAMES)
    for values in m.values():
        assert values["rmse"] == pytest.approx(0.5)
        assert values["rel_rmse"] == pytest.approx(0.5)
        assert values["r2"] == pytest.approx(1.0 - 4 * 0.25 / 4)


def test_a_perfect_prediction_scores_zero_error_and_r2_one():
    true = np.random.default_rng(0).normal(size=(50, 6))
    m = component_metrics(true, true)
    assert all(v["rmse"] == 0 and v["rel_rmse"] == 0 and v["r2"] == 1 for v in m.values())


def test_undefined_ratios_are_nan_and_flat_leaves_them_out():
    true = np.zeros((10, 6))
    true[:, 0] = 3.0  # force_x constant: no R²; the others all zero: no relative RMSE either
    m = component_metrics(true + 1.0, true)
    assert m["force_x"]["rel_rmse"] == pytest.approx(1 / 3) and np.isnan(m["force_x"]["r2"])
    assert np.isnan(m["torque_z"]["rel_rmse"]) and m["torque_z"]["rmse"] == pytest.approx(1.0)
    keys = flat(m, "interpolation")
    assert keys["interpolation.force_x.rmse"] == pytest.approx(1.0)
    assert "interpolation.force_x.r2" not in keys and "interpolation.torque_z.rel_rmse" not in keys
    assert all(np.isfinite(v) for v in keys.values())


@pytest.mark.parametrize(("pred", "true"), [((5, 6), (4, 6)), ((5, 3), (5, 3)), ((6,), (6,))])
def test_shapes_other_than_n_by_6_are_refused(pred, true):
    with pytest.raises(ValueError, match=r"must both be \(N, 6\)"):
        component_metrics(np.zeros(pred), np.zeros(true))
