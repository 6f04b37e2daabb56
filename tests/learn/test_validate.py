"""Held-out validation: per-point and per-group metrics, plots, and what it refuses."""

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.learn.metrics import component_metrics, flat
from dozerlab.learn.train import train_model
from dozerlab.learn.validate import evaluate, predict_store, validate
from dozerlab.runtime import DozerlabError
from tests.helpers import in_memory


@pytest.fixture(scope="module")
def trained(train_stores):
    """A history-2 ridge model and the metadata its job records."""
    cfg = load_config({"learn": {"history": 2}, "mlflow": {"enabled": False}})
    result = train_model("linear", train_stores, cfg, progress=False)
    meta = {
        "train_points": [s.point for s in train_stores],
        "train_keys": [
            [s.point["scenario"], s.point["speed"], s.point["depth"]] for s in train_stores
        ],
        "train_loss": result.train_loss,
        "val_loss": result.val_loss,
    }
    return result.model.eval(), meta


@pytest.fixture(scope="module")
def held_out():
    return {
        "interpolation": [in_memory(1.0, 0.1, seed=31), in_memory(0.75, 0.1, seed=32)],
        "extrapolation": [in_memory(2.0, 0.2, seed=33)],
    }


def test_predict_store_drops_the_steps_without_a_full_history(trained):
    model, _ = trained
    store = in_memory(1.0, 0.1, steps=40, seed=30)
    t, pred, true = predict_store(model, store)
    assert len(t) == len(pred) == len(true) == 39
    assert t[0] == store.time[1] and np.array_equal(true, store.target[1:])


def test_groups_points_and_overall_are_the_metrics_of_their_steps(trained, held_out, tmp_path):
    model, meta = trained
    result = validate(model, meta, held_out, tmp_path / "plots", tmp_path)
    assert list(result["groups"]) == ["interpolation", "extrapolation"]
    interp = result["groups"]["interpolation"]
    assert [p["name"] for p in interp["points"]] == [s.name for s in held_out["interpolation"]]
    series = [predict_store(model, s) for g in held_out.values() for s in g]
    expected = component_metrics(
        np.concatenate([p for _, p, _ in series]), np.concatenate([t for _, _, t in series])
    )
    assert flat(result["overall"], "") == pytest.approx(flat(expected, ""))
    first = interp["points"][0]["metrics"]
    assert flat(first, "") == pytest.approx(flat(component_metrics(*series[0][1:]), ""))
    assert interp["points"][0]["steps"] == 99 and "_series" not in interp["points"][0]
    assert result["summary"].startswith("linear: interpolation force_x rel. RMSE ")
    # the synthetic force is a smooth function of the fields: a ridge fit generalises
    assert interp["overall"]["force_x"]["r2"] > 0.9


def test_plots_are_written_and_referenced_relative_to_the_json(trained, held_out, tmp_path):
    model, meta = trained
    plots = validate(model, meta, held_out, tmp_path / "v" / "linear", tmp_path / "v")["plots"]
    assert plots["parity"] == "linear/parity.png" and plots["loss"] == "linear/loss.png"
    assert sorted(plots["series"]) == sorted(
        f"{g}: {s.name}" for g, stores in held_out.items() for s in stores
    )
    for rel in [plots["parity"], plots["loss"], *plots["series"].values()]:
        assert (tmp_path / "v" / rel).read_bytes().startswith(b"\x89PNG")


def test_a_training_point_among_held_out_points_is_refused(trained, train_stores):
    model, meta = trained
    with pytest.raises(DozerlabError, match="which the model was trained on"):
        validate(model, meta, {"interpolation": [train_stores[2]]})


def test_no_held_out_stores_or_another_grid_is_refused(trained):
    model, meta = trained
    with pytest.raises(ValueError, match="no held-out stores"):
        validate(model, meta, {"interpolation": [], "extrapolation": []})
    with pytest.raises(DozerlabError, match=r"has a \(6, 6, 4\) grid"):
        evaluate(model, [in_memory(1.0, 0.1, grid=(6, 6, 4))])
