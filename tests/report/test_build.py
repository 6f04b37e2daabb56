"""The report, on synthetic results (no simulation)."""

import re

import pytest

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.report.build import build_report
from tests.helpers import (
    SMALL_SWEEP,
    dynamics_json,
    png_file,
    reduced_json,
    report_bed,
    report_store,
    table_cells,
    validation_json,
)

CFG = load_config(SMALL_SWEEP)


def test_report_embeds_everything_with_units(tmp_path):
    results = tmp_path / "results"
    pts = P.sweep_points(CFG)
    for p in pts[:3]:  # the extrapolation point is "not built"
        report_store(P.field_path(results, p), p, wall_time=12.5 if p is pts[0] else None)
        png_file(P.trajectory_path(results, p, "png"), p.name)
    report_bed(results)
    validation_json(results, "linear")

    out = build_report(CFG, results, results / "report" / "index.html")
    text = out.read_text()
    ids = re.findall(r'<section id="([a-z]+)">', text)
    assert ids == ["sweep", "beds", "runs", "models"]
    # the sweep table: units in the headings, the simulation's own stepping time
    for heading in (
        "speed (m/s)",
        "depth (m)",
        "stepping wall time (s)",
        "mean |F| (kN)",
        "peak at (s)",
    ):
        assert f"<th>{heading}</th>" in text
    first = table_cells(text, "sweep", 0)
    assert first == [
        "hill", "training", "0.5", "0.1", "321", "12", "0.06", "12.5", "208 ×", "1.21", "2.02",
        "0.06",
    ]  # fmt: skip
    assert table_cells(text, "sweep", 1)[7:9] == ["–", "–"]  # a store without wall_time_s
    extra = table_cells(text, "sweep", 3)
    assert extra[:2] == ["hill", "held out, extrapolation"] and extra[4:] == ["–"] * 8
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
    validation_json(results, "linear")
    text = build_report(CFG, results, tmp_path / "models.html").read_text()
    assert re.findall(r'<section id="([a-z]+)">', text) == ["models"]


def test_smoke_test_config_says_so(tmp_path):
    cfg = load_config({**CFG, "report": {"smoke_test": True}})
    text = build_report(cfg, tmp_path / "results", tmp_path / "index.html").read_text()
    assert '<div class="note">Smoke test' in text


@pytest.mark.slow  # a pool of processes
def test_figures_drawn_by_several_processes_are_those_drawn_by_one(tmp_path):
    results = tmp_path / "results"
    for p in P.sweep_points(CFG)[:3]:
        report_store(P.field_path(results, p), p)
        png_file(P.trajectory_path(results, p, "png"), p.name)
    one = build_report(CFG, results, tmp_path / "one.html").read_text()
    two = build_report(CFG, results, tmp_path / "two.html", processes=2).read_text()
    runs = [re.search(r'<section id="runs">(.*?)</section>', t, re.S)[1] for t in (one, two)]
    assert runs[0] == runs[1] and runs[0].count("data:image/png;base64,") == 3 * 3


def test_the_summary_answers_the_four_questions_before_the_sections(tmp_path):
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["replay", "ridge"]}})
    results = tmp_path / "results"
    for p in P.sweep_points(cfg):
        report_store(P.field_path(results, p), p, wall_time=12.5)
    report_bed(results)
    (results / "validation").mkdir()
    validation_json(results, "linear")
    dynamics_json(results, "persistence", 0.2, 0.0)
    dynamics_json(results, "ridge", 0.1, 0.02)
    gif = b"GIF89a" + bytes(3_000_000)  # an animation of a few megabytes, as compare-reduced's
    for model in ("replay", "ridge"):
        reduced_json(results, model, gif)

    out = build_report(cfg, results, results / "report" / "index.html")
    text = out.read_text()
    top = text.split("<nav>")[0]  # what a reader sees first: title, intro, summary
    answers = re.findall(r'<li><a href="#([a-z]+)"><b>(.*?)</b></a>: (.*?)</li>', top)
    assert [(a, q) for a, q, _ in answers] == [
        ("sweep", "What the sweep covered"),
        ("models", "Best force model on held-out points"),
        ("dynamics", "Best field-evolution model"),
        ("reduced", "Reduced simulation against NDEM"),
    ]
    sweep, force, evolution, reduced = (a for _, _, a in answers)
    assert sweep == (
        "4 of 4 NDEM runs simulated (2 training, 2 held out) on hill, blade speeds 0.5–2.0 m/s, "
        "cut depths 0.1 m; mean |F| 1.21 kN (hill 0.5 m/s, 0.1 m); stepping took 12 s a run."
    )
    assert force.startswith("linear predicts the draft force best over the held-out groups")
    assert evolution.startswith("ridge evolves the fields best, started from NDEM&#x27;s")
    assert reduced == (
        "ridge is the best learned evolution model in the loop, on its one held-out point: "
        "smoothed-surface skill 0.80, low-passed force error 0.80× the twin&#x27;s, loop 62.0× "
        "as fast as NDEM; 2 of 3 targets met on every held-out point."
    )
    # each section opens with its verdict; beds and runs have one, outside the summary
    for section in ("sweep", "beds", "runs", "models", "dynamics", "reduced"):
        assert re.search(rf'<section id="{section}"><h2>[^<]*</h2>\n<p class="verdict">', text)
    # the animations are files beside the page, not base64 in it: the page stays small
    assert "data:image/gif" not in text
    shown = sorted(re.findall(r'<img src="animations/([^"]+)"', text))
    assert shown == [f"reduced_{m}_hill_speed~0.75_depth~0.1.gif" for m in ("replay", "ridge")]
    for name in shown:
        assert (out.parent / "animations" / name).read_bytes() == gif
    assert out.stat().st_size < 1_000_000 < len(gif)
    # replay's grains are steered towards its density (reduced.density_models) and its pile's
    # crest lifted (reduced.crest_models), the ridge's not
    assert "its velocity moving the grains and its density steering them, the pile" in text
    assert "steered towards ridge" not in text and "crest is lifted" not in text
    steered = load_config(
        {
            **SMALL_SWEEP,
            "reduced": {
                "dynamics_models": ["replay", "ridge"],
                "density_models": ["ridge"],
                "crest_models": ["ridge"],
            },
        }
    )
    text = build_report(steered, results, tmp_path / "steered.html").read_text()
    assert "density steering" not in text and "steered towards ridge&#x27;s density" in text
    assert "moving the grains: its errors" in text and "crest is lifted over" in text


def test_animations_the_page_no_longer_shows_are_removed(tmp_path):
    from PIL import Image

    results = tmp_path / "results"
    folder = results / "report" / "animations"
    folder.mkdir(parents=True)
    Image.new("RGB", (4, 4)).save(folder / "reduced_old.gif", format="GIF", comment="dozerlab")
    (folder / "mine.gif").write_bytes(b"GIF89a a user's animation")
    build_report(CFG, results, results / "report" / "index.html")
    assert sorted(p.name for p in folder.iterdir()) == ["mine.gif"]
