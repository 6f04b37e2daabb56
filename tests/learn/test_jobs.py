import json
from pathlib import Path

import mlflow
import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.learn import pyfunc
from dozerlab.learn.data import load_store
from dozerlab.learn.jobs import VALIDATION_JSON, train_job
from dozerlab.runtime import DozerlabError


def _inputs(store):
    return {
        "velocity": store.velocity,
        "density": store.density,
        "blade_velocity": store.blade_velocity,
    }


@pytest.mark.slow  # logs and reloads MLflow models
def test_logged_and_saved_models_predict_like_the_trained_one(tracking, store_files, config):
    config["learn"]["epochs"] = 2
    config["mlflow"]["enabled"] = True
    out = tracking / "models" / "cnn"
    result = train_job("cnn", store_files["train"], config, out, progress=False)
    held_out = _inputs(load_store(store_files["interpolation"][0]))
    expected = pyfunc.predict_arrays(result.model, held_out)
    for uri in (result.model_uri, str(out)):
        got = mlflow.pyfunc.load_model(uri).predict(held_out)
        assert list(got.columns) == [
            "force_x",
            "force_y",
            "force_z",
            "torque_x",
            "torque_y",
            "torque_z",
        ]
        np.testing.assert_allclose(got.to_numpy(), expected, rtol=1e-5, atol=1e-4)
    runs = mlflow.search_runs(experiment_names=["dozerlab"], filter_string="tags.model = 'cnn'")
    assert list(runs["tags.rule"]) == ["train"] and list(runs["tags.role"]) == ["train"]
    assert list(runs["tags.mlflow.runName"]) == ["train/force/cnn"]
    # registered by kind under the experiment's name: models:/NAME/VERSION loads it
    (version,) = mlflow.MlflowClient().search_model_versions("name = 'dozerlab-force-cnn'")
    assert version.run_id == runs.loc[0, "run_id"]
    got = mlflow.pyfunc.load_model(f"models:/dozerlab-force-cnn/{version.version}").predict(
        held_out
    )
    np.testing.assert_allclose(got.to_numpy(), expected, rtol=1e-5, atol=1e-4)
    history = mlflow.MlflowClient().get_metric_history(runs.loc[0, "run_id"], "val_loss")
    assert [m.step for m in history] == [0, 1]


def test_a_training_under_a_workflow_spools_its_run_and_model(
    tracking, store_files, config, monkeypatch
):
    from dozerlab import spool
    from dozerlab.tracking import PARENT_ENV, start_parent_run

    config["learn"]["epochs"] = 1
    config["mlflow"]["enabled"] = True
    parent = start_parent_run("dozerlab", "workflow")
    monkeypatch.setenv(PARENT_ENV, parent)
    monkeypatch.setenv(spool.SPOOL_ENV, str(tracking / "spool"))
    out = tracking / "models" / "spooled"
    result = train_job("linear", store_files["train"], config, out, progress=False)
    assert result.model_uri == ""  # known once logged
    client = mlflow.MlflowClient()
    assert spool.ingest(client, tracking / "spool", parent, with_open=False) == 1
    (run,) = mlflow.search_runs(
        experiment_names=["dozerlab"],
        filter_string=f"tags.mlflow.parentRunId = '{parent}'",
        output_format="list",
    )
    assert run.data.tags["rule"] == "train" and run.data.metrics["best_epoch"] == 0
    (output,) = run.outputs.model_outputs
    held_out = _inputs(load_store(store_files["interpolation"][0]))
    got = mlflow.pyfunc.load_model(f"models:/{output.model_id}").predict(held_out)
    np.testing.assert_allclose(got.to_numpy(), pyfunc.predict_arrays(result.model, held_out))
    # the ingestion registers it as a new version of dozerlab-force-linear, tagged with the sweep
    query = f"tags.`dozerlab.parent_run_id` = '{parent}'"
    (version,) = client.search_model_versions(query)
    assert version.name == "dozerlab-force-linear" and version.run_id == run.info.run_id
    registered = mlflow.pyfunc.load_model(f"models:/dozerlab-force-linear/{version.version}")
    np.testing.assert_allclose(registered.predict(held_out).to_numpy(), got.to_numpy())


