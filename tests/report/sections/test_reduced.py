"""The reduced-simulation section: per dynamics model its table with the targets, per point
its plots and animation."""

import json
import re

from dozerlab.config import load_config
from dozerlab.report.sections import reduced
from tests.helpers import SMALL_SWEEP, reduced_json, report_context

CFG = load_config(SMALL_SWEEP)


def test_a_comparison_becomes_a_table_and_a_block_of_plots(tmp_path):
    assert reduced.render(report_context(CFG, tmp_path)) is None
    reduced_json(tmp_path, "replay")
    text = reduced.render(report_context(CFG, tmp_path))
    assert "<h3>replay</h3>" in text and "replay feeds the loop NDEM's own fields" in (
        text.replace("&#x27;", "'")
    )
    assert (
        "targets: smoothed-surface skill ≥ 0.95, loop ≥ 40×, job ≥ 10×, "
        "overlap ≤ 10% of a radius, nothing left the bed" in text
    )
    # on top, a row per model: the means of the headline figures, the twin's, the targets met
    assert table_cells(text, 0) == [
        "replay",
        "linear-loop",
        "72.0",
        "90.0",
        "0.80",
        "8.0",
        "10.0",
        "0.80",
        "62.0",
        "–",
        "1 of 2",  # job_speedup is not judged without NDEM's job time
    ]
    # on the scales NDEM reproduces: each figure, the twin's, the skill (not the mean force's:
    # one twin's error of it is a chance draw, as near 0 as it likes)
    second = re.findall(r"<table>(.*?)</table>", text, re.S)[1]
    headings = re.findall(r"<th(?: class=\"text\")?>(.*?)</th>", second)
    assert headings == [
        "point",
        "group",
        "smoothed-surface accuracy (%)",
        "twin (%)",
        "skill (×)",
        "low-passed force x rel. RMSE (%)",
        "twin (%)",
        "skill (×)",
        "mean force x rel. error (%)",
        "twin (%)",
    ]
    assert table_cells(text, 1)[2:] == [
        "72.0",
        "90.0",
        "0.80",
        "8.0",
        "10.0",
        "0.80",
        "2.0",
        "1.0",
    ]
    # where the surface departs from NDEM's: each region's error and excess beside the twin's
    assert "Where the smoothed surface departs from NDEM&#x27;s" in text
    regions = table_cells(text, 2)[2:]
    assert regions[:6] == ["10.0", "5.0", "8.0", "2.0", "10.0", "3.0"]  # errors
    assert regions[6:] == ["2.0", "1.0", "-6.0", "-1.0", "5.0", "0.0"]  # excess
    # the grain scale and the fields, beside the twin's
    assert table_cells(text, 3)[2:] == [
        "90.0",
        "75.0",
        "30.0",
        "20.0",
        "20.0",
        "30.0",
        "10.0",
        "5.0",
        "4.2",
        "1",
    ]
    assert table_cells(text, 4)[2:] == ["5.0", "0", "62.0", "–"]
    assert (
        "<summary>hill: speed 0.75 m/s, depth 0.1 m — targets missed: replay_surface_skill</summary>"
        in text
    )
    assert "data:image/png;base64," in text and "data:image/gif" not in text
    assert text.count("<figure>") == 2  # the listed plot that is not there is left out
    # the animation is a file beside the page, shown by its relative path
    name = "reduced_replay_hill_speed~0.75_depth~0.1.gif"
    assert f'<img src="animations/{name}"' in text
    assert (tmp_path / "report" / "animations" / name).read_bytes() == b"GIF89a"
    assert (
        "<p>replay fields and the linear-loop force model on 1 held-out point: targets met on "
        "every point: loop_speedup; missed: replay_surface_skill (1 of 1).</p>" in text
    )


def table_cells(text: str, table: int) -> list[str]:
    """The cells of the first data row of the section's ``table``-th table."""
    body = re.findall(r"<table>(.*?)</table>", text, re.S)[table]
    row = next(r for r in re.findall(r"<tr>(.*?)</tr>", body) if "<td" in r)
    return re.findall(r"<td[^>]*>(.*?)</td>", row)


