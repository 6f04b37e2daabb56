"""MLflow records of every bed, simulation, training and validation job.

Runs go to MLflow's local SQLite store (``sqlite:///mlflow.db`` in the working directory, with
artifacts under ``mlruns/``) unless ``MLFLOW_TRACKING_URI`` names another one (a tracking
server, say). When ``DOZERLAB_PARENT_RUN_ID`` is set — the workflow sets it to the run of its
invocation — each job's run is a child of that run. ``DOZERLAB_MLFLOW=0`` turns tracking off.

A tracking server that does not answer yet (restarting, or still starting when the jobs do) is
waited for, up to ``DOZERLAB_MLFLOW_WAIT`` seconds (default 120), before a job gives up with an
error that names the server. A job running under SLURM tags its run with ``slurm_job_id``.

The parent run of one workflow invocation: the Snakefile's ``onstart`` handler (which Snakemake
calls only when jobs will run) starts it (:func:`start_parent_run`, ``dozerlab mlflow-start``)
before any job does, so the experiment and a fresh SQLite store are created once, not raced by
parallel jobs; it exports the run id as ``DOZERLAB_PARENT_RUN_ID``. ``onsuccess`` / ``onerror``
end it FINISHED / FAILED (:func:`end_parent_run`, ``dozerlab mlflow-end``) and attach the
artifacts (the report, Snakemake's log) that this invocation wrote.

Every run carries a ``role`` tag (``parent``, ``bed``, ``simulate``, ``train``, ``validate``,
``reduce``, ``compare``, ``adaptive``; :data:`ROLES`) beside its ``rule``, and a name in one style,
``<role>/<what>[/<point>]`` (:func:`run_name`): ``simulate/hill/speed~1_depth~0.04``,
``train/force/unet``, ``validate/evolution/ridge``, ``reduce/ridge/hill/speed~1.25_depth~0.06``,
``compare/ridge``, the parent ``sweep/<config file>``. A trained model is registered in the
MLflow Model Registry as ``<experiment>-force-<model>`` or ``<experiment>-evolution-<model>``
(the loop's force model ``<experiment>-force-<model>-loop-<dynamics model>``;
:func:`registered_name`), one version per training, so ``models:/NAME/VERSION`` loads it. The
parent run ends with the sweep's headline figures as metrics (:mod:`dozerlab.headline`) and its
wall time.

A Snakemake killed outright (SIGKILL, a lost node) ends nothing: its run would stay RUNNING.
So the parent run carries the workflow process's host, pid and start time as tags, and the next
``mlflow-start`` closes, as KILLED, every RUNNING parent run whose process on this host is gone.
"""

from __future__ import annotations

import fcntl
import os
import socket
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Iterator, Mapping, Sequence
from contextlib import AbstractContextManager, contextmanager, nullcontext
from pathlib import Path
from typing import Any, Protocol

from dozerlab import spool
from dozerlab.runtime import DozerlabError, process_token, workflow_process
from dozerlab.spool import spool_root, spooled_run

PARENT_ENV = "DOZERLAB_PARENT_RUN_ID"
#: ``0`` turns tracking off (``mlflow.enabled: false`` in the workflow).
ENABLED_ENV = "DOZERLAB_MLFLOW"
DEFAULT_URI = "sqlite:///mlflow.db"
#: How a parent run may end (``dozerlab mlflow-end --status``).
STATUSES = ("FINISHED", "FAILED", "KILLED")
#: Tags naming the workflow process of a parent run (see the module docstring).
HOST_TAG, PID_TAG, TOKEN_TAG = "dozerlab.host", "dozerlab.pid", "dozerlab.pid_start"
WAIT_ENV = "DOZERLAB_MLFLOW_WAIT"
DEFAULT_WAIT_S = 120.0
MAX_WAIT_S = 86400.0
#: The ``role`` tag of each rule's job runs; the workflow's own run is the ``parent``.
ROLES = {
    "bed": "bed",
    "simulate": "simulate",
    "twin": "simulate",
    "train": "train",
    "train_dynamics": "train",
    "train_loop_force": "train",
    "validate": "validate",
    "validate_dynamics": "validate",
    "reduce": "reduce",
    "reduce_training_points": "reduce",
    "compare_reduced": "compare",
    "adaptive_record": "adaptive",
    "adaptive_curve": "adaptive",
}
PARENT_ROLE = "parent"


def run_name(*parts: object) -> str:
    """A run's name: its parts (role first, then what it is about, then its point) joined by
    ``/``; empty parts are left out."""
    return "/".join(str(p) for p in parts if p not in (None, ""))


def registered_name(config: Mapping[str, Any] | None, family: str, model: str) -> str:
    """The Model Registry name of a trained model: ``<experiment>-<family>-<model>``
    (``family``: ``force`` or ``evolution``; the experiment from the config's ``mlflow``)."""
    experiment = (config or {}).get("mlflow", {}).get("experiment", "dozerlab")
    return f"{experiment}-{family}-{model}"


