"""``dozerlab adaptive-points``, ``adaptive-record`` and ``adaptive-curve`` on real files, and
the validation of ``sweep.adaptive``."""

import json
from pathlib import Path

import pytest

from dozerlab import sweep as P
from dozerlab.adaptive.curve import LOOP_COLUMNS, read_curve
from dozerlab.adaptive.design import read_points, round_zero
from dozerlab.cli import main
from dozerlab.config import load_config, read_yaml
from dozerlab.runtime import ConfigError
from tests.helpers import write

SWEEP = {
    "scenarios": ["hill"],
    "speeds": [0.5, 1.5],
    "depths": [0.05, 0.15],
    "interpolation": [{"scenario": "hill", "speed": 0.75, "depth": 0.1}],
    "extrapolation": [{"scenario": "hill", "speed": 2.0, "depth": 0.1}],
}
ADAPTIVE = {
    "enabled": True,
    "rounds": 1,
    "per_round": 2,
    "min_spacing": 0.5,
    "members": 8,
    "compare": True,
    "random_designs": 1,
}


def config(**adaptive) -> str:
    doc = {
        "sweep": {**SWEEP, "adaptive": {**ADAPTIVE, **adaptive}},
        "learn": {"models": ["linear"], "history": 1},
        "mlflow": {"enabled": False},
    }
    return json.dumps(doc)


@pytest.mark.parametrize(
    ("adaptive", "message"),
    [
        ({"initial": {"kind": "grid"}}, "sweep.adaptive.initial.kind"),
        ({"candidates": {"kind": "lattice", "count": 1}}, "sweep.adaptive.candidates.count"),
        ({"min_spacing": -0.1}, "sweep.adaptive.min_spacing"),
        ({"members": 1}, "sweep.adaptive.members"),
        ({"per_round": 0}, "sweep.adaptive.per_round"),
        ({"rounds": 2.5}, "sweep.adaptive.rounds"),
        ({"budget": 12}, "budget"),
    ],
)
def test_invalid_adaptive_fields_are_named(adaptive, message):
    with pytest.raises(ConfigError, match=message.replace(".", r"\.")):
        load_config({"sweep": {"adaptive": adaptive}})


def test_the_adaptive_config_spends_at_most_two_thirds_of_the_grids_runs():
    repo = Path(__file__).resolve().parents[2]
    base, over = (
        read_yaml(repo / "config" / "config.yaml"),
        read_yaml(repo / "config" / "adaptive.yaml"),
    )
    for key, value in over.items():  # Snakemake's overlay: mappings merged key by key
        base[key] = {**base[key], **value} if isinstance(value, dict) else value
    cfg = load_config(base)
    ad = cfg["sweep"]["adaptive"]
    assert ad["enabled"]
    grid = len(P.by_role(P.sweep_points(cfg), "train"))
    initial = len(round_zero(cfg))
    assert grid == 18 and initial + ad["rounds"] * ad["per_round"] <= 2 * grid // 3


def round_files(tmp_path, cfg):
    """Round 0's points, its NDEM runs as synthetic stores, round 1's points (through the CLI)."""
    results = tmp_path / "results"
    r0 = P.adaptive_path("adaptive_points", results, 0)
    assert main(["adaptive-points", "--round", "0", "--config", cfg, "--out", str(r0)]) == 0
    stores = [
        write(P.field_path(results, p), p.speed, p.depth, steps=40)
        for p in (r.point for r in read_points(r0))
    ]
    r1 = P.adaptive_path("adaptive_points", results, 1)
    argv = [
        "adaptive-points",
        "--round",
        "1",
        "--config",
        cfg,
        "--previous",
        str(r0),
        "--stores",
        *map(str, stores),
    ]
    assert main([*argv, "--out", str(r1)]) == 0
    return results, r0, r1


def test_rounds_write_points_away_from_earlier_runs(tmp_path, capsys):
    _, r0, r1 = round_files(tmp_path, config())
    first = read_points(r0)
    assert {(r.point.speed, r.point.depth) for r in first} == {
        (0.5, 0.05),
        (1.5, 0.05),
        (0.5, 0.15),
        (1.5, 0.15),
    }
    assert all(r.why.startswith("initial design") for r in first)
    second = read_points(r1)
    assert len(second) == 2
    assert not {r.point for r in second} & {r.point for r in first}
    assert all("run-to-run spread" in r.why and r.score > 0 for r in second)
    assert "round 1: hill speed~" in capsys.readouterr().out


