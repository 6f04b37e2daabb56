"""The learning curve's reduced-simulation figures on real small stores: each training set's force
model read off a held-out point's replay loop, measured as ``compare-reduced`` measures it."""

import numpy as np
import pytest

from dozerlab.adaptive.curve import (
    COLUMNS,
    LOOP_COLUMNS,
    Design,
    curve_rows,
    held_out_loop,
    loop_figures,
    loop_force_error,
    read_curve,
    write_curve,
)
from dozerlab.config import load_config
from dozerlab.learn.data import load_store
from dozerlab.learn.pyfunc import predict_arrays
from dozerlab.learn.train import train_model
from dozerlab.reduce.compare import FORCE_WINDOW, low_pass, relative_rmse
from dozerlab.runtime import DozerlabError
from dozerlab.sweep import SweepPoint
from tests.helpers import in_memory, write

CONFIG = load_config({"learn": {"models": ["linear"], "history": 2}, "mlflow": {"enabled": False}})
WARMUP = 5
TRAIN = [SweepPoint("hill", v, d) for v, d in ((0.5, 0.05), (1.5, 0.05), (0.5, 0.15), (1.5, 0.15))]


@pytest.fixture(scope="module")
def stores(tmp_path_factory):
    """NDEM's run of a held-out point, its replay loop (other fields: seed 1) and its twin."""
    d = tmp_path_factory.mktemp("loop")
    ndem = write(d / "ndem.zarr", 1.0, 0.1, steps=60)
    loop = write(d / "loop.zarr", 1.0, 0.1, steps=60, seed=1, attrs={"warmup_rows": WARMUP})
    twin = write(d / "twin.zarr", 1.0, 0.1, steps=60, seed=2)
    return ndem, loop, twin


@pytest.fixture(scope="module")
def model():
    train = [in_memory(p.speed, p.depth, steps=60, seed=i) for i, p in enumerate(TRAIN)]
    return train_model("linear", train, CONFIG).model


def lp_error(force, truth, rows):
    """compare-reduced's force_lp_rel_rmse, spelled out (rows 0.02 s apart)."""
    lp, lp_true = (low_pass(f[:, 0], 0.02, FORCE_WINDOW) for f in (force, truth))
    return relative_rmse(lp[rows], lp_true[rows])


def test_the_loops_force_is_the_models_reading_of_its_fields_after_the_warm_up(stores, model):
    ndem, loop, twin = stores
    run = held_out_loop(loop, ndem, twin)
    assert (run.warmup, run.row_dt) == (WARMUP, pytest.approx(0.02))
    s = load_store(loop)
    pred = predict_arrays(
        model, {"velocity": s.velocity, "density": s.density, "blade_velocity": s.blade_velocity}
    )
    # the warm-up rows are NDEM's (the loop's store), the rest the model's
    force = np.concatenate([s.target[:WARMUP, :3], pred[WARMUP:, :3]]).astype(np.float64)
    truth = load_store(ndem).target[:, :3].astype(np.float64)
    rows = slice(WARMUP, None)
    error = loop_force_error(model, run)
    assert error == pytest.approx(lp_error(force, truth, rows), rel=1e-9)
    assert 0 < error < 1
    twin_force = load_store(twin).target[:, :3].astype(np.float64)
    assert run.twin_error == pytest.approx(lp_error(twin_force, truth, rows), rel=1e-9)
    figures = loop_figures(model, [run, run])
    assert figures == {
        "reduced_force_lp_rel_rmse": pytest.approx(error),
        "twin_force_lp_rel_rmse": pytest.approx(run.twin_error),
        "reduced_force_lp_rel_rmse_skill": pytest.approx(error / run.twin_error),
    }


def test_without_a_twin_the_skill_is_nan(stores, model):
    ndem, loop, _ = stores
    figures = loop_figures(model, [held_out_loop(loop, ndem)])
    assert np.isfinite(figures["reduced_force_lp_rel_rmse"])
    assert np.isnan(figures["twin_force_lp_rel_rmse"])
    assert np.isnan(figures["reduced_force_lp_rel_rmse_skill"])


def test_a_loop_not_aligned_with_ndem_is_refused(stores, tmp_path):
    ndem, _, _ = stores
    short = write(tmp_path / "short.zarr", 1.0, 0.1, steps=40, seed=1)
    with pytest.raises(DozerlabError, match=r"short\.zarr has 40 rows but NDEM's .*ndem\.zarr 60"):
        held_out_loop(short, ndem)


def test_curve_rows_measure_each_set_in_the_loop_and_keep_the_columns(stores, tmp_path):
    ndem, loop, twin = stores
    by_point = {p: in_memory(p.speed, p.depth, steps=60, seed=i) for i, p in enumerate(TRAIN)}
    held = {"interpolation": [load_store(ndem)], "extrapolation": []}
    designs = [
        Design("adaptive", -1, (tuple(TRAIN[:2]), tuple(TRAIN))),
        Design("grid", -1, (tuple(TRAIN),)),
    ]
    loops = [held_out_loop(loop, ndem, twin)]
    rows = curve_rows(designs, by_point, held, CONFIG, "linear", loops, "linear")
    assert [(r["design"], r["runs"]) for r in rows] == [
        ("adaptive", 2),
        ("adaptive", 4),
        ("grid", 4),
    ]
    assert all(r["reduced_force_model"] == "linear" for r in rows)
    assert all(0 < r["reduced_force_lp_rel_rmse"] < 1 for r in rows)
    # the same training set, the same figures; the twin's is the set's alone
    assert {k: rows[1][k] for k in LOOP_COLUMNS} == {k: rows[2][k] for k in LOOP_COLUMNS}
    assert rows[0]["twin_force_lp_rel_rmse"] == rows[2]["twin_force_lp_rel_rmse"]
    plain = curve_rows(designs[1:], by_point, held, CONFIG, "linear")
    assert plain[0]["reduced_force_model"] == ""
    assert all(np.isnan(plain[0][k]) for k in LOOP_COLUMNS)
    assert plain[0]["heldout_force_rel_rmse"] == pytest.approx(rows[2]["heldout_force_rel_rmse"])

    path = tmp_path / "learning_curve.csv"
    write_curve(path, rows + plain)
    assert path.read_text().splitlines()[0] == ",".join(COLUMNS)
    back = read_curve(path)
    assert back[0]["reduced_force_model"] == "linear" and back[-1]["reduced_force_model"] == ""
    assert back[0]["reduced_force_lp_rel_rmse"] == pytest.approx(
        rows[0]["reduced_force_lp_rel_rmse"], rel=1e-5
    )
    assert np.isnan(back[-1]["reduced_force_lp_rel_rmse_skill"])


def test_a_curve_written_before_the_reduced_columns_reads_with_them_empty(tmp_path):
    path = tmp_path / "learning_curve.csv"
    path.write_text(",".join(COLUMNS[:7]) + "\nadaptive,-1,8,linear,0.09,0.08,0.1\n")
    (row,) = read_curve(path)
    assert row["runs"] == 8 and row["reduced_force_model"] == ""
    assert all(np.isnan(row[k]) for k in LOOP_COLUMNS)
