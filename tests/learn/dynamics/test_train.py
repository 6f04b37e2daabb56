"""Training of the evolution models: losses per epoch (per alpha for the ridge), the best kept."""

from dataclasses import replace

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.learn.dynamics.train import train_dynamics

from .helpers import steady, translating

CFG = load_config(
    {
        "mlflow": {"enabled": False},
        "learn": {"validation_block": 5},
        # several penalties, so that the ridge's choice among them is tested (the default has one)
        "dynamics": {"val_rollout": 2, "ridge_z_bands": [1, 3], "ridge_alphas": [1e-3, 0.1, 10.0]},
    }
)


def test_persistence_has_no_loss_on_a_field_that_does_not_change():
    seen = []
    r = train_dynamics(
        "persistence",
        [steady(40), replace(steady(40), point={"scenario": "step", "speed": 1.0, "depth": 0.2})],
        CFG,
        on_epoch=lambda *a: seen.append(a),
        progress=False,
    )
    assert (r.train_loss, r.val_loss, r.best_epoch) == ([0.0], [0.0], 0)
    assert seen == [(0, 0.0, 0.0)] and r.samples["train"] > r.samples["validation"] > 0
    assert not r.model.training


@pytest.fixture(scope="module")
def moving():
    return [translating(0), translating(1)]


def test_the_ridge_tries_every_alpha_keeps_the_best_and_beats_persistence(moving, capsys):
    ridge = train_dynamics("ridge", moving, CFG, progress=False)
    assert "ridge" not in capsys.readouterr().err  # no bar where the caller asked for none
    persistence = train_dynamics("persistence", moving, CFG, progress=False)
    assert len(ridge.train_loss) == len(ridge.val_loss) == len(CFG["dynamics"]["ridge_alphas"])
    assert ridge.best_epoch == int(np.argmin(ridge.val_loss))
    assert ridge.penalty == CFG["dynamics"]["ridge_alphas"][ridge.best_epoch]
    assert persistence.penalty is None
    assert min(ridge.val_loss) < 0.1 * persistence.val_loss[0]
    # three rows a call: each store gives two training windows fewer than persistence's one row
    assert (ridge.model.horizon, persistence.model.horizon) == (3, 1)
    assert ridge.samples["train"] == persistence.samples["train"] - 2 * len(moving)
    assert ridge.samples["validation"] == persistence.samples["validation"]
