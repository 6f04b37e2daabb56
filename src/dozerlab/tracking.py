"""MLflow records of every bed, simulation, training and validation job.

Runs go to MLflow's local SQLite store (``sqlite:///mlflow.db`` in the working directory, with
artifacts under ``mlruns/``) unless ``MLFLOW_TRACKING_URI`` names another one (a tracking
server, say). When ``DOZERLAB_PARENT_RUN_ID`` is set — the workflow sets it to the run of its
invocation — each job's run is a child of that run. ``DOZERLAB_MLFLOW=0`` turns tracking off.
"""

from __future__ import annotations

import fcntl
import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

PARENT_ENV = "DOZERLAB_PARENT_RUN_ID"
#: ``0`` turns tracking off (``mlflow.enabled: false`` in the workflow).
ENABLED_ENV = "DOZERLAB_MLFLOW"
DEFAULT_URI = "sqlite:///mlflow.db"


def enabled() -> bool:
    """Whether jobs log to MLflow (``DOZERLAB_MLFLOW`` is not ``0``)."""
    return os.environ.get(ENABLED_ENV, "1") != "0"


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


def configure(experiment: str = "dozerlab") -> str:
    """Point MLflow at the tracking store and experiment; return the experiment id."""
    import mlflow

    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    mlflow.set_tracking_uri(uri)
    with _store_lock(uri):
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

    configure(experiment)
    parent = os.environ.get(PARENT_ENV) or None
    all_tags = {"rule": rule, **{k: str(v) for k, v in (tags or {}).items()}}
    with mlflow.start_run(
        run_name=name, parent_run_id=parent, nested=parent is not None, tags=all_tags
    ) as run:
        if params:
            mlflow.log_params(flatten(params))
        yield run
