"""The model directory: saved, loaded back without MLflow and through MLflow, inputs checked."""

import json

import mlflow
import numpy as np
import pytest
import torch

from dozerlab.config import load_config
from dozerlab.learn import pyfunc
from dozerlab.learn.data import TARGET_NAMES
from dozerlab.learn.train import train_model
from dozerlab.runtime import DozerlabError
from tests.helpers import in_memory


def _inputs(store):
    return {k: getattr(store, k) for k in pyfunc.INPUT_NAMES}


@pytest.fixture(scope="module")
def saved(train_stores, tmp_path_factory):
    """A history-2 ridge model trained on the synthetic points and saved as a model directory."""
    cfg = load_config({"learn": {"history": 2}, "mlflow": {"enabled": False}})
    model = train_model("linear", train_stores, cfg, progress=False).model.eval()
    path = tmp_path_factory.mktemp("model") / "linear"
    meta = {"train_points": [s.point for s in train_stores], "learn": cfg["learn"]}
    pyfunc.save(model, meta, path, _inputs(train_stores[0]))
    return model, path


def test_with_history_stacks_consecutive_rows_and_repeats_the_first(train_stores):
    arrays = _inputs(train_stores[0])
    v, rho, vb = pyfunc.with_history(arrays, 3)
    assert (
        v.shape == (60, 3, 8, 6, 4, 3) and rho.shape == (60, 3, 8, 6, 4) and vb.shape == (60, 3, 3)
    )
    assert torch.equal(vb[5], torch.from_numpy(arrays["blade_velocity"][3:6]))
    assert torch.equal(vb[1], torch.from_numpy(arrays["blade_velocity"][[0, 0, 1]]))


def test_saved_directory_loads_back_the_same_model_without_mlflow(saved):
    model, path = saved
    back, meta = pyfunc.load(path)
    assert meta["kind"] == "linear" and meta["grid"] == [8, 6, 4] and meta["history"] == 2
    assert json.loads((path / "artifacts" / "meta.json").read_text()) == meta
    state, loaded = model.state_dict(), back.state_dict()
    assert state.keys() == loaded.keys()
    assert all(torch.equal(state[k], loaded[k]) for k in state)


def test_a_model_saved_before_the_contact_inputs_loads_without_them(train_stores, tmp_path):
    """Metadata without ``contact`` (models saved before it) rebuilds a model without the
    pushing gate, whose state dict then fits."""
    cfg = load_config({"learn": {"contact": False}, "mlflow": {"enabled": False}})
    model = train_model("linear", train_stores, cfg, progress=False).model.eval()
    pyfunc.save(model, {}, tmp_path / "old", _inputs(train_stores[0]))
    meta_path = tmp_path / "old" / "artifacts" / "meta.json"
    meta = json.loads(meta_path.read_text())
    del meta["contact"]
    back = pyfunc.build(meta, tmp_path / "old" / "artifacts" / "weights.pt")
    assert not back.contact and back.cond_mean.shape == (3 * back.history,)
    arrays = _inputs(train_stores[1])
    np.testing.assert_array_equal(
        pyfunc.predict_arrays(back, arrays), pyfunc.predict_arrays(model, arrays)
    )


def test_a_model_saved_before_the_blade_part_reads_the_whole_grid(saved, train_stores):
    model, path = saved
    meta = json.loads((path / "artifacts" / "meta.json").read_text())
    assert meta["blade_part"] == [0, 0, 6, 4]
    del meta["blade_part"]
    back = pyfunc.build(meta, path / "artifacts" / "weights.pt")
    assert back.blade_part == (0, 0, 6, 4)
    arrays = {k: v[:5] for k, v in _inputs(train_stores[1]).items()}
    np.testing.assert_array_equal(
        pyfunc.predict_arrays(back, arrays), pyfunc.predict_arrays(model, arrays)
    )


def test_mlflow_loads_the_directory_and_predicts_like_the_model(saved):
    model, path = saved
    arrays = _inputs(in_memory(1.0, 0.1, steps=30, seed=7))
    got = mlflow.pyfunc.load_model(str(path)).predict(arrays)
    assert list(got.columns) == list(TARGET_NAMES)
    # float32 sums, in another order on some CPUs
    np.testing.assert_allclose(got.to_numpy(), pyfunc.predict_arrays(model, arrays), rtol=1e-5)
    # the first row has no history: it repeats its own step, as the contract says
    first = pyfunc.predict_arrays(model, {k: a[:1] for k, a in arrays.items()})
    np.testing.assert_allclose(got.to_numpy()[:1], first, rtol=1e-5)


def test_a_directory_that_is_not_a_model_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="not a dozerlab model directory"):
        pyfunc.load(tmp_path)


@pytest.mark.parametrize(
    ("inputs", "message"),
    [
        (np.zeros((2, 8, 6, 4)), "must be a dict"),
        ({"velocity": np.zeros((2, 8, 6, 4, 3)), "density": np.zeros((2, 8, 6, 4))}, "lacks"),
        (
            {
                "velocity": np.zeros((2, 8, 6, 4, 3)),
                "density": np.zeros((2, 8, 6, 4)),
                "blade_velocity": np.zeros((3, 3)),
            },
            r"'blade_velocity' has shape \(3, 3\), expected \(2, 3\)",
        ),
    ],
)
def test_malformed_inputs_are_refused_by_name(inputs, message):
    with pytest.raises(DozerlabError, match=message):
        pyfunc.check_inputs(inputs, (8, 6, 4))
