"""The cluster path, for real: the quick sweep through SLURM with MLflow on a tracking server
backed by PostgreSQL (the services of ``.ci/cluster up``, which CI starts before pytest).

One run of ``snakemake --workflow-profile slurm --configfile config/quick.yaml`` (the README's
command, the plugin polling SLURM every 5 s instead of 40: a private test cluster can afford it,
and the sweep's chain of short jobs otherwise waits out a poll at every link) in a temporary
directory; the checks read what it left: every job was a SLURM job, the
report exists, and the server's PostgreSQL store holds one parent run with every child FINISHED.
Skipped, with the reason, when the services are absent.
"""

import os
import re
import subprocess
import sys
import time
import urllib.request
import uuid
from pathlib import Path

import pytest

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.tracking import PARENT_ENV
from tests.helpers import expected_job_runs, expected_jobs

pytestmark = [pytest.mark.cluster, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "config" / "quick.yaml"
CFG = load_config(QUICK)
POINTS = P.sweep_points(CFG)
MODELS = CFG["learn"]["models"]
ENV_FILE = Path(os.environ.get("DOZERLAB_CLUSTER_STATE", "/tmp/dozerlab-cluster")) / "env"
SUBMITTED = re.compile(r"has been submitted with SLURM jobid (\d+) \(log: (.+?)\)")


def read_env_file() -> dict[str, str]:
    """The ``export KEY=VALUE`` lines ``.ci/cluster up`` wrote."""
    out = {}
    for line in ENV_FILE.read_text().splitlines():
        key, _, value = line.removeprefix("export ").partition("=")
        out[key.strip()] = value.strip()
    return out


def services() -> tuple[dict[str, str] | None, str]:
    """The cluster's client environment, or None and the reason it cannot be used."""
    if not ENV_FILE.is_file():
        return None, f"no cluster services ({ENV_FILE} missing): run `.ci/cluster up` as root"
    env = read_env_file()
    need = {"SLURM_CONF", "MLFLOW_TRACKING_URI", "DOZERLAB_CLUSTER_BACKEND"}
    if not need <= env.keys():
        return None, f"{ENV_FILE} lacks {sorted(need - env.keys())}: rerun `.ci/cluster up`"
    try:
        sinfo = subprocess.run(
            ["sinfo", "--noheader", "--format", "%T"],
            env={**os.environ, "SLURM_CONF": env["SLURM_CONF"]},
            capture_output=True,
            text=True,
            timeout=30,
        )
    except FileNotFoundError:
        return None, "SLURM's sinfo is not installed: run `.ci/cluster up` as root"
    if sinfo.returncode != 0 or not re.search(r"idle|mixed|allocated", sinfo.stdout):
        return None, f"SLURM does not answer or has no usable node: {sinfo.stderr.strip()[:200]}"
    try:
        with urllib.request.urlopen(env["MLFLOW_TRACKING_URI"] + "/health", timeout=5):
            pass
    except OSError as err:
        return None, f"MLflow server {env['MLFLOW_TRACKING_URI']} does not answer: {err}"
    try:
        import psycopg2
        import snakemake_executor_plugin_slurm  # noqa: F401
    except ImportError as err:
        return None, f"cluster extras missing ({err}): pip install -r requirements-slurm.txt"
    with psycopg2.connect(env["DOZERLAB_CLUSTER_BACKEND"], connect_timeout=5):
        pass
    return env, ""


ENV, WHY = services()
if ENV is None:
    pytestmark.append(pytest.mark.skip(reason=WHY))


def slurm_snakemake(workdir: Path, experiment: str, *overlay: str) -> subprocess.CompletedProcess:
    """The README's cluster command in ``workdir``, MLflow runs going to ``experiment``."""
    extra = workdir / "test-overlay.yaml"
    extra.write_text("\n".join([f"mlflow: {{experiment: {experiment}}}", *overlay]) + "\n")
    drop = {PARENT_ENV, "DOZERLAB_MLFLOW", "MLFLOW_EXPERIMENT_NAME"}
    env = {k: v for k, v in os.environ.items() if k not in drop and not k.startswith("SLURM_")}
    env.update(ENV or {})
    cmd = [sys.executable, "-m", "snakemake", "--workflow-profile", "slurm",
           "-s", str(REPO / "Snakefile"), "--directory", str(workdir),
           "--slurm-init-seconds-before-status-checks", "5",
           "--configfile", str(QUICK), str(extra)]  # fmt: skip
    return subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=1800)