def test_without_twins_the_tables_hold_the_figures_alone(tmp_path):
    reduced_json(tmp_path, "ridge")
    path = tmp_path / "reduced" / "ridge.json"
    doc = json.loads(path.read_text())
    doc["points"] = [
        {k: v for k, v in p.items() if not k.startswith("twin_") and not k.endswith("_skill")}
        for p in doc["points"]
    ]
    path.write_text(json.dumps(doc))
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    text = reduced.render(report_context(cfg, tmp_path))
    assert "twin (%)" not in text and "no twin runs" in text
    assert table_cells(text, 0) == ["ridge", "linear-loop", "72.0", "8.0", "62.0", "–", "2 of 3"]
    assert table_cells(text, 1)[2:] == ["72.0", "8.0", "2.0"]
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "ridge is the best learned evolution model in the loop, on its one held-out point: "
        "smoothed-surface accuracy 72.0 %, low-passed force error 8.0 %, loop 62.0× as fast as "
        "NDEM; 2 of 3 targets met on every held-out point."
    )


def test_a_comparison_without_the_regions_shows_no_table_of_them(tmp_path):
    reduced_json(tmp_path, "ridge")
    path = tmp_path / "reduced" / "ridge.json"
    doc = json.loads(path.read_text())
    doc["points"] = [{k: v for k, v in p.items() if "surface_e" not in k} for p in doc["points"]]
    path.write_text(json.dumps(doc))
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    text = reduced.render(report_context(cfg, tmp_path))
    assert "Where the smoothed surface departs" not in text
    assert table_cells(text, 2)[2] == "90.0"  # the grain scale's table comes next


def test_a_skill_or_speed_up_a_hair_off_its_target_is_shown_on_its_side(tmp_path):
    reduced_json(tmp_path, "ridge")
    path = tmp_path / "reduced" / "ridge.json"
    doc = json.loads(path.read_text())
    doc["points"][0] |= {
        "surface_accuracy_skill": 0.89998,
        "loop_speedup": 39.96,
        "max_overlap_loop": 0.10004,
    }
    path.write_text(json.dumps(doc))
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    text = reduced.render(report_context(cfg, tmp_path))
    assert table_cells(text, 1)[4] == "0.89998"  # not "0.90" against the target 0.9
    # not "10.0" against an overlap of at most 10 %, nor "40.0" against the target 40
    assert table_cells(text, 4)[2:5] == ["10.004", "0", "39.96"]


def test_the_verdict_says_its_figures_are_means_over_the_held_out_points(tmp_path):
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    reduced_json(tmp_path, "ridge")
    path = tmp_path / "reduced" / "ridge.json"
    doc = json.loads(path.read_text())
    doc["points"].append(
        doc["points"][0]
        | {"surface_accuracy_skill": 0.9, "force_lp_rel_rmse_skill": 1.2, "loop_speedup": 38.0}
    )
    path.write_text(json.dumps(doc))
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "ridge is the best learned evolution model in the loop, means over its 2 held-out "
        "points: smoothed-surface skill 0.85, low-passed force error 1.00× the twin's, loop "
        "50.0× as fast as NDEM; 2 of 3 targets met on every held-out point."
    )


def test_the_verdict_is_the_best_learned_model_else_the_replay_control(tmp_path):
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["replay", "ridge", "unet"]}})
    assert reduced.verdict(report_context(cfg, tmp_path)) is None
    reduced_json(tmp_path, "replay")
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "replay (NDEM's own fields: the loop's own error), on its one held-out point: "
        "smoothed-surface skill 0.80, low-passed force error 0.80× the twin's, loop 62.0× as "
        "fast as NDEM; 1 of 2 targets met on every held-out point."
    )
    reduced_json(tmp_path, "ridge")
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "ridge is the best learned evolution model in the loop, on its one held-out point: "
        "smoothed-surface skill 0.80, low-passed force error 0.80× the twin's, loop 62.0× as "
        "fast as NDEM; 2 of 3 targets met on every held-out point."
    )
    # the highest mean smoothed-surface skill wins, whatever the order of the models
    reduced_json(tmp_path, "unet")
    path = tmp_path / "reduced" / "unet.json"
    doc = json.loads(path.read_text())
    doc["points"][0] |= {"surface_accuracy_skill": 0.85, "job_speedup": 12.0}
    doc["points"][0]["targets_met"] |= {"surface_skill": False, "job_speedup": True}
    path.write_text(json.dumps(doc))
    assert reduced.verdict(report_context(cfg, tmp_path)) == (
        "unet is the best learned evolution model in the loop, on its one held-out point: "
        "smoothed-surface skill 0.85, low-passed force error 0.80× the twin's, loop 62.0× and "
        "job 12.0× as fast as NDEM; 3 of 4 targets met on every held-out point."
    )
    # the section's table: a row per model, in the config's order
    text = reduced.render(report_context(cfg, tmp_path))
    first = re.findall(r"<table>(.*?)</table>", text, re.S)[0]
    rows = [re.findall(r"<td[^>]*>(.*?)</td>", r) for r in re.findall(r"<tr>(.*?)</tr>", first)]
    assert [(r[0], r[4], r[9], r[10]) for r in rows if r] == [
        ("replay", "0.80", "–", "1 of 2"),
        ("ridge", "0.80", "–", "2 of 3"),
        ("unet", "0.85", "12.0", "3 of 4"),
    ]


