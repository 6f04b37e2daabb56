"""The report, on synthetic results (no simulation)."""

import json
import re

import numpy as np
import pytest
from matplotlib.figure import Figure

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.fields.store import write_store
from dozerlab.report import html, sections
from dozerlab.report.build import build_report
from tests.helpers import SMALL_SWEEP

CFG = load_config(SMALL_SWEEP)


def _png(path, title):
    fig = Figure(figsize=(3, 2))
    fig.subplots().set_title(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def _store(path, point, steps=6, wall_time=None):
    rng = np.random.default_rng(0)
    x, y, z = np.linspace(0.05, 0.55, 4), np.linspace(-0.3, 0.3, 3), np.linspace(-0.05, 0.25, 3)
    t = 0.01 * np.arange(1, steps + 1)
    force = np.tile([1000.0, 0.0, 300.0], (steps, 1))
    force[-1, 0] = 2000.0
    write_store(
        path,
        x=x,
        y=y,
        z=z,
        time=t,
        velocity=rng.normal(size=(steps, 4, 3, 3, 3)).astype(np.float32),
        density=rng.uniform(0, 1600, size=(steps, 4, 3, 3)).astype(np.float32),
        force=force,
        torque=np.zeros((steps, 3)),
        blade_velocity=np.tile([point.speed, 0, 0], (steps, 1)),
        blade_position=np.zeros((steps, 3)),
        attrs={
            "scenario": point.scenario,
            "speed": point.speed,
            "depth": point.depth,
            "bins": [4, 3, 3],
            "bin_size": [0.15, 0.2, 0.1],
            "dt": 0.01,
            "iterations": 10,
            "sample_every": 2,
            "particle_count": 321,
            "seed": 1,
            "dozerlab_version": "test",
            "config": "{}",
        }
        | ({"wall_time_s": wall_time} if wall_time is not None else {}),
    )


def _bed(results):
    from dozerlab.scenarios.bed import Bed

    rng = np.random.default_rng(1)
    n = 40
    pos = np.column_stack(
        [rng.uniform(0.05, 0.95, n), rng.uniform(-0.2, 0.2, n), rng.uniform(0.05, 0.3, n)]
    )
    zeros = np.zeros((n, 3))
    bed = Bed("hill", 1.0, 0.5, pos, np.full(n, 0.05), np.ones(n), zeros, zeros, {}, 1)
    P.bed_path(results, "hill").parent.mkdir(parents=True, exist_ok=True)
    bed.save(P.bed_path(results, "hill"))


def _validation(results, model):
    metrics = {
        c: {"rmse": 10.0, "rel_rmse": 0.125, "r2": 0.5}
        for c in ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
    }
    point = {"name": "hill speed~0.75_depth~0.1", "metrics": metrics}
    plots = results / "validation" / model
    _png(plots / "parity.png", "parity")
    doc = {
        "model": model,
        "summary": f"{model}: fine",
        "overall": metrics,
        "groups": {
            g: {"overall": metrics, "points": [point]} for g in ("interpolation", "extrapolation")
        },
        "training": {"epochs": 1, "best_epoch": 0, "samples": {"train": 10}, "seconds": 1.5},
        "plots": {"parity": f"{model}/parity.png", "series": {}},
    }
    path = P.validation_path(results, model)
    path.write_text(json.dumps(doc))


def _cells(text, section, row):
    body = re.search(rf'<section id="{section}">(.*?)</section>', text, re.S)[1]
    rows = [r for r in re.findall(r"<tr>(.*?)</tr>", body) if "<td" in r]
    return re.findall(r"<td[^>]*>(.*?)</td>", rows[row])


def test_report_embeds_everything_with_units(tmp_path):
    results = tmp_path / "results"
    pts = P.sweep_points(CFG)
    for p in pts[:3]:  # the extrapolation point is "not built"
        _store(P.field_path(results, p), p, wall_time=12.5 if p is pts[0] else None)
        _png(P.trajectory_path(results, p, "png"), p.name)
    _bed(results)
    _validation(results, "linear")

    out = build_report(CFG, results, results / "report" / "index.html")
    text = out.read_text()
    ids = re.findall(r'<section id="([a-z]+)">', text)
    assert ids == ["sweep", "beds", "runs", "models"]
    # the sweep table: units in the headings, the simulation's own stepping time
    for heading in ("speed (m/s)", "depth (m)", "stepping wall time (s)", "mean |F| (kN)"):
        assert f"<th>{heading}</th>" in text
    first = _cells(text, "sweep", 0)
    assert first == [
        "hill", "training", "0.5", "0.1", "321", "12", "0.06", "12.5", "208 ×", "1.21", "2.02"
    ]  # fmt: skip
    assert _cells(text, "sweep", 1)[7:9] == ["–", "–"]  # a store without wall_time_s
    extra = _cells(text, "sweep", 3)
    assert extra[:2] == ["hill", "held out, extrapolation"] and extra[4:] == ["–"] * 7
    assert "Not built yet: hill speed~2.0_depth~0.1." in text
    # the models: a chart and a table of percentages (unit in the heading, 12.5 in the cell)
    assert "<th>force_x rel. RMSE (%)</th>" in text and "<td>12.5</td>" in text
    assert 'id="validation-linear"' in text
    assert "Lowest force_x relative RMSE: on the interpolation points linear, 12.5 %" in text
    # every image embedded: sweep map; bed; per built point trajectory, slice, force;
    # the error chart and the model's parity plot
    assert text.count('src="data:image/png;base64,') == 1 + 1 + 3 * 3 + 2
    assert 'src="linear/' not in text and "Smoke test" not in text


def test_sections_without_data_are_left_out(tmp_path):
    results = tmp_path / "results"
    text = build_report(CFG, results, tmp_path / "empty.html").read_text()
    assert "<section" not in text and f"No results under {results} yet." in text

    (results / "validation").mkdir(parents=True)
    _validation(results, "linear")
    text = build_report(CFG, results, tmp_path / "models.html").read_text()
    assert re.findall(r'<section id="([a-z]+)">', text) == ["models"]


def test_smoke_test_config_says_so(tmp_path):
    cfg = load_config({**CFG, "report": {"smoke_test": True}})
    text = build_report(cfg, tmp_path / "results", tmp_path / "index.html").read_text()
    assert '<div class="note">Smoke test' in text


def test_every_section_module_is_complete():
    found = sections.modules()
    assert [m.ORDER for m in found] == sorted(m.ORDER for m in found)
    for m in found:
        assert isinstance(m.TITLE, str) and callable(m.render)


@pytest.mark.parametrize(
    ("value", "text"), [(0.0912, "9.1 %"), (1.0, "100.0 %"), (None, "–"), (float("nan"), "–")]
)
def test_percent(value, text):
    assert html.percent(value) == text


def test_table_puts_units_in_headings():
    cols = [html.Column("name", text=True), html.Column("force", "kN", lambda v: f"{v:.1f}")]
    out = html.table(cols, [["a", 1.25], [html.Group("group")]])
    assert '<th class="text">name</th><th>force (kN)</th>' in out
    assert "<td>1.2</td>" in out and '<td class="text" colspan="2">group</td>' in out


def test_images_of_each_kind_are_embedded(tmp_path):
    gif = tmp_path / "a.gif"
    gif.write_bytes(b"GIF89a")
    assert html.data_uri(gif).startswith("data:image/gif;base64,")
    with pytest.raises(ValueError, match="cannot embed"):
        html.data_uri(tmp_path / "a.txt")
