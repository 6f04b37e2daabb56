"""A tiny adaptive sweep for real: Snakemake's checkpoints write two rounds after the initial
design, their NDEM runs, training and validation are ordinary jobs, and MLflow holds a run per
round. The quick sweep's bed and ranges (config/quick.yaml) with an adaptive overlay: the tests'
lattice bed diverged at some of a 3 × 3 lattice's points (grains jammed where the blade's edge
cuts a layer through its centres)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from dozerlab import sweep as P
from dozerlab.adaptive.curve import read_curve
from dozerlab.adaptive.design import read_points
from dozerlab.config import load_config, read_yaml

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
QUICK = REPO / "config" / "quick.yaml"
OVERLAY = {
    "sweep": {
        "adaptive": {
            "enabled": True,
            "rounds": 2,
            "per_round": 1,
            "candidates": {"kind": "lattice", "count": 3},
            "min_spacing": 0.5,
            "members": 8,
        },
    },
    "learn": {"models": ["linear"]},
}


def snakemake(workdir: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "snakemake", *args, "--cores", "2", "-s", str(REPO / "Snakefile")]
    cmd += ["--directory", str(workdir), "--configfile", str(QUICK), str(workdir / "adaptive.yaml")]
    drop = {
        "DOZERLAB_PARENT_RUN_ID",
        "MLFLOW_TRACKING_URI",
        "DOZERLAB_MLFLOW",
        "MLFLOW_EXPERIMENT_NAME",
    }
    env = {k: v for k, v in os.environ.items() if k not in drop}
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=3600)


def test_a_two_round_adaptive_sweep_runs_resumes_and_records_each_round(tmp_path):
    (tmp_path / "adaptive.yaml").write_text(yaml.safe_dump(OVERLAY))
    quick = read_yaml(QUICK)
    cfg = load_config(
        {
            **quick,
            "sweep": {**quick["sweep"], **OVERLAY["sweep"]},
            "learn": {**quick["learn"], **OVERLAY["learn"]},
        }
    )
    results = tmp_path / P.RESULTS
    # round 1's record first (an interrupted sweep), then the rest from there
    first = snakemake(tmp_path, str(P.adaptive_path("adaptive_record", P.RESULTS, 1)))
    assert first.returncode == 0, first.stderr[-4000:]
    assert not P.adaptive_path("adaptive_points", results, 2).exists()
    done = snakemake(tmp_path)
    assert done.returncode == 0, done.stderr[-4000:]
    assert "adaptive_points round=0" not in done.stderr  # round 0 was not redone

    rounds = [read_points(P.adaptive_path("adaptive_points", results, r)) for r in range(3)]
    assert [len(r) for r in rounds] == [4, 1, 1]
    picked = [s.point for r in rounds for s in r]
    assert len(set(picked)) == 6
    assert (
        P.SweepPoint("hill", 1.25, 0.06) not in picked
    )  # the held-out point at the lattice's centre
    for s in rounds[1] + rounds[2]:
        assert "run-to-run spread" in s.why and s.score > 0
        assert P.field_path(results, s.point).is_dir()  # its NDEM run was made
    for r in range(3):
        record = json.loads(P.adaptive_path("adaptive_record", results, r).read_text())
        assert record["runs"] == 4 + r and 0 < record["errors"]["linear"] < 10
    curve = read_curve(results / P.PATHS["learning_curve"])
    assert [(c["design"], c["runs"]) for c in curve] == [
        ("adaptive", 4),
        ("adaptive", 5),
        ("adaptive", 6),
    ]
    assert (results / P.PATHS["learning_curve_plots"] / "rounds_map.png").is_file()

    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name(cfg["mlflow"]["experiment"])
    runs = client.search_runs([exp.experiment_id], "tags.rule = 'adaptive_record'")
    assert sorted(r.data.tags["round"] for r in runs) == ["0", "1", "2"]
    assert all(
        "runs" in r.data.metrics and "heldout_force_rel_rmse_linear" in r.data.metrics for r in runs
    )

    again = snakemake(tmp_path)
    assert again.returncode == 0 and "Nothing to be done" in again.stderr + again.stdout