def test_cli_train_validate_evaluate(tracking, store_files, capsys):
    files = [str(p) for p in store_files["train"]]
    out = tracking / "models" / "linear"
    assert (
        main(
            [
                "train",
                "--model",
                "linear",
                "--train",
                *files,
                "--config",
                "{}",
                "--out",
                str(out),
                "--threads",
                "1",
            ]
        )
        == 0
    )
    assert pyfunc.MODEL_DIR.recognise(out)  # so a rerun may replace it
    report = tracking / "validation" / "linear.json"
    argv = [
        "validate",
        "--model",
        str(out),
        "--interpolation",
        str(store_files["interpolation"][0]),
        "--extrapolation",
        str(store_files["extrapolation"][0]),
        "--out",
        str(report),
    ]
    assert main(argv) == 0
    result = json.loads(report.read_text())
    assert set(result["groups"]) == {"interpolation", "extrapolation"}
    assert result["groups"]["interpolation"]["overall"]["force_x"]["rel_rmse"] < 0.2
    # JSON and plots only: the report (dozerlab.report) builds all HTML
    assert not report.with_suffix(".html").exists()
    assert (report.parent / result["plots"]["parity"]).is_file()
    assert result["training"]["epochs"] == 1  # the closed-form ridge
    assert (tracking / "validation" / "linear" / "interpolation_00.png").is_file()
    assert VALIDATION_JSON.recognise(report)
    assert main(["evaluate", "--model", str(out), str(store_files["interpolation"][0])]) == 0
    assert "overall" in capsys.readouterr().out
    # A store of another grid, and a held-out point that was a training point, fail clearly.
    assert main(["evaluate", "--model", str(out), str(store_files["other_grid"][0])]) == 2
    assert "grid but the model expects (8, 6, 4)" in capsys.readouterr().err
    assert main([*argv[:4], files[0], "--out", str(tracking / "leak.json")]) == 2
    assert "trained on" in capsys.readouterr().err


@pytest.mark.slow  # two trainings
def test_a_force_model_trained_on_loop_fields_says_so(tracking, store_files, config, capsys):
    """``--loop-fields``: the reduced loop's runs of the training points give the fields, NDEM's
    runs the force; the model, its metadata and its MLflow run say which fields it learnt."""
    from dozerlab.reduce.models import ForcePredictor
    from tests.helpers import write
    from tests.learn.conftest import TRAIN_POINTS

    files = [str(p) for p in store_files["train"]]
    loops = [
        str(write(tracking / "loop" / f"{i}.zarr", s, d, seed=40 + i))
        for i, (s, d) in enumerate(TRAIN_POINTS[:4])
    ]
    out, plain = tracking / "loop_model", tracking / "plain_model"
    argv = ["train", "--model", "linear", "--train", *files, "--config", "{}", "--out"]
    assert main([*argv, str(plain)]) == 0
    assert main([*argv, str(out), "--loop-fields", *loops]) == 0
    meta = json.loads((out / "artifacts" / "meta.json").read_text())
    assert meta["loop_fields"] == [str(Path(p).resolve()) for p in loops]
    assert ForcePredictor(out).name == "linear-loop" and ForcePredictor(plain).name == "linear"
    held_out = _inputs(load_store(store_files["interpolation"][0]))
    fitted = [pyfunc.FORMAT.load(d)[0] for d in (out, plain)]
    a, b = (pyfunc.predict_arrays(m, held_out) for m in fitted)
    assert not np.allclose(a, b)  # other fields, another fit
    runs = mlflow.search_runs(
        experiment_names=["dozerlab"], filter_string="tags.rule = 'train_loop_force'"
    )
    assert list(runs["tags.fields"]) == ["loop"]
    assert list(runs["tags.mlflow.runName"]) == ["train/force/linear-loop"]  # not "linear"
    assert runs.loc[0, "params.loop_fields"] == ",".join(loops)
    # one reduced run per training store, of the same point
    assert main([*argv, str(tracking / "m2"), "--loop-fields", *loops[:3]]) == 2
    assert "3 loop-field stores for 4 training stores" in capsys.readouterr().err
    assert main([*argv, str(tracking / "m3"), "--loop-fields", *reversed(loops)]) == 2
    assert "runs of different points" in capsys.readouterr().err


def test_pyfunc_input_of_wrong_grid_is_refused(store_files):
    model = pyfunc.ForceModel("linear", (6, 6, 4))
    with pytest.raises(DozerlabError, match="trained on a \\(6, 6, 4\\) grid"):
        pyfunc.predict_arrays(model, _inputs(load_store(store_files["train"][0])))
