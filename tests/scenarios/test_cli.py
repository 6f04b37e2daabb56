import json

import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.runtime import FIGURE
from dozerlab.scenarios.bed import BED_FILE, Bed
from dozerlab.scenarios.trajectory import Trajectory

TINY = {
    "bed": {
        "length": 0.25,
        "width": 0.12,
        "radius": 0.025,
        "iterations": 15,
        "emitter_speed": 2.0,
        "settle_kinetic_energy": 2.0e-4,
    },
    "scenarios": {"step": {"high_height": 0.14, "low_height": 0.04, "goal_height": 0.08}},
}


def test_bed_command_writes_bed_and_plot(tmp_path, capsys):
    out, png = tmp_path / "beds" / "step.npz", tmp_path / "step.png"
    rc = main(
        [
            "bed",
            "--scenario",
            "step",
            "--config",
            json.dumps(TINY),
            "--out",
            str(out),
            "--plot",
            str(png),
            "--threads",
            "1",
            "--no-progress",
        ]
    )
    assert rc == 0
    bed = Bed.load(out)
    assert bed.scenario == "step" and bed.count > 10 and bed.settle_time.size > 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    # what a rerun may replace (runtime.atomic_output): the bed and figure are recognised as ours
    assert BED_FILE.recognise(out) and FIGURE.recognise(png)


def test_trajectory_command_writes_csv_and_plot(step_bed, tmp_path):
    step_bed.save(tmp_path / "step.npz")
    out, png = tmp_path / "t" / "speed~1.0_depth~0.1.csv", tmp_path / "t.png"
    rc = main(
        [
            "trajectory",
            "--bed",
            str(tmp_path / "step.npz"),
            "--speed",
            "1.0",
            "--depth",
            "0.1",
            "--config",
            "{}",
            "--out",
            str(out),
            "--plot",
            str(png),
        ]
    )
    assert rc == 0
    traj = Trajectory.load_csv(out)
    np.testing.assert_allclose(np.linalg.norm(traj.velocity, axis=1), 1.0, rtol=1e-9)
    assert png.exists()


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["bed", "--scenario", "dune", "--out", "x.npz"], "--scenario 'dune' is not defined"),
        (
            ["trajectory", "--speed", "-1", "--depth", "0.1"],
            "argument --speed: -1.0 is less than the minimum of 0.01",
        ),
        (["trajectory", "--speed", "1", "--depth", "2.0"], "deeper than the bed"),
        (
            [
                "trajectory",
                "--speed",
                "1",
                "--depth",
                "0.1",
                "--config",
                '{"scenarios": {"step": {"goal_height": 3.0}}}',
            ],
            "outside the bed",
        ),
    ],
)
def test_bad_arguments_exit_2_with_a_clear_message(step_bed, tmp_path, capsys, args, message):
    step_bed.save(tmp_path / "step.npz")
    if args[0] == "trajectory":
        args = args + ["--bed", str(tmp_path / "step.npz"), "--out", str(tmp_path / "t.csv")]
    try:
        code = main(args)
    except SystemExit as exc:  # argparse refuses a flag outside the schema's bounds
        code = exc.code
    assert code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "t.csv").exists()


@pytest.mark.slow  # settles a bed; test_bed_command_writes_bed_and_plot is the fast one
def test_bed_command_logs_an_mlflow_run(tmp_path, monkeypatch):
    import mlflow

    monkeypatch.setenv("DOZERLAB_MLFLOW", "1")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.chdir(tmp_path)
    rc = main(
        [
            "bed",
            "--scenario",
            "step",
            "--config",
            json.dumps(TINY),
            "--out",
            "b.npz",
            "--plot",
            "b.png",
            "--no-progress",
        ]
    )
    assert rc == 0
    runs = mlflow.search_runs(experiment_names=["dozerlab"], output_format="list")
    assert len(runs) == 1
    run = runs[0]
    assert run.data.tags["scenario"] == "step" and run.data.tags["rule"] == "bed"
    assert run.data.metrics["particle_count"] == Bed.load("b.npz").count
    assert run.data.params["bed.radius"] == "0.025"
    assert any(a.path == "b.png" for a in mlflow.MlflowClient().list_artifacts(run.info.run_id))
