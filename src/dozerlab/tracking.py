"""MLflow records of every bed, simulation, training and validation job.

Runs go to MLflow's local SQLite store (``sqlite:///mlflow.db`` in the working directory, with
artifacts under ``mlruns/``) unless ``MLFLOW_TRACKING_URI`` names another one (a tracking
server, say). When ``DOZERLAB_PARENT_RUN_ID`` is set — the workflow sets it to the run of its
invocation — each job's run is a child of that run. ``DOZERLAB_MLFLOW=0`` turns tracking off.

A tracking server that does not answer yet (restarting, or still starting when the jobs do) is
waited for, up to ``DOZERLAB_MLFLOW_WAIT`` seconds (default 120), before a job gives up with an
error that names the server. A job running under SLURM tags its run with ``slurm_job_id``.
"""

from __future__ import annotations

import fcntl
import os
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

PARENT_ENV = "DOZERLAB_PARENT_RUN_ID"
DEFAULT_URI = "sqlite:///mlflow.db"
WAIT_ENV = "DOZERLAB_MLFLOW_WAIT"
DEFAULT_WAIT_S = 120.0
MAX_WAIT_S = 86400.0


class TrackingServerUnreachable(RuntimeError):
    """The MLflow tracking server did not answer within the bounded wait."""


def enabled() -> bool:
    """Whether jobs log to MLflow (``DOZERLAB_MLFLOW`` is not ``0``)."""
    return os.environ.get("DOZERLAB_MLFLOW", "1") != "0"


@contextmanager
def _store_lock(uri: str) -> Iterator[None]:
    """Hold an exclusive lock next to a local SQLite store (``<db>.lock``); other URIs need none.

    Jobs started together on a fresh store would each create its tables and experiment, and all
    but one fail ("table ... already exists"); under the lock the first creates them and the
    others find them."""
    prefix = "sqlite:///"
    if not uri.startswith(prefix):
        yield
        return
    with open(uri[len(prefix) :] + ".lock", "a") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


def wait_limit() -> float:
    """Seconds to wait for a tracking server: ``DOZERLAB_MLFLOW_WAIT``, 0–86400, default 120."""
    raw = os.environ.get(WAIT_ENV, "")
    if not raw:
        return DEFAULT_WAIT_S
    try:
        value = float(raw)
    except ValueError:
        value = -1.0
    if not 0.0 <= value <= MAX_WAIT_S:
        raise ValueError(
            f"{WAIT_ENV} must be a number of seconds in [0, {MAX_WAIT_S:g}], got '{raw}'"
        )
    return value


def wait_for_server(uri: str, limit_s: float) -> None:
    """Return once the tracking server at ``uri`` answers its ``/health`` endpoint.

    Polls with a growing interval (0.5 s doubling to 8 s) for at most ``limit_s`` seconds, then
    raises :class:`TrackingServerUnreachable`. URIs other than http(s) return at once.
    """
    if not uri.startswith(("http://", "https://")):
        return
    health = uri.rstrip("/") + "/health"
    deadline = time.monotonic() + limit_s
    interval = 0.5
    while True:
        try:
            with urllib.request.urlopen(health, timeout=5) as response:
                if response.status == 200:
                    return
                reason = f"HTTP {response.status}"
        except (urllib.error.URLError, OSError) as err:
            reason = str(getattr(err, "reason", err))
        left = deadline - time.monotonic()
        if left <= 0:
            raise TrackingServerUnreachable(
                f"MLflow tracking server {uri} (MLFLOW_TRACKING_URI) did not answer for "
                f"{limit_s:g} s ({reason}); start it, or set {WAIT_ENV} to wait longer"
            )
        time.sleep(min(interval, left))
        interval = min(2 * interval, 8.0)


def configure(experiment: str = "dozerlab", parent_run_id: str | None = None) -> str:
    """Point MLflow at the tracking store and experiment; return the experiment id.

    With ``parent_run_id`` the experiment is the parent run's, whatever ``experiment`` says: a
    job whose command is not given the config's ``mlflow.experiment`` (bed, simulate) still lands
    beside its parent. A tracking server is first waited for (:func:`wait_for_server`).
    """
    import mlflow

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    wait_for_server(uri, wait_limit())
    mlflow.set_tracking_uri(uri)
    with _store_lock(uri):
        if parent_run_id:
            parent = mlflow.MlflowClient().get_run(parent_run_id)
            return mlflow.set_experiment(experiment_id=parent.info.experiment_id).experiment_id
        return mlflow.set_experiment(experiment).experiment_id


def flatten(params: Mapping[str, Any], prefix: str = "") -> dict[str, str]:
    """Flatten nested config sections into ``section.field`` keys with string values."""
    out: dict[str, str] = {}
    for key, value in params.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping):
            out.update(flatten(value, f"{name}."))
        else:
            out[name] = str(value)[:6000]
    return out


@contextmanager
def tracked_run(
    name: str,
    *,
    rule: str,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    experiment: str = "dozerlab",
) -> Iterator[Any]:
    """Open an MLflow run for one job; yields the active run, or None when tracking is off.

    ``tags`` (scenario, speed, depth, model, …) and the ``rule`` tag make runs filterable in
    ``mlflow ui``; ``params`` may be nested (config sections) and are flattened. A job that
    raises leaves its run marked FAILED.
    """
    if not enabled():
        yield None
        return
    import mlflow

    parent = os.environ.get(PARENT_ENV) or None
    configure(experiment, parent)
    all_tags = {"rule": rule, **{k: str(v) for k, v in (tags or {}).items()}}
    if os.environ.get("SLURM_JOB_ID"):
        all_tags["slurm_job_id"] = os.environ["SLURM_JOB_ID"]
    with mlflow.start_run(
        run_name=name, parent_run_id=parent, nested=parent is not None, tags=all_tags
    ) as run:
        if params:
            mlflow.log_params(flatten(params))
        yield run
