"""MLflow records: jobs' runs under a workflow's parent run, the store under jobs that start
together (what `snakemake --cores N` or a user's shell loop does on a fresh project), and jobs
whose tracking server is not up yet."""

import os
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest
from mlflow.tracking import MlflowClient

from dozerlab import tracking
from dozerlab.runtime import WORKFLOW_HOST_ENV, WORKFLOW_PID_ENV, DozerlabError

JOB = """
import sys, time
start = float(sys.argv[1])
while time.time() < start:
    pass
from dozerlab.tracking import tracked_run
with tracked_run("job" + sys.argv[2], rule="test"):
    pass
"""


@pytest.mark.slow  # four job processes race to create a store's tables
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


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_wait_limit_refuses_a_bad_value_by_name(monkeypatch):
    monkeypatch.setenv(tracking.WAIT_ENV, "soon")
    with pytest.raises(
        ValueError,
        match=r"DOZERLAB_MLFLOW_WAIT must be a number of seconds in \[0, 86400\], got 'soon'",
    ):
        tracking.wait_limit()
    monkeypatch.setenv(tracking.WAIT_ENV, "-1")
    with pytest.raises(ValueError, match="DOZERLAB_MLFLOW_WAIT"):
        tracking.wait_limit()
    monkeypatch.setenv(tracking.WAIT_ENV, "7.5")
    assert tracking.wait_limit() == 7.5
    monkeypatch.delenv(tracking.WAIT_ENV)
    assert tracking.wait_limit() == tracking.DEFAULT_WAIT_S


def test_a_job_gives_up_on_an_absent_server_after_the_bounded_wait(tmp_path, monkeypatch):
    uri = f"http://127.0.0.1:{free_port()}"  # nothing listens there
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv(tracking.WAIT_ENV, "2")
    monkeypatch.chdir(tmp_path)
    start = time.monotonic()
    with (
        pytest.raises(tracking.TrackingServerUnreachable, match=rf"{uri} .*did not answer for 2 s"),
        tracking.tracked_run("job", rule="test"),
    ):
        pass
    assert time.monotonic() - start >= 2.0  # it did wait, and then stopped
    assert not (tmp_path / "mlflow.db").exists()  # no fallback to a local store


@pytest.mark.slow  # starts a real MLflow server
def test_a_job_waits_for_a_server_that_comes_up_late_and_records_its_run(tmp_path, monkeypatch):
    """A real tracking server on 127.0.0.1, started seconds after the job: the job waits for it,
    and its run lands FINISHED in the server's store."""
    port = free_port()
    uri = f"http://127.0.0.1:{port}"
    backend = f"sqlite:///{tmp_path / 'server.db'}"
    server_cmd = [sys.executable, "-m", "mlflow", "server", "--host", "127.0.0.1", "--port",
                  str(port), "--workers", "1", "--backend-store-uri", backend,
                  "--artifacts-destination", str(tmp_path / "artifacts")]  # fmt: skip
    servers: list[subprocess.Popen] = []

    def start_late() -> None:
        time.sleep(3.0)
        servers.append(
            subprocess.Popen(
                server_cmd,
                stdout=subprocess.DEVNULL,
                stderr=(tmp_path / "server.log").open("w"),
                start_new_session=True,  # the server's workers are stopped with it
            )
        )

    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.setenv(tracking.WAIT_ENV, "180")
    monkeypatch.delenv(tracking.PARENT_ENV, raising=False)
    monkeypatch.chdir(tmp_path)
    starter = threading.Thread(target=start_late)
    starter.start()
    try:
        with tracking.tracked_run("late", rule="test") as run:
            run_id = run.info.run_id
        client = MlflowClient(tracking_uri=uri)
        assert client.get_run(run_id).info.status == "FINISHED"
    finally:
        starter.join()
        for server in servers:  # the server, its uvicorn worker and job consumers: one group
            os.killpg(server.pid, signal.SIGTERM)
            try:
                server.wait(timeout=30)
            except subprocess.TimeoutExpired:
                os.killpg(server.pid, signal.SIGKILL)
                server.wait()
    assert not (tmp_path / "mlflow.db").exists()


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


