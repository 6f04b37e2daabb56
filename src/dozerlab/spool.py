"""Job runs recorded on disk under a workflow, logged to MLflow by one process.

Importing MLflow and opening its store cost a job about 3 s (1–2 s of imports, 0.6–0.9 s for
the SQLite store's schema check, the rest in ``start_run``): more than a quick-config simulation
steps, and some 4 core-minutes of the default sweep's 80 jobs (BENCHMARKS.md). So a job of a
workflow that records its run here — the Snakefile sets ``DOZERLAB_MLFLOW_SPOOL`` next to the
parent run's ``DOZERLAB_PARENT_RUN_ID`` — writes it as a folder, without importing MLflow::

    <spool>/<parent run id>/<record>/run.json        name, tags, params, metrics, times, status
    <spool>/<parent run id>/<record>/artifacts/...   copies of the files the job logged
    <spool>/<parent run id>/<record>/model/...       a copy of the model directory it logged
    <spool>/<parent run id>/groups.json              the sweep's points: their group (mlflow-start)

A job's folder is ``.open-<record>`` while it runs and ``<record>`` once its status is known.
One process logs the finished ones as MLflow child runs of the parent, with the job's own start
and end times, and then removes them: ``dozerlab mlflow-ingest RUN_ID --follow`` runs beside the
workflow (the runs show in ``mlflow ui`` a second or two after their jobs end), and
``mlflow-end`` logs what is left when the workflow ends, an open record as a KILLED run (its job
was killed outright). A record is removed only after its run is complete in MLflow, and a run
half-logged by an ingestion that was cut off is replaced (each run carries its record's name as
the ``dozerlab.record`` tag): nothing is lost or logged twice. ``mlflow-start`` logs the records
that a killed workflow left.

Ingestion also adds what a job does not know: the ``group`` of its sweep point (``training``,
``interpolation``, ``extrapolation`` or ``transfer``, from ``groups.json``) with ``held_out`` (``true`` or
``false``) on runs tagged with a point, and it registers a logged model in the MLflow Model
Registry under the name the job gave (:func:`register_model`).
"""

from __future__ import annotations

import faulthandler
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from pathlib import Path
from typing import Any

#: The spool folder; set by the workflow, with ``DOZERLAB_PARENT_RUN_ID``.
SPOOL_ENV = "DOZERLAB_MLFLOW_SPOOL"
RECORD_TAG = "dozerlab.record"
OPEN_PREFIX = ".open-"
RUN_FILE = "run.json"
MODEL_DIR = "model"
GROUPS_FILE = "groups.json"
#: A sweep point's role (:mod:`dozerlab.sweep`) as the ``group`` tag of its runs.
GROUP_OF_ROLE = {
    "train": "training",
    "interpolation": "interpolation",
    "extrapolation": "extrapolation",
    "transfer": "transfer",
}
#: MLflow's limits on one ``log_batch`` call.
PARAMS_PER_BATCH, METRICS_PER_BATCH = 100, 1000


def spool_root() -> Path | None:
    """The spool folder named by ``DOZERLAB_MLFLOW_SPOOL``, or None when jobs log directly."""
    raw = os.environ.get(SPOOL_ENV, "")
    return Path(raw) if raw else None


def _now_ms() -> int:
    return int(time.time() * 1000)


def _write_json(path: Path, doc: Mapping[str, Any]) -> None:
    """Replace ``path`` with ``doc`` at once (a reader sees the old or the new file, never half)."""
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(doc))
    os.replace(tmp, path)


