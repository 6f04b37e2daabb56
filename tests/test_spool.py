"""Job runs spooled on disk under a workflow and logged to MLflow by one process: complete,
with their own times, never lost, never twice."""

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from dozerlab import spool, tracking
from tests.helpers import imported_by


@pytest.fixture
def workflow(mlflow_store, tmp_path, monkeypatch):
    """A parent run and a spool, as the Snakefile sets them: (client, parent id, spool root)."""
    parent = tracking.start_parent_run("dozerlab", "workflow")
    root = tmp_path / "spool"
    monkeypatch.setenv(tracking.PARENT_ENV, parent)
    monkeypatch.setenv(spool.SPOOL_ENV, str(root))
    return mlflow_store, parent, root


def children(client, parent):
    exp = client.get_run(parent).info.experiment_id
    found = client.search_runs([exp], f"tags.mlflow.parentRunId = '{parent}'")
    return {r.info.run_name: r for r in found}


def test_a_spooled_run_is_logged_whole_with_its_own_times(workflow, tmp_path):
    client, parent, root = workflow
    plots = tmp_path / "plots"
    (plots / "sub").mkdir(parents=True)
    (plots / "a.png").write_bytes(b"png")
    (plots / "sub" / "b.gif").write_bytes(b"gif")
    (tmp_path / "out.json").write_text("{}")
    before = int(time.time() * 1000)
    with tracking.tracked_run(
        "simulate hill", rule="simulate", tags={"speed": 1.0}, params={"solver": {"dt": 0.01}}
    ) as run:
        assert isinstance(run, spool.SpooledRun)
        run.log_metrics({"loss": 2.0}, step=0)
        run.log_metrics({"loss": 1.0}, step=1)
        run.log_artifact(tmp_path / "out.json")
        run.log_artifacts(plots, artifact_path="plots")
        time.sleep(0.05)
    (plots / "a.png").write_bytes(b"rewritten after the job")  # the record keeps its own file
    assert children(client, parent) == {}  # nothing in MLflow before it is ingested

    assert spool.ingest(client, root, parent, with_open=False) == 1
    run = children(client, parent)["simulate hill"]
    assert run.info.status == "FINISHED"
    assert run.data.tags["rule"] == "simulate" and run.data.tags["speed"] == "1.0"
    assert run.data.tags["mlflow.source.name"].startswith("dozerlab")
    assert run.data.params == {"solver.dt": "0.01"}
    history = client.get_metric_history(run.info.run_id, "loss")
    assert sorted((m.step, m.value) for m in history) == [(0, 2.0), (1, 1.0)]
    assert before <= run.info.start_time <= run.info.end_time - 50
    arts = {a.path for a in client.list_artifacts(run.info.run_id)}
    assert arts == {"out.json", "plots"}
    local = client.download_artifacts(run.info.run_id, "plots", str(tmp_path / "dl"))
    assert (tmp_path / "dl" / "plots" / "a.png").read_bytes() == b"png"
    assert os.path.isfile(os.path.join(local, "sub", "b.gif"))
    assert list((root / parent).iterdir()) == []  # logged, so removed


def test_a_spooled_job_imports_no_mlflow(workflow, tmp_path):
    code = (
        "from dozerlab.tracking import tracked_run\n"
        "with tracked_run('job', rule='test', params={'a': 1}) as run:\n"
        "    run.log_metrics({'x': 1.0})"
    )
    assert imported_by(code, ("mlflow",)) == []
    assert len(spool.pending(workflow[2], workflow[1], with_open=False)) == 1