def test_a_comparison_with_unseen_terrain_shows_its_skill_beside_the_seen_shapes(tmp_path):
    reduced_json(tmp_path, "replay")  # without unseen terrain: the first test's table
    path = tmp_path / "reduced" / "replay.json"
    doc = json.loads(path.read_text())
    doc["transfer"] = {
        "surface_skill_seen": 0.72,
        "surface_skill_unseen": 0.54,
        "gap": -0.18,
        "target": 0.1,
        "met": False,
    }
    path.write_text(json.dumps(doc))
    text = reduced.render(report_context(CFG, tmp_path))
    assert "surface skill, unseen terrain / seen" in text
    assert table_cells(text, 0)[-1] == "0.54 / 0.72 (beyond 0.1)"


def test_with_twin_draws_the_runs_stand_against_ndems_expected_run(tmp_path):
    """reduced.twin.draws > 1: a table per model of each run against the draws' mean, beside
    NDEM's own run against it, and the expected-run force skill in the models table."""
    reduced_json(tmp_path, "ridge")
    path = tmp_path / "reduced" / "ridge.json"
    doc = json.loads(path.read_text())
    for p in doc["points"]:
        p |= {
            "twin_draws": 4,
            "expected_surface_accuracy": 0.8,
            "ndem_expected_surface_accuracy": 0.95,
            "expected_surface_accuracy_skill": 0.8 / 0.95,
            "expected_force_lp_rel_rmse": 0.05,
            "ndem_expected_force_lp_rel_rmse": 0.1,
            "expected_force_lp_rel_rmse_skill": 0.5,
        }
    path.write_text(json.dumps(doc))
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    text = reduced.render(report_context(cfg, tmp_path)).replace("&#x27;", "'")
    assert "Against NDEM's expected run, the mean of 4 twin draws" in text
    headings = re.findall(r"<th(?: class=\"text\")?>(.*?)</th>", text)
    assert "force skill, expected run (×)" in headings
    assert table_cells(text, 0)[8] == "0.50"  # after the twin's force figure and its skill
    expected = re.findall(r"<table>(.*?)</table>", text, re.S)[2]
    assert re.findall(r"<th(?: class=\"text\")?>(.*?)</th>", expected)[2:] == [
        "smoothed-surface accuracy (%)",
        "NDEM's run (%)",
        "skill (×)",
        "low-passed force x rel. RMSE (%)",
        "NDEM's run (%)",
        "skill (×)",
    ]
    assert table_cells(text, 2)[2:] == ["80.0", "95.0", "0.84", "5.0", "10.0", "0.50"]
    # without draws, neither the table nor the column
    reduced_json(tmp_path / "one", "ridge")
    text = reduced.render(report_context(cfg, tmp_path / "one"))
    assert "expected run" not in text


def test_the_speed_ups_name_the_ndem_they_are_over(tmp_path):
    """With solver.active_zone the workflow's NDEM is the zone's, 2-3x the full solve: its
    speed-ups must not read as the full solve's."""
    reduced_json(tmp_path, "ridge")
    cfg = load_config({**SMALL_SWEEP, "reduced": {"dynamics_models": ["ridge"]}})
    text = reduced.render(report_context(cfg, tmp_path)).replace("&#x27;", "'")
    assert "NDEM ran the full solve" in text and "active zone" not in text
    assert reduced.verdict(report_context(cfg, tmp_path)).endswith(
        "loop 62.0× as fast as NDEM; 2 of 3 targets met on every held-out point."
    )
    zone = load_config(
        {
            **SMALL_SWEEP,
            "solver": {**SMALL_SWEEP.get("solver", {}), "active_zone": {"enabled": True}},
            "reduced": {"dynamics_models": ["ridge"]},
        }
    )
    reduced_json(tmp_path / "zone", "ridge")
    text = reduced.render(report_context(zone, tmp_path / "zone")).replace("&#x27;", "'")
    assert "NDEM ran with its active zone" in text and "not over the full solve" in text
    assert "loop 62.0× as fast as NDEM with its active zone;" in reduced.verdict(
        report_context(zone, tmp_path / "zone")
    )
