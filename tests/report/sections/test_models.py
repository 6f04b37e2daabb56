"""The models section: the best model per group, the comparison table, each model's details."""

import json
import re

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.sections import models
from tests.helpers import SMALL_SWEEP, report_context, validation_json

CFG = load_config({**SMALL_SWEEP, "learn": {"models": ["linear", "mlp"]}})


def test_best_model_per_group_and_a_row_per_model_and_group(tmp_path):
    assert models.render(report_context(CFG, tmp_path)) is None
    assert models.verdict(report_context(CFG, tmp_path)) is None
    (tmp_path / "validation").mkdir()
    validation_json(tmp_path, "linear")
    validation_json(tmp_path, "mlp")
    path = P.validation_path(tmp_path, "mlp")
    doc = json.loads(path.read_text())
    doc["groups"]["interpolation"]["overall"]["force_x"] = {
        "rmse": 2500.0,
        "rel_rmse": 0.05,
        "r2": 0.99,
    }
    doc["groups"]["interpolation"]["points"][0]["point"] = {
        "scenario": "hill",
        "speed": 0.75,
        "depth": 0.1,
    }
    doc["training"] = {"epochs": 40, "best_epoch": 31, "seconds": 61.0}
    path.write_text(json.dumps(doc))

    text = models.render(report_context(CFG, tmp_path))
    assert (
        "Lowest force_x relative RMSE: on the interpolation points mlp, 5.0 %; "
        "on the extrapolation points linear, 12.5 %." in text
    )
    summary = text.split("<details")[0]
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", r) for r in re.findall(r"<tr>(.*?)</tr>", summary)]
    rows = [r for r in rows if r]
    assert [r[:2] for r in rows] == [
        ["linear", "interpolation"],
        ["linear", "extrapolation"],
        ["mlp", "interpolation"],
        ["mlp", "extrapolation"],
    ]
    assert rows[2][2:5] == ["5.0", "2.5", "0.990"]  # %, kN, R²
    mlp = text.split('id="validation-mlp"')[1]
    assert "mlp: fine; 40 epochs, best at epoch 32; training took 61 s." in mlp  # 1-based
    assert '<td class="text">hill, 0.75 m/s, 0.1 m</td>' in mlp
    # the verdict: the lowest mean over the groups (mlp 8.75 %, linear 12.5 %), per group
    assert models.verdict(report_context(CFG, tmp_path)) == (
        "mlp predicts the draft force best over the held-out groups (mean force_x relative RMSE "
        "8.8 %): 5.0 % on the interpolation and 12.5 % on the extrapolation points; next best "
        "linear (mean 12.5 %), 12.5 % and 12.5 %; the thesis CNN "
        "reached 10 % on its training data."
    )
    assert "closed-form fit (no epochs)" in text.split('id="validation-mlp"')[0]


def test_the_unseen_terrain_group_has_its_rows_and_its_best_model(tmp_path):
    (tmp_path / "validation").mkdir()
    validation_json(tmp_path, "linear")
    path = P.validation_path(tmp_path, "linear")
    doc = json.loads(path.read_text())
    doc["groups"]["transfer"] = json.loads(json.dumps(doc["groups"]["extrapolation"]))
    doc["groups"]["transfer"]["overall"]["force_x"]["rel_rmse"] = 0.2
    path.write_text(json.dumps(doc))
    text = models.render(report_context(CFG, tmp_path))
    assert "on the unseen terrain points linear, 20.0 %" in text
    summary = text.split("<details")[0]
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", r) for r in re.findall(r"<tr>(.*?)</tr>", summary)]
    assert [r[:2] for r in rows if r][-1] == ["linear", "unseen terrain"]
