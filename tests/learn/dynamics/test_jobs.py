import json

import mlflow
import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.config import load_config
from dozerlab.learn.data import load_store
from dozerlab.learn.dynamics import pyfunc

CONFIG = json.dumps(
    {
        "learn": {"validation_block": 5},
        # the stores have 4 rows of bins: the default height bands cut the default volume's 8
        "dynamics": {
            "epochs": 1,
            "samples_per_epoch": 8,
            "rollout_steps": 30,
            "rollout_starts": 2,
            "ridge_z_bands": [1, 3],
            "ridge_alphas": [1e-3, 0.1, 10.0],
        },
    }
)


@pytest.mark.slow  # trains, validates, logs models
def test_cli_trains_validates_and_logs_to_mlflow(tracking, store_files, capsys):
    train = [str(p) for p in store_files["train"]]
    out = tracking / "results" / "dynamics" / "ridge"
    assert (
        main(
            [
                "train-dynamics",
                "--model",
                "ridge",
                "--train",
                *train,
                "--config",
                CONFIG,
                "--out",
                str(out),
                "--threads",
                "1",
            ]
        )
        == 0
    )
    # the ridge's "epochs" are its candidate penalties: the line names the one kept
    kept = capsys.readouterr().out
    assert "validation rollout loss" in kept and " at penalty " in kept and " at epoch " not in kept
    js = tracking / "results" / "dynamics" / "ridge.json"
    held = [
        "--interpolation",
        str(store_files["interpolation"][0]),
        "--extrapolation",
        str(store_files["extrapolation"][0]),
    ]
    assert (
        main(
            ["validate-dynamics", "--model", str(out), *held, "--out", str(js), "--config", CONFIG]
        )
        == 0
    )
    assert "interpolation velocity error one-step" in capsys.readouterr().out
    result = json.loads(js.read_text())
    assert set(result["groups"]) == {"interpolation", "extrapolation"}
    o = result["overall"]
    assert set(o["rollout_at"]) == {"10", "50", "100"} and o["rollout_at"]["100"]["steps"] <= 30
    assert len(o["rollout"]["velocity"]) == len(o["rollout"]["mass_ratio"]) <= 30
    assert 0 <= o["one_step"]["velocity"] < 1 and o["mass"]["max_abs_error"] >= 0
    for png in [result["plots"]["rollout"], *result["plots"]["slices"].values()]:
        assert (js.parent / png).stat().st_size > 1000

    runs = mlflow.search_runs(experiment_names=["dozerlab"], filter_string="tags.model = 'ridge'")
    assert sorted(runs["tags.rule"]) == ["train_dynamics", "validate_dynamics"]
    trained = runs[runs["tags.rule"] == "train_dynamics"].iloc[0]
    assert trained["metrics.train_seconds"] > 0 and trained["params.dynamics.history"] == "2"
    alphas = load_config(json.loads(CONFIG))["dynamics"]["ridge_alphas"]
    assert trained["metrics.penalty"] == alphas[int(trained["metrics.best_epoch"])]
    assert f" at penalty {trained['metrics.penalty']:g} " in kept
    logged = mlflow.pyfunc.load_model(f"runs:/{trained['run_id']}/model")
    s = load_store(store_files["interpolation"][0])
    inputs = {
        "velocity": s.velocity[None, :2],
        "density": s.density[None, :2],
        "blade_velocity": s.blade_velocity[None, :5],  # history 2, three rows predicted
    }
    model, _ = pyfunc.load(out)
    assert model.horizon == 3  # dynamics.ridge_horizon
    np.testing.assert_allclose(
        logged.predict(inputs)["density"],
        pyfunc.predict_arrays(model, inputs)["density"],
        rtol=1e-5,
    )


def test_training_points_and_other_grids_are_refused(tracking, store_files, capsys):
    train = [str(p) for p in store_files["train"]]
    out = tracking / "persistence"
    assert (
        main(
            [
                "train-dynamics",
                "--model",
                "persistence",
                "--train",
                *train,
                "--config",
                CONFIG,
                "--out",
                str(out),
            ]
        )
        == 0
    )
    capsys.readouterr()
    bad = tracking / "bad.json"
    assert (
        main(
            [
                "validate-dynamics",
                "--model",
                str(out),
                "--interpolation",
                train[0],
                "--out",
                str(bad),
                "--config",
                CONFIG,
            ]
        )
        == 2
    )
    assert "trained on" in capsys.readouterr().err
    other = str(store_files["other_grid"][0])
    assert (
        main(
            [
                "validate-dynamics",
                "--model",
                str(out),
                "--extrapolation",
                other,
                "--out",
                str(bad),
                "--config",
                CONFIG,
            ]
        )
        == 2
    )
    assert "grid" in capsys.readouterr().err
    assert not bad.exists()
