"""The report and the sweep's naming, on synthetic results (no simulation)."""

import json
import re

import numpy as np
import pytest
from matplotlib.figure import Figure

from dozerlab import sweep as P
from dozerlab.config import ConfigError, load_config
from dozerlab.fields.store import write_store
from dozerlab.report.build import build_report, inline_images

CFG = load_config(
    {
        "sweep": {
            "scenarios": ["hill"],
            "speeds": [0.5, 1.0],
            "depths": [0.1],
            "interpolation": [{"scenario": "hill", "speed": 0.75, "depth": 0.1}],
            "extrapolation": [{"scenario": "hill", "speed": 2.0, "depth": 0.1}],
        },
        "learn": {"models": ["linear"]},
    }
)


@pytest.mark.parametrize(
    ("value", "text"), [(1.0, "1.0"), (0.1, "0.1"), (0.05, "0.05"), (1e-5, "0.00001"), (20, "20.0")]
)
def test_numbers_round_trip(value, text):
    assert P.fmt_number(value) == text
    assert P.check_canonical("speed", text) == pytest.approx(value)
    assert re.fullmatch(P.NUMBER_PATTERN, text)


@pytest.mark.parametrize("text", ["1", "1.00", "01.0"])
def test_non_canonical_spelling_names_the_canonical_one(text):
    with pytest.raises(ValueError, match=r"speed~1\.0"):
        P.check_canonical("speed", text)


def test_sweep_points_and_paths():
    pts = P.sweep_points(CFG)
    assert [(p.role, p.name) for p in pts] == [
        ("train", "speed~0.5_depth~0.1"),
        ("train", "speed~1.0_depth~0.1"),
        ("interpolation", "speed~0.75_depth~0.1"),
        ("extrapolation", "speed~2.0_depth~0.1"),
    ]
    assert str(P.field_path("results", pts[1])) == "results/fields/hill/speed~1.0_depth~0.1.zarr"
    assert (
        str(P.trajectory_path("results", pts[1], "png"))
        == "results/trajectories/hill/speed~1.0_depth~0.1.png"
    )
    back = P.parse_point("results/fields/hill/speed~1.0_depth~0.1.zarr")
    assert (back.scenario, back.speed, back.depth) == ("hill", 1.0, 0.1)


def test_held_out_point_on_the_grid_is_refused():
    cfg = load_config({"sweep": {"speeds": [1.0], "depths": [0.1]}})
    cfg["sweep"]["extrapolation"] = [{"scenario": "step", "speed": 1.0, "depth": 0.1}]
    with pytest.raises(ConfigError, match=r"sweep\.extrapolation\.0"):
        P.sweep_points(cfg)
    with pytest.raises(ConfigError, match=r"sweep\.extrapolation\.0"):
        load_config(cfg)  # and the config is refused before anything runs


def _png(path, title):
    fig = Figure(figsize=(3, 2))
    fig.subplots().set_title(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def _store(path, point, steps=6):
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
        },
    )


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
        "plots": {"parity": f"{model}/parity.png", "series": {}},
    }
    path = P.validation_path(results, model)
    path.write_text(json.dumps(doc))


def test_report_embeds_everything_and_marks_missing_points(tmp_path):
    results = tmp_path / "results"
    pts = P.sweep_points(CFG)
    for p in pts[:3]:  # the extrapolation point is "not built"
        _store(P.field_path(results, p), p)
        _png(P.trajectory_path(results, p, "png"), p.name)
    _png(results / "beds" / "hill.png", "bed")
    bench = P.simulate_benchmark_path(results, pts[0])
    bench.parent.mkdir(parents=True)
    bench.write_text("s\th:m:s\tmax_rss\n12.5\t0:00:12\t100\n")
    _validation(results, "linear")

    out = build_report(CFG, results, results / "report" / "index.html")
    text = out.read_text()
    rows = [r for r in re.findall(r"<tr>(.*?)</tr>", text) if "<td" in r]
    first = re.findall(r"<td[^>]*>(.*?)</td>", rows[0])
    assert first == ["hill", "train", "0.5", "0.1", "321", "12", "12.5", "1207", "2022"]
    extra = re.findall(r"<td[^>]*>(.*?)</td>", rows[3])
    assert extra[:2] == ["hill", "extrapolation"] and extra[4:] == ["–"] * 5
    assert "speed~2.0_depth~0.1: not built yet" in text
    # per built point: trajectory, slice, force; the bed; the model's parity plot
    assert text.count('src="data:image/png;base64,') == 3 * 3 + 1 + 1
    assert 'src="linear/' not in text and "../validation" not in text
    assert "<td>0.125</td>" in text  # the model comparison table


def test_inline_images_keeps_missing_links(tmp_path):
    _png(tmp_path / "a.png", "a")
    out = inline_images('<img src="a.png"><img src="gone.png">', tmp_path)
    assert out.startswith('<img src="data:image/png;base64,') and 'src="gone.png"' in out