def test_parent_run_children_tags_params_and_failed_job(mlflow_store, tmp_path, capsys):
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
    report = tmp_path / "report"  # the report's folder: the page and its animations
    (report / "animations").mkdir(parents=True)
    (report / "index.html").write_text("<html></html>")
    (report / "animations" / "a.gif").write_bytes(b"GIF89a")
    (report / ".snakemake_timestamp").write_bytes(b"")  # hidden: not logged
    log = tmp_path / "snakemake.log"
    log.write_text("done")
    headline = {"force_x_rel_rmse/best": 0.25}
    logged = tracking.end_parent_run(
        parent, "FINISHED", [report, log, tmp_path / "absent.log"], headline
    )
    assert logged == [report, log]
    # the count of every job run under the parent, not only those ingested at its end
    said = capsys.readouterr().err
    assert f"MLflow: 2 job runs under workflow run {parent}" in said
    assert "models registered: none" in said

    run = mlflow_store.get_run(parent)
    assert run.info.status == "FINISHED"
    assert run.data.params == {"solver.dt": "0.01"}
    assert run.data.tags["rule"] == "workflow" and run.data.tags["configfiles"] == "a.yaml"
    assert run.data.tags["role"] == "parent"
    assert run.data.metrics["force_x_rel_rmse/best"] == 0.25
    assert run.data.metrics["wall_seconds"] >= 0
    assert [a.path for a in mlflow_store.list_artifacts(parent)] == ["report", "snakemake.log"]
    assert [a.path for a in mlflow_store.list_artifacts(parent, "report")] == [
        "report/animations",
        "report/index.html",
    ]
    assert [a.path for a in mlflow_store.list_artifacts(parent, "report/animations")] == [
        "report/animations/a.gif"
    ]
    exp = mlflow_store.get_experiment_by_name("dozerlab").experiment_id
    children = {
        r.info.run_name: r
        for r in mlflow_store.search_runs([exp], f"tags.mlflow.parentRunId = '{parent}'")
    }
    assert children["simulate hill"].info.status == "FINISHED"
    assert children["simulate hill"].data.tags["speed"] == "1.0"
    assert children["simulate hill"].data.params == {"solver.dt": "0.01"}
    assert children["train"].info.status == "FAILED"
    assert [children[n].data.tags["role"] for n in ("simulate hill", "train")] == [
        "simulate",
        "train",
    ]


def test_run_and_registry_names_have_one_style():
    assert tracking.run_name("simulate", "hill", "speed~1_depth~0.04") == (
        "simulate/hill/speed~1_depth~0.04"
    )
    assert tracking.run_name("compare", "ridge", None, "") == "compare/ridge"
    mine = {"mlflow": {"experiment": "mine"}}
    assert tracking.registered_name(mine, "evolution", "unet") == "mine-evolution-unet"
    assert tracking.registered_name(None, "force", "cnn") == "dozerlab-force-cnn"
    assert set(tracking.ROLES.values()) == {
        "bed",
        "simulate",
        "train",
        "validate",
        "reduce",
        "compare",
        "adaptive",
    }


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


def _sleeper() -> subprocess.Popen:
    """A stand-in for a Snakemake process."""
    return subprocess.Popen([sys.executable, "-c", "import time; time.sleep(120)"])


def _start_as(monkeypatch, proc: subprocess.Popen, name: str) -> str:
    monkeypatch.setenv(WORKFLOW_PID_ENV, str(proc.pid))
    monkeypatch.setenv(WORKFLOW_HOST_ENV, socket.gethostname())
    run_id = tracking.start_parent_run("dozerlab", name)
    monkeypatch.delenv(WORKFLOW_PID_ENV)
    return run_id


def test_the_parent_run_of_a_killed_snakemake_is_closed_as_killed(
    mlflow_store, monkeypatch, capsys
):
    killed, running = _sleeper(), _sleeper()
    try:
        ids = {
            name: _start_as(monkeypatch, p, name)
            for name, p in (("killed", killed), ("running", running))
        }
        tags = mlflow_store.get_run(ids["killed"]).data.tags
        assert tags[tracking.HOST_TAG] == socket.gethostname()
        assert tags[tracking.PID_TAG] == str(killed.pid)
        # A run of another machine cannot be checked from here: it is left alone.
        ids["elsewhere"] = _start_as(monkeypatch, killed, "elsewhere")
        mlflow_store.set_tag(ids["elsewhere"], tracking.HOST_TAG, "another-node")
        os.kill(killed.pid, signal.SIGKILL)
        killed.wait()
        new = tracking.start_parent_run("dozerlab", "next")
        status = {name: mlflow_store.get_run(run_id).info.status for name, run_id in ids.items()}
        assert status == {"killed": "KILLED", "running": "RUNNING", "elsewhere": "RUNNING"}
        assert mlflow_store.get_run(new).info.status == "RUNNING"
        assert f"closed parent run {ids['killed']} as KILLED" in capsys.readouterr().err
    finally:
        for p in (killed, running):
            p.kill()
            p.wait()


def test_a_garbage_tracking_store_is_one_line_naming_it(tmp_path, monkeypatch, capsys):
    """A local mlflow.db that is not SQLite gave a sqlalchemy traceback."""
    from dozerlab.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    monkeypatch.delenv(tracking.PARENT_ENV, raising=False)
    monkeypatch.setenv(tracking.ENABLED_ENV, "1")
    db = tmp_path / "mlflow.db"
    db.write_bytes(b"\x7fELF\x02\x01\x01" + bytes(range(256)) * 8)
    before = db.read_bytes()
    assert main(["mlflow-start", "--config", "{}"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert "MLflow tracking store mlflow.db is not an SQLite database" in err
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{db}")
    with (
        pytest.raises(DozerlabError, match=f"store {db} is not an SQLite database"),
        tracking.tracked_run("job", rule="bed"),
    ):
        pass
    assert db.read_bytes() == before  # left as it was
    db.write_bytes(b"")  # an empty file is a store MLflow creates its tables in
    assert tracking.tracking_uri() == f"sqlite:///{db}"