class TrackingServerUnreachable(RuntimeError):
    """The MLflow tracking server did not answer within the bounded wait."""


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


#: The first bytes of every SQLite database file.
_SQLITE_MAGIC = b"SQLite format 3\x00"


def tracking_uri() -> str:
    """The tracking store's URI (``MLFLOW_TRACKING_URI``, default :data:`DEFAULT_URI`).

    A local SQLite store that exists but is not an SQLite database (a garbage or truncated
    ``mlflow.db``) is refused with :class:`~dozerlab.runtime.DozerlabError` naming the file,
    before MLflow opens it and fails with a database traceback.
    """
    uri = os.environ.get("MLFLOW_TRACKING_URI", DEFAULT_URI)
    prefix = "sqlite:///"
    if uri.startswith(prefix):
        path = Path(uri[len(prefix) :])
        try:
            with open(path, "rb") as db:
                head = db.read(len(_SQLITE_MAGIC))
        except FileNotFoundError:
            return uri  # MLflow creates it
        except OSError as exc:
            raise DozerlabError(
                f"MLflow tracking store {path} cannot be read: {exc.strerror}"
            ) from None
        if head and head != _SQLITE_MAGIC:
            raise DozerlabError(
                f"MLflow tracking store {path} is not an SQLite database (it does not start with "
                "'SQLite format 3'); move it away, or set MLFLOW_TRACKING_URI to another store"
            )
    return uri


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


def configure(experiment: str = "dozerlab", parent: str | None = None) -> str:
    """Point MLflow at the tracking store and experiment; return the experiment id.

    With a ``parent`` run id the experiment is the parent's, whatever ``experiment`` says: a
    child run outside its parent's experiment would not show under it. A tracking server is
    first waited for (:func:`wait_for_server`).
    """
    import mlflow

    uri = tracking_uri()
    wait_for_server(uri, wait_limit())
    mlflow.set_tracking_uri(uri)
    with _store_lock(uri):
        if parent is not None:
            experiment_id = mlflow.get_run(parent).info.experiment_id
            return mlflow.set_experiment(experiment_id=experiment_id).experiment_id
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


class JobRun(Protocol):
    """What a job logs to its run (MLflow's fluent calls, for a live or a spooled run)."""

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None: ...

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None: ...

    def log_artifacts(self, directory: str | Path, artifact_path: str | None = None) -> None: ...

    def log_model(self, directory: str | Path, registered_name: str | None = None) -> str:
        """Log a saved MLflow model directory as the run's model, registered as a new version
        of ``registered_name`` when given; its URI, or "" if not yet."""
        ...


class LiveRun:
    """The job's active MLflow run (``info``: MLflow's RunInfo of it)."""

    def __init__(self, run: Any) -> None:
        self.info = run.info

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        import mlflow

        mlflow.log_metrics(dict(metrics), step=step)

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        import mlflow

        mlflow.log_artifact(str(path), artifact_path=artifact_path)

    def log_artifacts(self, directory: str | Path, artifact_path: str | None = None) -> None:
        import mlflow

        mlflow.log_artifacts(str(directory), artifact_path=artifact_path)

    def log_model(self, directory: str | Path, registered_name: str | None = None) -> str:
        from mlflow import MlflowClient

        client = MlflowClient()
        uri = spool.log_model_dir(client, self.info.experiment_id, self.info.run_id, directory)
        if registered_name:
            parent = os.environ.get(PARENT_ENV) or None
            spool.register_model(client, registered_name, uri, self.info.run_id, parent)
        return uri


@contextmanager
def tracked_run(
    name: str,
    *,
    rule: str,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
    experiment: str = "dozerlab",
) -> Iterator[JobRun | None]:
    """Open an MLflow run for one job; yields it, or None when tracking is off.

    The run goes into ``experiment``, or, under a parent run (``DOZERLAB_PARENT_RUN_ID``), into
    the parent's experiment. ``tags`` (scenario, speed, depth, model, …), the ``rule`` tag and
    its ``role`` (:data:`ROLES`) make runs filterable in ``mlflow ui``; ``params`` may be nested (config sections) and are
    flattened. A job that raises leaves its run marked FAILED. Under a workflow with a spool
    (``DOZERLAB_MLFLOW_SPOOL``, :mod:`dozerlab.spool`) the run is recorded there, without
    MLflow.
    """
    if not enabled():
        yield None
        return
    parent = os.environ.get(PARENT_ENV) or None
    all_tags = {"rule": rule, "role": ROLES.get(rule, rule)}
    all_tags |= {k: str(v) for k, v in (tags or {}).items()}
    if os.environ.get("SLURM_JOB_ID"):
        all_tags["slurm_job_id"] = os.environ["SLURM_JOB_ID"]
    root = spool_root()
    if parent is not None and root is not None:
        with spooled_run(root, parent, name, all_tags, flatten(params or {})) as spooled:
            yield spooled
        return
    import mlflow

    configure(experiment, parent)
    with mlflow.start_run(
        run_name=name, parent_run_id=parent, nested=parent is not None, tags=all_tags
    ) as run:
        if params:
            mlflow.log_params(flatten(params))
        yield LiveRun(run)


