"""The linear force model's rows from column sums against the model's own forward."""

import numpy as np
import pytest
import torch

from dozerlab.learn import pyfunc
from dozerlab.learn.inference import LinearForceRows
from dozerlab.learn.models import ForceModel


def _random_linear(grid, history, contact, part, seed):
    """A linear force model with random weights and normalisation (no fit needed: the check is
    that both paths compute the same function of the same parameters)."""
    torch.manual_seed(seed)
    model = ForceModel("linear", grid, history, contact=contact, blade_part=part).eval()
    with torch.no_grad():
        for p in model.parameters():
            p.normal_()
        for name in ("chan_mean", "cond_mean", "y_mean"):
            getattr(model, name).normal_()
        for name in ("chan_std", "cond_std", "y_std"):
            getattr(model, name).uniform_(0.5, 2.0)
    return model


@pytest.mark.parametrize(
    ("history", "contact", "part"),
    [(1, True, (2, 1, 5, 3)), (3, True, None), (2, False, (1, 0, 6, 4)), (1, False, None)],
)
def test_rows_are_the_models_own_predictions(history, contact, part):
    grid = (6, 6, 4)
    model = _random_linear(grid, history, contact, part, seed=history)
    rng = np.random.default_rng(history)
    rows = 9
    velocity = rng.normal(0.0, 0.5, (rows, *grid, 3)).astype(np.float32)
    density = rng.uniform(0.0, 1600.0, (rows, *grid)).astype(np.float32)
    blade = rng.normal(0.0, 1.0, (rows, 3))
    blade[2] = 0.0  # a blade at rest: the pushing gate's share is 0
    want = pyfunc.predict_arrays(
        model, {"velocity": velocity, "density": density, "blade_velocity": blade}, batch=4
    )
    got = LinearForceRows(model)(velocity, density, blade)
    scale = np.abs(want).max(axis=0)
    assert got.shape == (rows, 6)
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-4 * scale.max())
    if contact:  # the one-sided contact holds on this path too
        assert (got[:, 0] <= 0.0).all()
    # float64 fields give the same rows (the loop's own arrays are float32)
    np.testing.assert_allclose(
        LinearForceRows(model)(velocity.astype(np.float64), density.astype(np.float64), blade),
        got,
        rtol=1e-9,
        atol=1e-9 * scale.max(),
    )


def test_other_models_and_other_grids_are_refused():
    with pytest.raises(ValueError, match="linear"):
        LinearForceRows(ForceModel("mlp", (6, 6, 4)))
    rows = LinearForceRows(ForceModel("linear", (6, 6, 4)))
    with pytest.raises(ValueError, match="velocity must have shape"):
        rows(np.zeros((2, 6, 6, 5, 3)), np.zeros((2, 6, 6, 4)), np.zeros((2, 3)))
    assert rows(np.zeros((0, 6, 6, 4, 3)), np.zeros((0, 6, 6, 4)), np.zeros((0, 3))).shape == (0, 6)