def test_failed_and_killed_jobs_are_logged_so(workflow):
    client, parent, root = workflow
    with pytest.raises(RuntimeError), tracking.tracked_run("train", rule="train"):
        raise RuntimeError("boom")
    code = (
        "import os, signal\n"
        "from dozerlab.tracking import tracked_run\n"
        "with tracked_run('killed', rule='simulate', params={'a': 1}):\n"
        "    os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    assert subprocess.run([sys.executable, "-c", code]).returncode == -signal.SIGKILL
    assert spool.ingest(client, root, parent, with_open=False) == 1  # a running job is left
    assert len(spool.pending(root, parent, with_open=True)) == 1
    assert spool.ingest(client, root, parent, with_open=True) == 1
    runs = children(client, parent)
    assert runs["train"].info.status == "FAILED"
    assert runs["killed"].info.status == "KILLED" and runs["killed"].data.params == {"a": "1"}


def test_an_ingestion_cut_off_midway_is_redone_not_doubled(workflow):
    client, parent, root = workflow
    with tracking.tracked_run("bed hill", rule="bed") as run:
        run.log_metrics({"count": 3.0})
    (folder,) = spool.pending(root, parent, with_open=False)
    record = json.loads((folder / spool.RUN_FILE).read_text())["record"]
    exp = client.get_run(parent).info.experiment_id
    client.create_run(exp, tags={spool.RECORD_TAG: record, "mlflow.parentRunId": parent})
    assert spool.ingest(client, root, parent, with_open=False) == 1
    found = client.search_runs([exp], f"tags.`{spool.RECORD_TAG}` = '{record}'")
    assert len(found) == 1 and found[0].data.metrics == {"count": 3.0}


def test_a_damaged_record_is_refused_by_name_and_kept_the_others_logged(workflow):
    client, parent, root = workflow
    for name in ("bed hill", "bed step"):
        with tracking.tracked_run(name, rule="bed"):
            pass
    folder = spool.pending(root, parent, with_open=False)[0]
    (folder / spool.RUN_FILE).write_text('{"record": "x"')
    with pytest.raises(
        ValueError, match=f"logged 1 job runs; left damaged MLflow spool record {folder}"
    ):
        spool.ingest(client, root, parent, with_open=False)
    assert folder.is_dir() and list(children(client, parent)) == ["bed step"]


STUBBORN = """
import faulthandler, signal, time
signal.signal(signal.SIGTERM, signal.SIG_IGN)
faulthandler.register(signal.SIGUSR1, all_threads=True)
print("ready", flush=True)
def hang_in_a_record():
    time.sleep(60)
hang_in_a_record()
"""


def test_a_follower_that_does_not_stop_is_killed_with_its_stacks_in_its_log(tmp_path):
    log = tmp_path / "ingest.log"
    with open(log, "w") as out:
        proc = subprocess.Popen([sys.executable, "-c", STUBBORN], stdout=out, stderr=out)
    try:
        deadline = time.monotonic() + 30
        while "ready" not in log.read_text():
            assert proc.poll() is None and time.monotonic() < deadline, log.read_text()
            time.sleep(0.05)
        assert not spool.stop_follower(proc, within_s=0.5)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert "in hang_in_a_record" in log.read_text()


def test_a_follower_asked_to_stop_while_it_starts_stops_by_itself(tmp_path, monkeypatch):
    """SIGTERM from the moment its command runs, MLflow's imports included: the follower ends
    by itself, having logged nothing, rather than being cut off at an arbitrary point."""
    monkeypatch.setenv(spool.SPOOL_ENV, str(tmp_path / "spool"))
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    script = (
        "import os, signal, sys\n"
        "from dozerlab import cli\n"
        "sys.argv = ['dozerlab', 'mlflow-ingest', 'nothing', '--follow']\n"
        "import dozerlab.spool as spool\n"
        "stop_on_signals = spool.stop_on_signals\n"
        "def asked_at_once():\n"
        "    stop = stop_on_signals()\n"
        "    os.kill(os.getpid(), signal.SIGTERM)\n"
        "    return stop\n"
        "spool.stop_on_signals = asked_at_once\n"
        "sys.exit(cli.main())\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 0, done.stderr[-3000:]
    assert "logged 0 job runs of workflow run nothing" in done.stderr


@pytest.mark.slow  # a follower process and several jobs
def test_the_follower_logs_runs_as_jobs_end_and_stops_on_sigterm(workflow, tmp_path):
    client, parent, _root = workflow
    follower = subprocess.Popen(
        [sys.executable, "-m", "dozerlab", "mlflow-ingest", parent, "--follow"],
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        with tracking.tracked_run("simulate hill", rule="simulate") as run:
            run.log_metrics({"steps": 10.0})
        deadline = time.monotonic() + 60
        while "simulate hill" not in children(client, parent):
            assert follower.poll() is None and time.monotonic() < deadline, follower.stderr.read()
            time.sleep(0.2)
        follower.send_signal(signal.SIGTERM)
        _, err = follower.communicate(timeout=60)
    finally:
        if follower.poll() is None:
            follower.kill()
    assert follower.returncode == 0, err
    assert f"logged 1 job runs of workflow run {parent}" in err
    assert children(client, parent)["simulate hill"].data.metrics == {"steps": 10.0}


def test_the_end_of_a_workflow_logs_what_is_left_and_the_next_start_what_a_killed_one_left(
    workflow, tmp_path, monkeypatch
):
    client, parent, root = workflow
    with tracking.tracked_run("validate unet", rule="validate"):
        pass
    tracking.end_parent_run(parent, "FINISHED")
    assert children(client, parent)["validate unet"].info.status == "FINISHED"
    assert not (root / parent).exists()

    # A workflow killed before mlflow-end: its parent was closed, its records stay ...
    killed = tracking.start_parent_run("dozerlab", "workflow")
    monkeypatch.setenv(tracking.PARENT_ENV, killed)
    with tracking.tracked_run("simulate step", rule="simulate"):
        pass
    client.set_terminated(killed, status="KILLED")
    # ... and the next workflow's start logs them
    tracking.start_parent_run("dozerlab", "workflow")
    assert children(client, killed)["simulate step"].info.status == "FINISHED"
    assert not (root / killed).exists()


def test_runs_of_a_sweep_point_say_its_group(mlflow_store, tmp_path, monkeypatch):
    """The jobs do not know their point's group (their config leaves the sweep out, so that
    editing it reruns nothing); the parent run records the groups and the ingestion tags them."""
    from dozerlab.config import load_config

    root = tmp_path / "spool"
    monkeypatch.setenv(spool.SPOOL_ENV, str(root))
    sweep = {
        "scenarios": ["hill"],
        "speeds": [1.0, 1.5],
        "depths": [0.04],
        "interpolation": [{"scenario": "hill", "speed": 1.25, "depth": 0.04}],
        "extrapolation": [{"scenario": "hill", "speed": 0.75, "depth": 0.04}],
        "transfer": [{"scenario": "trench", "speed": 1.0, "depth": 0.04}],
    }
    parent = tracking.start_parent_run("dozerlab", "sweep/x", config=load_config({"sweep": sweep}))
    monkeypatch.setenv(tracking.PARENT_ENV, parent)
    for speed in (1.0, 1.25, 0.75, 2.0):
        point = {"scenario": "hill", "speed": speed, "depth": 0.04}
        with tracking.tracked_run(f"simulate {speed}", rule="simulate", tags=point):
            pass
    point = {"scenario": "trench", "speed": 1.0, "depth": 0.04}
    with tracking.tracked_run("simulate trench", rule="simulate", tags=point):
        pass
    with tracking.tracked_run("compare ridge", rule="compare_reduced"):
        pass
    tracking.end_parent_run(parent)
    runs = children(mlflow_store, parent)
    tags = {
        name: (r.data.tags.get("group"), r.data.tags.get("held_out")) for name, r in runs.items()
    }
    assert tags == {
        "simulate 1.0": ("training", "false"),
        "simulate 1.25": ("interpolation", "true"),
        "simulate 0.75": ("extrapolation", "true"),
        "simulate trench": ("transfer", "true"),
        "simulate 2.0": (None, None),  # not a point of this sweep
        "compare ridge": (None, None),
    }
    assert runs["compare ridge"].data.tags["role"] == "compare"
    assert not (root / parent).exists()  # the groups file goes with the last record