def job_run(
    config: Mapping[str, Any] | None,
    name: str,
    *,
    rule: str,
    tags: Mapping[str, Any] | None = None,
    params: Mapping[str, Any] | None = None,
) -> AbstractContextManager[JobRun | None]:
    """:func:`tracked_run` as a job's validated ``config`` asks: no run (None) when
    ``mlflow.enabled`` is false, else one in ``mlflow.experiment``. Every job opens its run so."""
    cfg = (config or {}).get("mlflow", {})
    if not cfg.get("enabled", True):
        return nullcontext(None)
    experiment = cfg.get("experiment", "dozerlab")
    return tracked_run(name, rule=rule, tags=tags, params=params, experiment=experiment)


def close_stale_runs(client: Any, experiment_id: str) -> list[str]:
    """End as KILLED the RUNNING parent runs whose workflow process on this host is gone.

    Runs of other hosts, and runs without the process tags, are left alone (their process
    cannot be checked from here). Returns the ids closed.
    """
    runs = client.search_runs(
        [experiment_id],
        filter_string="tags.rule = 'workflow' and attributes.status = 'RUNNING'",
        max_results=1000,
    )
    closed = []
    for run in runs:
        tags = run.data.tags
        if tags.get(HOST_TAG) != socket.gethostname() or not tags.get(PID_TAG, "").isdigit():
            continue
        if process_token(int(tags[PID_TAG])) != tags.get(TOKEN_TAG):
            client.set_tag(run.info.run_id, "dozerlab.closed", "its snakemake process was gone")
            client.set_terminated(run.info.run_id, status="KILLED")
            closed.append(run.info.run_id)
    return closed


def start_parent_run(
    experiment: str,
    name: str,
    *,
    config: Mapping[str, Any] | None = None,
    tags: Mapping[str, str] | None = None,
) -> str:
    """Create the experiment if needed and a RUNNING parent run in it; return the run id.

    First closes the stale parent runs of this host (:func:`close_stale_runs`); the new run is
    tagged with the workflow's process (``DOZERLAB_WORKFLOW_PID``) when it runs on this host.
    ``config`` (the validated config) is logged flattened as the run's params. When
    ``DOZERLAB_PARENT_RUN_ID`` is already set (the workflow itself runs inside a tracked run),
    the new run is nested under that one.
    """
    from mlflow import MlflowClient
    from mlflow.entities import Param

    experiment_id = configure(experiment)
    client = MlflowClient()
    for run_id in close_stale_runs(client, experiment_id):
        print(
            f"closed parent run {run_id} as KILLED: its snakemake process is gone", file=sys.stderr
        )
    ingest_ended(client)
    all_tags = {"rule": "workflow", "role": PARENT_ROLE, "workdir": str(Path.cwd())}
    all_tags |= dict(tags or {})
    if (proc := workflow_process()) is not None:
        all_tags |= {HOST_TAG: socket.gethostname(), PID_TAG: str(proc[0]), TOKEN_TAG: proc[1]}
    outer = os.environ.get(PARENT_ENV)
    if outer:
        all_tags["mlflow.parentRunId"] = outer
    run = client.create_run(experiment_id, tags=all_tags, run_name=name)
    if config:
        params = [Param(k, v) for k, v in flatten(config).items()]
        for i in range(0, len(params), 100):  # MLflow takes at most 100 params per batch
            client.log_batch(run.info.run_id, params=params[i : i + 100])
        if (root := spool_root()) is not None and "sweep" in config:
            spool.write_groups(root, run.info.run_id, point_groups(config))
    return run.info.run_id


def point_groups(config: Mapping[str, Any]) -> dict[str, str]:
    """Each sweep point of the validated ``config`` (``scenario/speed~S_depth~D``) and its
    group: ``training``, ``interpolation``, ``extrapolation`` or ``transfer`` (the held-out
    ones; ``transfer`` on terrain of no training point)."""
    from dozerlab.sweep import sweep_points

    return {f"{p.scenario}/{p.name}": spool.GROUP_OF_ROLE[p.role] for p in sweep_points(config)}


