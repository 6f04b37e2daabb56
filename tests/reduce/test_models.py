"""The learned parts the reduced loop drives: field models (replay, pyfunc) and the force model."""

from __future__ import annotations

from dataclasses import replace

import mlflow
import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.fields.store import open_store
from dozerlab.learn.data import load_store
from dozerlab.learn.dynamics import pyfunc
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.reduce.models import (
    REPLAY,
    ForcePredictor,
    PyfuncFieldModel,
    ReplayFieldModel,
    RunFrame,
    load_field_model,
)
from dozerlab.runtime import DozerlabError
from tests.learn.dynamics.helpers import translating


def test_replay_answers_with_the_stores_next_rows_and_repeats_its_last(ndem_run):
    tmp, _ = ndem_run
    store = load_store(tmp / "ndem.zarr")
    replay = load_field_model(REPLAY, store.grid, tmp / "ndem.zarr")
    assert isinstance(replay, ReplayFieldModel) and (replay.history, replay.horizon) == (1, 1)
    three = ReplayFieldModel(tmp / "ndem.zarr", horizon=3)
    last = store.density.shape[0] - 1
    v, rho = three.predict(store.velocity[:1], store.density[:1], store.blade_velocity[:4], 0)
    np.testing.assert_array_equal(rho, store.density[1:4])
    np.testing.assert_array_equal(v, store.velocity[1:4])
    _, rho = three.predict(
        store.velocity[:1], store.density[:1], store.blade_velocity[:4], last - 1
    )
    np.testing.assert_array_equal(rho, store.density[[last, last, last]])


def test_models_that_are_not_there_are_named(tmp_path):
    with pytest.raises(DozerlabError, match=r"needs the point's NDEM store \(--ndem\)"):
        load_field_model(REPLAY, (6, 5, 4))
    with pytest.raises(DozerlabError, match="not an MLflow model directory"):
        load_field_model(tmp_path, (6, 5, 4))
    with pytest.raises(FileNotFoundError, match="not a dozerlab model directory"):
        ForcePredictor(tmp_path)


def test_the_force_model_reads_only_its_history_of_rows(ndem_run):
    tmp, config = ndem_run
    store = load_store(tmp / "ndem.zarr")
    forces = ForcePredictor(tmp / "linear")
    assert forces.history == config["learn"]["history"] == 2 and forces.name == "linear"
    rows = slice(3, 8)
    f, t = forces.predict(store.velocity[rows], store.density[rows], store.blade_velocity[rows])
    f2, t2 = forces.predict(store.velocity[6:8], store.density[6:8], store.blade_velocity[6:8])
    assert f.shape == t.shape == (3,) and np.isfinite(f).all()
    np.testing.assert_array_equal(f, f2)
    np.testing.assert_array_equal(t, t2)


def test_the_batched_rows_are_each_rows_own_prediction(ndem_run):
    tmp, _ = ndem_run
    store = load_store(tmp / "ndem.zarr")
    forces = ForcePredictor(tmp / "linear")
    f, t = forces.predict_rows(store.velocity, store.density, store.blade_velocity)
    assert f.shape == t.shape == (store.density.shape[0], 3)
    for k in (0, 1, 5, store.density.shape[0] - 1):
        fk, tk = forces.predict(
            store.velocity[: k + 1], store.density[: k + 1], store.blade_velocity[: k + 1]
        )
        # a linear model's rows come from column sums in float64, the single row through the
        # module in float32: on this run's mirror-symmetric fields the rows' mirror-odd
        # components are 0, the module's its float32 round-off times this small fit's odd
        # weights (up to 1e5): 0.016 N and N·m
        np.testing.assert_allclose(f[k], fk, rtol=1e-5, atol=0.05)
        np.testing.assert_allclose(t[k], tk, rtol=1e-5, atol=0.05)


def test_a_run_whose_blade_part_the_force_model_does_not_read_is_refused(ndem_run):
    tmp, _ = ndem_run
    store = load_store(tmp / "ndem.zarr")
    forces = ForcePredictor(tmp / "linear")
    _, ny, nz = store.grid
    frame = RunFrame("t.csv", 10, store.grid, store.bin_size, store.row_dt, {})
    forces.check_run(frame)  # no blade part given: the whole grid, the model's
    forces.check_run(replace(frame, blade_part=(0, 0, ny, nz)))
    with pytest.raises(DozerlabError, match=r"reads bins \[0, 0, \d+, \d+\] .*behind_bins"):
        forces.check_run(replace(frame, blade_part=(2, 0, ny, nz)))


