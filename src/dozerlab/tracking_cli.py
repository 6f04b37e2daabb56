"""``dozerlab mlflow-start`` / ``mlflow-end`` — the parent MLflow run of one workflow invocation.

The Snakefile's ``onstart`` handler (which Snakemake calls only when jobs will run) starts the
parent run before any job does, so the experiment and a fresh SQLite store are created once,
not raced by parallel jobs; it exports the run id as ``DOZERLAB_PARENT_RUN_ID`` and every job's
``tracking.tracked_run`` becomes its child. ``onsuccess`` / ``onerror`` end it FINISHED / FAILED
and attach the artifacts (the report, Snakemake's log) that this invocation wrote.

A Snakemake killed outright (SIGKILL, a lost node) ends nothing: its run would stay RUNNING.
So the parent run carries the workflow process's host, pid and start time as tags, and the next
``mlflow-start`` closes, as KILLED, every RUNNING parent run whose process on this host is gone.
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

STATUSES = ("FINISHED", "FAILED", "KILLED")
#: Tags naming the workflow process of a parent run (see the module docstring).
HOST_TAG, PID_TAG, TOKEN_TAG = "dozerlab.host", "dozerlab.pid", "dozerlab.pid_start"


def close_stale_runs(client: Any, experiment_id: str) -> list[str]:
    """End as KILLED the RUNNING parent runs whose workflow process on this host is gone.

    Runs of other hosts, and runs without the process tags, are left alone (their process
    cannot be checked from here). Returns the ids closed.
    """
    from dozerlab.runtime import process_token

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

    from dozerlab import tracking
    from dozerlab.runtime import workflow_process

    experiment_id = tracking.configure(experiment)
    client = MlflowClient()
    for run_id in close_stale_runs(client, experiment_id):
        print(
            f"closed parent run {run_id} as KILLED: its snakemake process is gone", file=sys.stderr
        )
    all_tags = {"rule": "workflow", "workdir": str(Path.cwd()), **dict(tags or {})}
    if (proc := workflow_process()) is not None:
        all_tags |= {HOST_TAG: socket.gethostname(), PID_TAG: str(proc[0]), TOKEN_TAG: proc[1]}
    outer = os.environ.get(tracking.PARENT_ENV)
    if outer:
        all_tags["mlflow.parentRunId"] = outer
    run = client.create_run(experiment_id, tags=all_tags, run_name=name)
    if config:
        params = [Param(k, v) for k, v in tracking.flatten(config).items()]
        for i in range(0, len(params), 100):  # MLflow takes at most 100 params per batch
            client.log_batch(run.info.run_id, params=params[i : i + 100])
    return run.info.run_id


def end_parent_run(
    run_id: str, status: str = "FINISHED", artifacts: Sequence[str | Path] = ()
) -> list[Path]:
    """End the parent run with ``status``, logging each of ``artifacts`` written since it began.

    Paths that do not exist, or that are older than the run (a report this invocation did not
    rebuild), are skipped. Returns the paths logged.
    """
    if status not in STATUSES:
        raise ValueError(f"status must be one of {STATUSES}, got '{status}'")
    from mlflow import MlflowClient

    from dozerlab import tracking

    client = MlflowClient(tracking_uri=os.environ.get("MLFLOW_TRACKING_URI", tracking.DEFAULT_URI))
    started = client.get_run(run_id).info.start_time / 1000.0
    logged = []
    for path in map(Path, artifacts):
        if path.is_file() and path.stat().st_mtime >= started:
            client.log_artifact(run_id, str(path))
            logged.append(path)
    client.set_terminated(run_id, status=status)
    return logged


def register(sub: argparse._SubParsersAction) -> None:
    # Internal (the Snakefile's hooks call them): no help= keeps them out of `dozerlab --help`.
    p = sub.add_parser(
        "mlflow-start", description="start the parent MLflow run of a workflow; print its id"
    )
    p.add_argument(
        "--experiment",
        default=None,
        help="experiment name (default: the config's mlflow.experiment)",
    )
    p.add_argument("--name", default="workflow", help="run name")
    p.add_argument(
        "--config", default=None, help="YAML file or inline JSON, logged as the run's params"
    )
    p.add_argument(
        "--tag", action="append", default=[], metavar="KEY=VALUE", help="a tag (repeatable)"
    )
    p.set_defaults(func=_start)

    p = sub.add_parser(
        "mlflow-end", description="end a parent MLflow run, logging the artifacts it produced"
    )
    p.add_argument("run_id", help="the id mlflow-start printed")
    p.add_argument("--status", default="FINISHED", choices=STATUSES)
    p.add_argument(
        "--artifact",
        action="append",
        default=[],
        metavar="PATH",
        help="a file to log if this invocation wrote it (repeatable)",
    )
    p.set_defaults(func=_end)


def _start(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config

    cfg = load_config(args.config)
    tags = {}
    for item in args.tag:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"--tag must be KEY=VALUE, got '{item}'")
        tags[key] = value
    experiment = args.experiment or cfg["mlflow"]["experiment"]
    print(start_parent_run(experiment, args.name, config=cfg, tags=tags))
    return 0


def _end(args: argparse.Namespace) -> int:
    for path in end_parent_run(args.run_id, args.status, args.artifact):
        print(f"logged {path}", file=sys.stderr)
    return 0