class SpooledRun:
    """One job's run, recorded in its spool folder; the methods match MLflow's fluent API."""

    def __init__(self, folder: Path, doc: dict[str, Any]) -> None:
        self.folder = folder
        self.doc = doc

    def log_metrics(self, metrics: Mapping[str, float], step: int | None = None) -> None:
        """Record ``metrics`` (at ``step``, default 0) with the time of the call."""
        stamp = _now_ms()
        self.doc["metrics"].extend([k, float(v), stamp, int(step or 0)] for k, v in metrics.items())

    def log_artifact(self, path: str | Path, artifact_path: str | None = None) -> None:
        """Record the file at ``path`` (under ``artifact_path`` in the run's artifacts)."""
        dest = self.folder / "artifacts" / (artifact_path or "")
        dest.mkdir(parents=True, exist_ok=True)
        shutil.copy2(path, dest / Path(path).name)

    def log_artifacts(self, directory: str | Path, artifact_path: str | None = None) -> None:
        """Record every file under ``directory`` (under ``artifact_path``), as it lies there."""
        dest = self.folder / "artifacts" / (artifact_path or "")
        shutil.copytree(directory, dest, dirs_exist_ok=True)

    def log_model(self, directory: str | Path, registered_name: str | None = None) -> str:
        """Record the saved MLflow model ``directory`` as the run's model, to be registered as
        a version of ``registered_name`` when given; its ``models:/`` URI is known once it is
        logged, so "" here."""
        shutil.copytree(directory, self.folder / MODEL_DIR)
        if registered_name:
            self.doc["registered_model"] = registered_name
        return ""

    def save(self) -> None:
        _write_json(self.folder / RUN_FILE, self.doc)


@contextmanager
def spooled_run(
    root: Path,
    parent: str,
    name: str,
    tags: Mapping[str, str],
    params: Mapping[str, str],
) -> Iterator[SpooledRun]:
    """Record one job's run under ``root/parent``; a job that raises records FAILED."""
    record = f"{time.time_ns():020d}-{os.getpid()}-{uuid.uuid4().hex[:8]}"
    folder = root / parent / (OPEN_PREFIX + record)
    folder.mkdir(parents=True)
    command = " ".join(["dozerlab", *sys.argv[1:2]])
    doc: dict[str, Any] = {
        "record": record,
        "name": name,
        "tags": {"mlflow.source.name": command, "mlflow.source.type": "LOCAL", **tags},
        "params": dict(params),
        "metrics": [],
        "start_time": _now_ms(),
        "end_time": None,
        "status": "RUNNING",
    }
    run = SpooledRun(folder, doc)
    run.save()  # a job killed outright leaves this: logged KILLED, with its params
    status = "FAILED"
    try:
        yield run
        status = "FINISHED"
    finally:
        doc["status"], doc["end_time"] = status, _now_ms()
        run.save()
        os.rename(folder, folder.with_name(record))


def pending(root: Path, parent: str, *, with_open: bool) -> list[Path]:
    """The record folders of ``parent`` under ``root`` in the order their jobs began; the open
    ones (jobs still running, or killed) only ``with_open``."""
    base = root / parent
    if not base.is_dir():
        return []
    found = [
        d
        for d in base.iterdir()
        if d.is_dir()
        and (d / RUN_FILE).is_file()
        and (with_open or not d.name.startswith(OPEN_PREFIX))
    ]
    return sorted(found, key=lambda d: d.name.removeprefix(OPEN_PREFIX))


def _load(folder: Path) -> dict[str, Any]:
    """A record's run.json, refused by name when it is not one."""
    try:
        doc = json.loads((folder / RUN_FILE).read_text())
        missing = {"record", "name", "tags", "params", "metrics", "start_time", "status"} - set(doc)
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"damaged MLflow spool record {folder}: {exc}") from exc
    if missing:
        raise ValueError(f"damaged MLflow spool record {folder}: no {sorted(missing)}")
    return dict(doc)