def test_a_pyfunc_evolution_model_predicts_as_the_model_itself(ndem_run, tmp_path):
    from dozerlab.learn.dynamics import pyfunc
    from dozerlab.learn.dynamics.models import DynamicsModel

    tmp, _ = ndem_run
    store = load_store(tmp / "ndem.zarr")
    model = DynamicsModel("persistence", store.grid, 1, 2, store.row_dt, store.bin_size)
    arrays = {
        "velocity": store.velocity,
        "density": store.density,
        "blade_velocity": store.blade_velocity,
    }
    pyfunc.save(model, {"train_points": []}, tmp_path / "persistence", arrays)
    field = PyfuncFieldModel(tmp_path / "persistence", store.grid)
    assert (field.name, field.history, field.horizon) == ("persistence", 1, 2)
    v, rho = field.predict(store.velocity[4:5], store.density[4:5], store.blade_velocity[4:7], 4)
    window = {
        "velocity": store.velocity[None, 4:5],
        "density": store.density[None, 4:5],
        "blade_velocity": store.blade_velocity[None, 4:7],
    }
    expected = pyfunc.predict_arrays(model, window)
    assert v.shape == (2, *store.grid, 3) and rho.shape == (2, *store.grid)
    np.testing.assert_allclose(rho, expected["density"][0], rtol=1e-6)
    np.testing.assert_allclose(v, expected["velocity"][0], rtol=1e-6, atol=1e-7)


def test_the_loops_direct_model_calls_match_the_pyfunc(ndem_run):
    tmp, _ = ndem_run
    forces = ForcePredictor(tmp / "linear")
    nd = open_store(tmp / "ndem.zarr")
    v, rho, vb = (
        nd[k].values.astype(np.float32) for k in ("velocity", "density", "blade_velocity")
    )
    k = 5  # the loop passes the rows up to the current one; the pyfunc predicts each of them
    force, torque = forces.predict(v[:k], rho[:k], vb[:k])
    pyfunc = mlflow.pyfunc.load_model(str(tmp / "linear"))
    frame = pyfunc.predict({"velocity": v[:k], "density": rho[:k], "blade_velocity": vb[:k]})
    # float32 sums over a few thousand features in another order (one row against a batch)
    np.testing.assert_allclose(np.r_[force, torque], frame.to_numpy()[-1], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("kind", ["unet", "ridge"])
def test_the_loops_direct_field_model_calls_match_the_pyfunc(kind, tmp_path):
    # the ridge's calls go through its own inference (RidgeInference), the U-Net's through
    # the module: both answer as MLflow's pyfunc does
    cfg = load_config(
        {
            "mlflow": {"enabled": False},
            "learn": {"validation_block": 5},
            # both kinds predict the 2 rows the inputs below hold; the stores have 4 rows of bins
            "dynamics": {
                "epochs": 1,
                "samples_per_epoch": 8,
                "history": 2,
                "horizon": 2,
                "ridge_horizon": 2,
                "ridge_z_bands": [1, 3],
            },
        }
    )
    stores = [translating(i, rows=30) for i in range(2)]
    model = train_dynamics(kind, stores, cfg, progress=False).model
    arrays = {k: getattr(stores[0], k) for k in ("velocity", "density", "blade_velocity")}
    pyfunc.save(model, {"train_points": []}, tmp_path / kind, arrays)
    held = translating(7, rows=30)
    loop = PyfuncFieldModel(tmp_path / kind, held.grid)
    assert (loop.ridge is not None) == (kind == "ridge")
    v, rho = loop.predict(held.velocity[3:5], held.density[3:5], held.blade_velocity[3:7], 4)
    want = mlflow.pyfunc.load_model(str(tmp_path / kind)).predict(
        {
            "velocity": held.velocity[None, 3:5],
            "density": held.density[None, 3:5],
            "blade_velocity": held.blade_velocity[None, 3:7],
        }
    )
    # float32 sums in another order (densities of ~10³ kg/m³)
    np.testing.assert_allclose(v, want["velocity"][0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rho, want["density"][0], rtol=1e-5, atol=1e-3)
