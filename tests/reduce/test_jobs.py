"""The reduce and compare-reduced jobs: refusals before work, and the comparison's JSON."""

from __future__ import annotations

import json
import shutil

import pytest

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.reduce.jobs import COMPARISON_JSON, compare_job, reduce_job
from dozerlab.runtime import FOLDER_MARK, DozerlabError
from tests.helpers import REDUCED_RUN

SWEEP = {"scenarios": ["hill"], "speeds": [1.0], "depths": [0.06], "extrapolation": []}


def test_replay_without_the_ndem_store_is_refused_before_writing(ndem_run, tmp_path):
    tmp, config = ndem_run
    with pytest.raises(DozerlabError, match="--ndem"):
        reduce_job(
            tmp / "bed.npz",
            tmp / "speed~0.5_depth~0.06.csv",
            config,
            "replay",
            tmp / "linear",
            tmp_path / "r.zarr",
            tmp_path / "r.npz",
        )
    assert list(tmp_path.iterdir()) == []


def test_a_sweep_without_held_out_points_has_nothing_to_compare(tmp_path):
    config = load_config({**REDUCED_RUN, "sweep": {**SWEEP, "interpolation": []}})
    with pytest.raises(DozerlabError, match="no held-out points"):
        compare_job("replay", config, tmp_path, tmp_path / "c.json", tmp_path / "plots")
    assert list(tmp_path.iterdir()) == []


def test_ndem_compared_with_itself_meets_the_accuracy_targets_only(ndem_run, tmp_path):
    tmp, _ = ndem_run
    held = {"scenario": "hill", "speed": 0.5, "depth": 0.06}
    config = load_config({**REDUCED_RUN, "sweep": {**SWEEP, "interpolation": [held]}})
    point = next(p for p in P.sweep_points(config) if p.role == "interpolation")
    results = tmp_path / "results"
    stores = (P.field_path(results, point), P.reduced_path(results, "replay", point))
    for dest in (*stores, P.twin_path(results, point)):
        shutil.copytree(tmp / "ndem.zarr", dest)  # the "reduced" run and the "twin" are NDEM's own
    P.bed_path(results, "hill").parent.mkdir(parents=True)
    shutil.copy(tmp / "bed.npz", P.bed_path(results, "hill"))
    states = (P.state_path(results, point), P.reduced_path(results, "replay", point, "npz"))
    for dest in (*states, P.twin_path(results, point, "npz")):
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(tmp / "ndem.npz", dest)
    out, plots = tmp_path / "replay.json", tmp_path / "compare"
    summary = compare_job("replay", config, results, out, plots, animation=False)
    assert COMPARISON_JSON.recognise(out)
    written = json.loads(out.read_text())  # NaN where a figure is unknown: compared by key
    assert written.keys() == summary.keys() and written["overall"] == summary["overall"]
    (entry,) = summary["points"]
    assert entry["role"] == "interpolation" and entry["force_x_rel_rmse"] == 0.0
    assert entry["twin_surface_accuracy"] == 1.0 and entry["surface_accuracy_skill"] == 1.0
    assert entry["targets_met"]["replay_surface_skill"]
    assert entry["targets_met"]["loop_speedup"] is False  # the same run: 1×, not 50×
    assert sorted(p.name for p in plots.iterdir()) == sorted([FOLDER_MARK, *entry["plots"]])
    assert len(entry["plots"]) == 4  # force, fields, height, surface; no GIF
    assert entry["surface_error_beside"] == 0.0 == summary["overall"]["all"]["surface_error_beside"]
    assert summary["overall"]["all"]["twin_surface_excess_ahead"] == 0.0
    assert summary["overall"]["interpolation"] == summary["overall"]["all"]
    assert summary["overall"]["all"]["loop_speedup"] == 1.0


def test_the_summary_averages_every_figure_the_twins_and_the_skills():
    from dozerlab.reduce.compare import FIGURES
    from dozerlab.reduce.jobs import AGGREGATE

    for key in FIGURES:
        assert {key, f"twin_{key}", f"{key}_skill"} <= AGGREGATE.keys()