def log_record(client: Any, experiment_id: str, parent: str, folder: Path) -> str:
    """Log the record in ``folder`` as a child run of ``parent``; return the run id.

    A record still open is logged KILLED, ending when it was last written. A run of the same
    record left by an ingestion that was cut off is deleted first."""
    from mlflow.entities import Metric, Param
    from mlflow.tracking.context.registry import resolve_tags

    doc = _load(folder)
    doc["tags"].update(group_tags(folder.parent, doc["tags"]))
    status, end = doc["status"], doc["end_time"]
    if status == "RUNNING":
        status, end = "KILLED", int((folder / RUN_FILE).stat().st_mtime * 1000)
    query = f"tags.`{RECORD_TAG}` = '{doc['record']}'"
    for old in client.search_runs([experiment_id], filter_string=query, max_results=10):
        client.delete_run(old.info.run_id)
    tags = resolve_tags({**doc["tags"], "mlflow.parentRunId": parent, RECORD_TAG: doc["record"]})
    run_id: str = client.create_run(
        experiment_id, start_time=doc["start_time"], tags=tags, run_name=doc["name"]
    ).info.run_id
    params = [Param(k, v) for k, v in doc["params"].items()]
    for i in range(0, len(params), PARAMS_PER_BATCH):
        client.log_batch(run_id, params=params[i : i + PARAMS_PER_BATCH])
    metrics = [Metric(k, v, stamp, step) for k, v, stamp, step in doc["metrics"]]
    for i in range(0, len(metrics), METRICS_PER_BATCH):
        client.log_batch(run_id, metrics=metrics[i : i + METRICS_PER_BATCH])
    if (folder / "artifacts").is_dir():
        client.log_artifacts(run_id, str(folder / "artifacts"))
    if (folder / MODEL_DIR).is_dir():
        uri = log_model_dir(client, experiment_id, run_id, folder / MODEL_DIR)
        if doc.get("registered_model") and status == "FINISHED":
            register_model(client, doc["registered_model"], uri, run_id, parent)
    client.set_terminated(run_id, status=status, end_time=end)
    return run_id


def register_model(
    client: Any, name: str, model_uri: str, run_id: str, parent: str | None = None
) -> int:
    """Register the logged model ``model_uri`` (``models:/<model id>``) as a new version of
    ``name`` in the MLflow Model Registry, creating ``name`` if needed; return the version.

    The version is tagged with its run and, under a workflow, the parent run, so
    ``models:/NAME/VERSION`` leads back to the sweep that trained it."""
    from mlflow.exceptions import MlflowException

    try:
        client.create_registered_model(name)
    except MlflowException as exc:
        if exc.error_code not in ("RESOURCE_ALREADY_EXISTS", "ALREADY_EXISTS"):
            raise
    tags = {"dozerlab.run_id": run_id} | ({"dozerlab.parent_run_id": parent} if parent else {})
    version = client.create_model_version(
        name,
        source=model_uri,
        run_id=run_id,
        tags=tags,
        model_id=model_uri.removeprefix("models:/"),
    )
    return int(version.version)


def write_groups(root: Path, parent: str, groups: Mapping[str, str]) -> None:
    """Record the group of each sweep point (``scenario/speed~S_depth~D``: ``training``,
    ``interpolation``, ``extrapolation`` or ``transfer``) for the ingestion of ``parent``'s records."""
    (root / parent).mkdir(parents=True, exist_ok=True)
    _write_json(root / parent / GROUPS_FILE, dict(groups))


def group_tags(base: Path, tags: Mapping[str, str]) -> dict[str, str]:
    """The ``group`` and ``held_out`` tags of a run tagged with a sweep point (``scenario``,
    ``speed``, ``depth``) that ``base/groups.json`` names; none otherwise."""
    from dozerlab.sweep import point_name

    path = base / GROUPS_FILE
    if not path.is_file() or not {"scenario", "speed", "depth"} <= set(tags):
        return {}
    try:
        key = f"{tags['scenario']}/{point_name(float(tags['speed']), float(tags['depth']))}"
    except ValueError:
        return {}
    group = json.loads(path.read_text()).get(key)
    if group is None:
        return {}
    return {"group": group, "held_out": str(group != GROUP_OF_ROLE["train"]).lower()}


