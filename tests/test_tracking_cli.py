"""The workflow's parent run: a run whose Snakemake was killed is closed by the next one."""

import os
import signal
import socket
import subprocess
import sys

import pytest
from mlflow.tracking import MlflowClient

from dozerlab.runtime import WORKFLOW_HOST_ENV, WORKFLOW_PID_ENV
from dozerlab.tracking import PARENT_ENV
from dozerlab.tracking_cli import HOST_TAG, PID_TAG, start_parent_run


@pytest.fixture
def store(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.delenv(PARENT_ENV, raising=False)
    return MlflowClient(tracking_uri=f"sqlite:///{tmp_path / 'mlflow.db'}")


def _sleeper() -> subprocess.Popen:
    """A stand-in for a Snakemake process."""
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])


def _start_as(monkeypatch, proc: subprocess.Popen, name: str, host: str | None = None) -> str:
    monkeypatch.setenv(WORKFLOW_PID_ENV, str(proc.pid))
    monkeypatch.setenv(WORKFLOW_HOST_ENV, socket.gethostname())
    run_id = start_parent_run("dozerlab", name)
    monkeypatch.delenv(WORKFLOW_PID_ENV)
    return run_id


def test_the_parent_run_of_a_killed_snakemake_is_closed_as_killed(store, monkeypatch, capsys):
    killed, running = _sleeper(), _sleeper()
    try:
        ids = {
            name: _start_as(monkeypatch, p, name)
            for name, p in (("killed", killed), ("running", running))
        }
        tags = store.get_run(ids["killed"]).data.tags
        assert tags[HOST_TAG] == socket.gethostname() and tags[PID_TAG] == str(killed.pid)
        # A run of another machine cannot be checked from here: it is left alone.
        ids["elsewhere"] = _start_as(monkeypatch, killed, "elsewhere")
        store.set_tag(ids["elsewhere"], HOST_TAG, "another-node")
        os.kill(killed.pid, signal.SIGKILL)
        killed.wait()
        new = start_parent_run("dozerlab", "next")
        status = {name: store.get_run(run_id).info.status for name, run_id in ids.items()}
        assert status == {"killed": "KILLED", "running": "RUNNING", "elsewhere": "RUNNING"}
        assert store.get_run(new).info.status == "RUNNING"
        assert f"closed parent run {ids['killed']} as KILLED" in capsys.readouterr().err
    finally:
        for p in (killed, running):
            p.kill()
            p.wait()


def test_the_internal_commands_are_hidden_from_help(capsys):
    from dozerlab.cli import main

    with pytest.raises(SystemExit):
        main(["--help"])
    listed = capsys.readouterr().out
    assert "simulate" in listed and "mlflow-start" not in listed and "mlflow-end" not in listed
    with pytest.raises(SystemExit):
        main(["mlflow-end", "--help"])  # still there for the Snakefile's hooks
    assert "--status" in capsys.readouterr().out