def server_runs(experiment: str) -> list:
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=ENV["MLFLOW_TRACKING_URI"])
    exp = client.get_experiment_by_name(experiment)
    return [] if exp is None else client.search_runs([exp.experiment_id], max_results=1000)


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    workdir = tmp_path_factory.mktemp("slurm")
    experiment = f"cluster-test-{uuid.uuid4().hex[:8]}"
    start = time.monotonic()
    done = slurm_snakemake(workdir, experiment)
    wall = time.monotonic() - start
    print(f"quick sweep through SLURM: {wall:.0f} s")  # shown with pytest -s; README records it
    assert done.returncode == 0, done.stderr[-5000:]
    # the console shows a line per job; Snakemake's own log keeps every submission and its log
    (log,) = (workdir / ".snakemake" / "log").glob("*.snakemake.log")
    return workdir, experiment, log.read_text()


EXPECTED_RUNS = expected_job_runs(CFG)
EXPECTED_JOBS = expected_jobs(CFG)


def test_every_job_ran_as_a_slurm_job_with_its_log_kept(sweep):
    workdir, _, log = sweep
    submitted = SUBMITTED.findall(log)
    jobs = sum(EXPECTED_JOBS.values()) + len(POINTS) + 1  # and a trajectory per point, the report
    assert len(submitted) == jobs, log[-3000:]
    assert len({job_id for job_id, _ in submitted}) == jobs
    for job_id, path in submitted:
        slurm_log = Path(path)
        assert slurm_log.is_file() and slurm_log.name == f"{job_id}.log"
        assert workdir in slurm_log.parents
    assert "Select jobs to execute" in log and "Finished jobid" in log


def test_the_report_exists(sweep):
    workdir, _, _ = sweep
    text = (workdir / "results" / "report" / "index.html").read_text()
    for model in MODELS:
        assert f'id="validation-{model}"' in text


def test_the_postgres_store_holds_one_parent_and_every_child_finished(sweep):
    workdir, experiment, log = sweep
    all_runs = server_runs(experiment)
    parents = [r for r in all_runs if r.data.tags.get("rule") == "workflow"]
    assert len(parents) == 1
    parent = parents[0]
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["workdir"] == str(workdir)
    children = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    assert len(all_runs) == 1 + len(children)
    rules = sorted(r.data.tags["rule"] for r in children)
    assert {rule: rules.count(rule) for rule in EXPECTED_RUNS} == EXPECTED_RUNS
    assert len(children) == sum(EXPECTED_RUNS.values())
    slurm_ids = {job_id for job_id, _ in SUBMITTED.findall(log)}
    child_ids = [r.data.tags.get("slurm_job_id") for r in children]
    assert set(child_ids) <= slurm_ids
    # one SLURM job per run, but the training points' reduced runs of one model share a job
    shared = {
        r.data.tags.get("slurm_job_id")
        for r in children
        if r.data.tags["rule"] == "reduce_training_points"
    }
    assert len(shared) == EXPECTED_JOBS["reduce_training_points"]
    assert len(set(child_ids)) == sum(EXPECTED_JOBS.values())
    # Straight from PostgreSQL: the server's backend store holds them, every one FINISHED.
    import psycopg2

    with psycopg2.connect(ENV["DOZERLAB_CLUSTER_BACKEND"]) as db, db.cursor() as cur:
        cur.execute(
            "select r.status, count(*) from runs r join experiments e"
            " on r.experiment_id = e.experiment_id where e.name = %s group by r.status",
            (experiment,),
        )
        assert dict(cur.fetchall()) == {"FINISHED": 1 + len(children)}


def test_a_job_no_node_can_hold_is_refused_before_anything_is_submitted(tmp_path):
    experiment = f"cluster-refused-{uuid.uuid4().hex[:8]}"
    done = slurm_snakemake(tmp_path, experiment, "threads: {bed: 64}")
    assert done.returncode != 0
    assert "refusing to submit: job bed (scenario=hill) asks 64 threads" in done.stderr
    assert "threads.<rule>" in done.stderr
    assert not SUBMITTED.search(done.stderr)
    assert server_runs(experiment) == []  # refused before the parent run, too