def test_a_round_without_the_earlier_runs_is_refused(tmp_path, capsys):
    results = tmp_path / "results"
    r0 = P.adaptive_path("adaptive_points", results, 0)
    assert main(["adaptive-points", "--round", "0", "--config", config(), "--out", str(r0)]) == 0
    out = P.adaptive_path("adaptive_points", results, 1)
    assert (
        main(
            [
                "adaptive-points",
                "--round",
                "1",
                "--config",
                config(),
                "--previous",
                str(r0),
                "--out",
                str(out),
            ]
        )
        == 2
    )
    assert "no NDEM run given for hill/speed~0.5_depth~0.05" in capsys.readouterr().err
    assert not out.exists()


def test_the_record_and_the_learning_curve(tmp_path, capsys):
    cfg = config()
    results, r0, r1 = round_files(tmp_path, cfg)
    loaded = load_config(json.loads(cfg))
    points = P.sweep_points(loaded)
    for p in points:
        if p.role != "train" or not P.field_path(results, p).exists():
            write(P.field_path(results, p), p.speed, p.depth, steps=40)
    for r in read_points(r1):
        if not P.field_path(results, r.point).exists():
            write(P.field_path(results, r.point), r.point.speed, r.point.depth, steps=40)
    # the random designs draw from the 3 × 3 lattice: every candidate gets a store
    from dozerlab.adaptive.design import Box, candidates

    for p in candidates(
        ["hill"], Box.of(loaded["sweep"]), loaded["sweep"]["adaptive"]["candidates"]
    ):
        if not P.field_path(results, p).exists():
            write(P.field_path(results, p), p.speed, p.depth, steps=40)
    # the held-out points' replay loops (other fields than NDEM's) and twins
    held_out = [p for p in points if p.role != "train"]
    for i, p in enumerate(held_out):
        attrs = {"warmup_rows": 2}
        write(P.reduced_path(results, "replay", p), p.speed, p.depth, attrs, steps=40, seed=i + 1)
        write(P.twin_path(results, p), p.speed, p.depth, steps=40, seed=i + 7)
    model = P.adaptive_path("adaptive_model", results, 1, "linear")
    train = [str(P.field_path(results, s.point)) for s in read_points(r0) + read_points(r1)]
    argv = ["train", "--model", "linear", "--train", *train, "--config", cfg, "--out", str(model)]
    assert main(argv) == 0
    record = P.adaptive_path("adaptive_record", results, 1)
    argv = ["adaptive-record", "--config", cfg, "--rounds", str(r0), str(r1)]
    argv += ["--models", str(model), "--results", str(results), "--out", str(record)]
    assert main(argv) == 0
    doc = json.loads(record.read_text())
    assert (doc["round"], doc["runs"], len(doc["points"]), doc["errors"]) == (1, 6, 2, {})
    loop = doc["reduced"]["linear"]
    assert 0 < loop["reduced_force_lp_rel_rmse"] < 1 and 0 < loop["twin_force_lp_rel_rmse"] < 1
    assert "linear in the replay loop, low-passed force_x rel. RMSE" in capsys.readouterr().out
    out = results / P.PATHS["learning_curve"]
    plots = results / P.PATHS["learning_curve_plots"]
    argv = [
        "adaptive-curve",
        "--config",
        cfg,
        "--rounds",
        str(r0),
        str(r1),
        "--results",
        str(results),
    ]
    assert main([*argv, "--out", str(out), "--plots", str(plots)]) == 0
    rows = read_curve(out)
    got = {(r["design"], r["seed"], r["runs"]) for r in rows}
    seed = loaded["seed"]
    assert got == {("adaptive", -1, 4), ("adaptive", -1, 6), ("grid", -1, 4)} | {
        ("random", seed, n) for n in (4, 6)
    }
    assert all(0 < r["heldout_force_rel_rmse"] < 1 for r in rows)
    # the reduced simulation: the loops' force model of each set, beside the twins
    assert all(r["reduced_force_model"] == "linear" for r in rows)
    assert all(0 < r[k] < 1 for r in rows for k in LOOP_COLUMNS[:2])
    (adaptive_6,) = [r for r in rows if (r["design"], r["runs"]) == ("adaptive", 6)]
    assert adaptive_6["reduced_force_lp_rel_rmse"] == pytest.approx(
        loop["reduced_force_lp_rel_rmse"], rel=1e-4
    )
    assert sorted(p.name for p in plots.iterdir() if p.suffix == ".png") == [
        "learning_curve.png",
        "rounds_map.png",
    ]
