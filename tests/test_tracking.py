"""MLflow records: jobs' runs under a workflow's parent run, and the store under jobs that start
together (what `snakemake --cores N` or a user's shell loop does on a fresh project)."""

import os
import subprocess
import sys
import time

import pytest
from mlflow.tracking import MlflowClient

from dozerlab import tracking

JOB = """
import sys, time
start = float(sys.argv[1])
while time.time() < start:
    pass
from dozerlab.tracking import tracked_run
with tracked_run("job" + sys.argv[2], rule="test"):
    pass
"""


def test_jobs_started_together_on_a_fresh_store_all_record(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith(("MLFLOW_", "DOZERLAB_"))}
    start = time.time() + 5.0  # past every interpreter's start-up, so they reach the store at once
    procs = [
        subprocess.Popen(
            [sys.executable, "-c", JOB, str(start), str(i)],
            cwd=tmp_path,
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for i in range(4)
    ]
    outputs = [p.communicate(timeout=120)[0] for p in procs]
    assert [p.returncode for p in procs] == [0] * 4, "\n".join(outputs)
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = client.search_runs([client.get_experiment_by_name("dozerlab").experiment_id])
    assert sorted(r.info.run_name for r in runs) == [f"job{i}" for i in range(4)]


def test_flatten_nests_sections_into_dotted_string_params():
    flat = tracking.flatten({"solver": {"dt": 0.01, "iterations": 100}, "seed": 2018, "x": [1, 2]})
    assert flat == {"solver.dt": "0.01", "solver.iterations": "100", "seed": "2018", "x": "[1, 2]"}
    assert len(tracking.flatten({"long": "a" * 10_000})["long"]) == 6000


def test_tracking_off_yields_no_run_and_writes_no_store(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")
    assert not tracking.enabled()
    with tracking.tracked_run("job", rule="test") as run:
        assert run is None
    assert list(tmp_path.iterdir()) == []


def test_parent_run_children_tags_params_and_failed_job(mlflow_store, tmp_path):
    parent = tracking.start_parent_run(
        "dozerlab", "workflow", config={"solver": {"dt": 0.01}}, tags={"configfiles": "a.yaml"}
    )
    os.environ[tracking.PARENT_ENV] = parent
    try:
        with tracking.tracked_run(
            "simulate hill", rule="simulate", tags={"speed": 1.0}, params={"solver": {"dt": 0.01}}
        ):
            pass
        with pytest.raises(RuntimeError), tracking.tracked_run("train", rule="train"):
            raise RuntimeError("boom")
    finally:
        del os.environ[tracking.PARENT_ENV]
    report = tmp_path / "index.html"
    report.write_text("<html></html>")
    logged = tracking.end_parent_run(parent, "FINISHED", [report, tmp_path / "absent.log"])
    assert logged == [report]

    run = mlflow_store.get_run(parent)
    assert run.info.status == "FINISHED"
    assert run.data.params == {"solver.dt": "0.01"}
    assert run.data.tags["rule"] == "workflow" and run.data.tags["configfiles"] == "a.yaml"
    assert [a.path for a in mlflow_store.list_artifacts(parent)] == ["index.html"]
    exp = mlflow_store.get_experiment_by_name("dozerlab").experiment_id
    children = {
        r.info.run_name: r
        for r in mlflow_store.search_runs([exp], f"tags.mlflow.parentRunId = '{parent}'")
    }
    assert children["simulate hill"].info.status == "FINISHED"
    assert children["simulate hill"].data.tags["speed"] == "1.0"
    assert children["simulate hill"].data.params == {"solver.dt": "0.01"}
    assert children["train"].info.status == "FAILED"


def test_end_parent_run_refuses_an_unknown_status(mlflow_store):
    with pytest.raises(ValueError, match="status must be one of"):
        tracking.end_parent_run("0" * 32, "DONE")


def test_a_child_run_goes_into_its_parents_experiment(mlflow_store, monkeypatch):
    parent = tracking.start_parent_run("sweep", "workflow")
    monkeypatch.setenv(tracking.PARENT_ENV, parent)
    with tracking.tracked_run("bed hill", rule="bed") as child:  # default experiment "dozerlab"
        pass
    assert child.info.experiment_id == mlflow_store.get_run(parent).info.experiment_id
    assert mlflow_store.get_experiment_by_name("dozerlab") is None


def test_job_run_follows_the_configs_mlflow_section(mlflow_store):
    off = {"mlflow": {"enabled": False, "experiment": "x"}}
    with tracking.job_run(off, "job", rule="test") as run:
        assert run is None
    on = {"mlflow": {"enabled": True, "experiment": "mine"}}
    with tracking.job_run(on, "job", rule="test", tags={"model": "mlp"}) as run:
        pass
    got = mlflow_store.get_run(run.info.run_id)
    assert mlflow_store.get_experiment(got.info.experiment_id).name == "mine"
    assert got.data.tags["rule"] == "test" and got.data.tags["model"] == "mlp"