def log_model_dir(client: Any, experiment_id: str, run_id: str, directory: str | Path) -> str:
    """Log a saved MLflow model ``directory`` as the model ``model`` of run ``run_id`` (a
    LoggedModel with the run as its source and output, as ``log_model`` makes); return its
    ``models:/`` URI."""
    from mlflow.entities import LoggedModelOutput, LoggedModelStatus

    model = client.create_logged_model(experiment_id, name=MODEL_DIR, source_run_id=run_id)
    client.log_model_artifacts(model.model_id, str(directory))
    client.finalize_logged_model(model.model_id, LoggedModelStatus.READY)
    client.log_outputs(run_id, [LoggedModelOutput(model.model_id, step=0)])
    return f"models:/{model.model_id}"


def ingest(client: Any, root: Path, parent: str, *, with_open: bool) -> int:
    """Log and remove the records of ``parent`` (see :func:`pending`); return how many.

    A damaged record is left where it is and named, after the others are logged."""
    damaged = []
    count = 0
    for folder in pending(root, parent, with_open=with_open):
        try:
            _log_and_remove(client, parent, folder)
            count += 1
        except ValueError as exc:
            damaged.append(str(exc))
    if damaged:
        raise ValueError(f"logged {count} job runs; left " + "; ".join(damaged))
    return count


def _log_and_remove(client: Any, parent: str, folder: Path) -> None:
    log_record(client, client.get_run(parent).info.experiment_id, parent, folder)
    shutil.rmtree(folder)


def clear(root: Path, parent: str) -> None:
    """Remove ``parent``'s spool folder if it holds no record (its groups file goes with it)."""
    base = root / parent
    if base.is_dir() and not pending(root, parent, with_open=True):
        (base / GROUPS_FILE).unlink(missing_ok=True)
        if not any(base.iterdir()):
            base.rmdir()


def parents(root: Path) -> list[str]:
    """The parent run ids with records under ``root``."""
    return sorted(d.name for d in root.iterdir() if d.is_dir()) if root.is_dir() else []


#: How long a follower asked to stop may take to finish the record it is logging.
FOLLOWER_STOP_S = 30.0


def stop_on_signals() -> threading.Event:
    """An event that SIGTERM and SIGINT set from now on, for a follower to stop at its next
    check: raised as ``SystemExit`` instead, a signal would land anywhere in MLflow's imports or
    a record's logging. SIGUSR1 writes the process's thread stacks to stderr, so that one that
    does not stop can be seen where it hangs (:func:`stop_follower`)."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set())
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    return stop


def start_follower(parent: str, log: Path) -> subprocess.Popen[bytes]:
    """``dozerlab mlflow-ingest PARENT --follow`` in a session of its own (Ctrl-C reaches the
    workflow alone, which stops it with :func:`stop_follower`), its output appended to ``log``."""
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "dozerlab", "mlflow-ingest", parent, "--follow"],
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,
        )


def stop_follower(proc: subprocess.Popen[bytes], within_s: float = FOLLOWER_STOP_S) -> bool:
    """Ask the follower ``proc`` to stop (SIGTERM) and wait up to ``within_s`` seconds for it to
    finish its record; one still running then writes its thread stacks to its log (SIGUSR1) and
    is killed. Returns whether it stopped by itself. A killed follower loses nothing: mlflow-end
    logs the records it left, replacing a run it had half logged."""
    proc.terminate()
    try:
        proc.wait(timeout=within_s)
        return True
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(0.5)  # for the stacks to be written
        proc.kill()
        proc.wait()
        return False


def follow(client: Any, root: Path, parent: str, stop: threading.Event, poll_s: float = 1.0) -> int:
    """Log ``parent``'s records as their jobs finish, until ``stop`` is set
    (:func:`stop_on_signals`); the record being logged then is completed first. Returns how
    many were logged."""
    count = 0
    damaged: set[Path] = set()  # named once, left for mlflow-end to name again
    while not stop.is_set():
        for folder in pending(root, parent, with_open=False):
            if stop.is_set():
                break
            if folder in damaged:
                continue
            try:
                _log_and_remove(client, parent, folder)
                count += 1
            except ValueError as exc:
                damaged.add(folder)
                print(exc, file=sys.stderr, flush=True)
        stop.wait(poll_s)
    return count