def end_parent_run(
    run_id: str,
    status: str = "FINISHED",
    artifacts: Sequence[str | Path] = (),
    metrics: Mapping[str, float] | None = None,
) -> list[Path]:
    """End the parent run with ``status``, logging each of ``artifacts`` written since it began
    (a file, or a folder, the report's, whose files are logged under its name), ``metrics``
    (the sweep's headline figures) and ``wall_seconds`` (since the run began).

    Paths that do not exist, or that are older than the run (a report this invocation did not
    rebuild), are skipped. Prints the paths logged, how many job runs the parent holds and the
    models this invocation registered. Returns the paths logged.
    """
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}, got '{status}'")
    from mlflow import MlflowClient
    from mlflow.entities import Metric

    uri = tracking_uri()
    client = MlflowClient(tracking_uri=uri)
    run = client.get_run(run_id)
    started = run.info.start_time / 1000.0
    if (root := spool_root()) is not None:
        spool.ingest(client, root, run_id, with_open=True)
        spool.clear(root, run_id)
    logged = []
    for path in map(Path, artifacts):
        if path.is_file() and path.stat().st_mtime >= started:
            client.log_artifact(run_id, str(path))
            logged.append(path)
            print(f"MLflow: logged {path} on the workflow run", file=sys.stderr)
        elif path.is_dir() and _newest(path) >= started:
            for file in _files(path):  # under the folder's name, as they lie in it
                where = file.parent.relative_to(path.parent).as_posix()
                client.log_artifact(run_id, str(file), artifact_path=where)
            logged.append(path)
            print(f"MLflow: logged {path} on the workflow run", file=sys.stderr)
    now = int(time.time() * 1000)
    figures = {**(metrics or {}), "wall_seconds": now / 1000.0 - started}
    client.log_batch(run_id, metrics=[Metric(k, float(v), now, 0) for k, v in figures.items()])
    client.set_terminated(run_id, status=status)
    children = client.search_runs(
        [run.info.experiment_id],
        filter_string=f"tags.mlflow.parentRunId = '{run_id}'",
        max_results=10000,
    )
    experiment = client.get_experiment(run.info.experiment_id).name
    print(
        f"MLflow: {len(children)} job runs under workflow run {run_id} "
        f"(experiment {experiment}, {uri})\n        " + registered_summary(client, run_id),
        file=sys.stderr,
    )
    return logged


def registered_summary(client: Any, parent: str) -> str:
    """``models registered: NAME vN, …`` for the model versions of workflow run ``parent``."""
    versions = client.search_model_versions(f"tags.`dozerlab.parent_run_id` = '{parent}'")
    names = sorted(f"{v.name} v{v.version}" for v in versions)
    return "models registered: " + (", ".join(names) if names else "none")


def _files(folder: Path) -> list[Path]:
    """The files under ``folder``, without hidden ones (Snakemake's ``.snakemake_timestamp``)."""
    return sorted(
        f
        for f in folder.rglob("*")
        if f.is_file() and not any(p.startswith(".") for p in f.relative_to(folder).parts)
    )


def _newest(folder: Path) -> float:
    """The latest modification time (s since the epoch) of the files under ``folder``, 0 if none."""
    return max((f.stat().st_mtime for f in _files(folder)), default=0.0)


def _remove_if_empty(folder: Path) -> None:
    if folder.is_dir() and not any(folder.iterdir()):
        folder.rmdir()


def ingest_ended(client: Any) -> None:
    """Log the spooled job runs that ended workflows left (their snakemake was killed before
    ``mlflow-end``): those of parent runs no longer RUNNING in this store."""
    root = spool_root()
    if root is None:
        return
    from mlflow.exceptions import MlflowException

    for parent in spool.parents(root):
        try:
            status = client.get_run(parent).info.status
        except MlflowException:
            print(f"spooled runs of {parent}: no such run in this store; left", file=sys.stderr)
            continue
        if status != "RUNNING":
            count = spool.ingest(client, root, parent, with_open=True)
            print(f"logged {count} job runs that workflow run {parent} left", file=sys.stderr)
            spool.clear(root, parent)


def _spool_client() -> tuple[Path, Any]:
    """The spool folder and a client of the tracking store (a server is waited for)."""
    from mlflow import MlflowClient

    root = spool_root()
    if root is None:
        raise ValueError(f"{spool.SPOOL_ENV} is not set: no spooled job runs to log")
    uri = tracking_uri()
    wait_for_server(uri, wait_limit())
    return root, MlflowClient(tracking_uri=uri)


def ingest_finished(run_id: str) -> int:
    """Log the spooled runs of workflow run ``run_id`` whose jobs have ended; return how many."""
    root, client = _spool_client()
    return spool.ingest(client, root, run_id, with_open=False)


def follow_parent(run_id: str, stop: threading.Event) -> int:
    """Log the spooled runs of workflow run ``run_id`` as its jobs end, until ``stop`` is set
    (``dozerlab mlflow-ingest --follow``, beside the workflow). Returns how many."""
    root, client = _spool_client()
    return spool.follow(client, root, run_id, stop)
