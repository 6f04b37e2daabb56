"""Command-line interface: ``python -m dozerlab <command> …`` (or the ``dozerlab`` script).

Each layer registers its commands from its own ``cli`` module (``dozerlab.<layer>.cli``); the
commands of no layer (``config``, ``mlflow-start``, ``mlflow-end``, ``mlflow-ingest``) are
registered here. Every ``cli`` module's top level imports only argparse so that ``--help`` is
instant; heavy imports happen inside the handlers, and a handler's work is a call into its layer
(a job in ``<layer>.jobs`` where it loads, computes, records in MLflow and saves). Every
handler receives the parsed namespace and returns an exit code. Errors the user can fix
(``ValueError`` and its kin: bad config, bad arguments, diverged runs) print one clear
message and exit with status 2, without a traceback.
"""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from collections.abc import Sequence

from dozerlab import __version__
from dozerlab.cliargs import add_command
from dozerlab.runtime import DozerlabError, die_with_workflow, freeze_heap
from dozerlab.tracking import STATUSES

# The layers' command modules; each defines ``register(subparsers)`` and adds its own commands.
COMMAND_MODULES = (
    "dozerlab.report.cli",
    "dozerlab.scenarios.cli",
    "dozerlab.fields.cli",
    "dozerlab.learn.cli",
    "dozerlab.learn.dynamics.cli",
    "dozerlab.reduce.cli",
    "dozerlab.adaptive.cli",
    "dozerlab.verify",
)


def register(sub: argparse._SubParsersAction) -> None:
    """The commands of no layer: ``config``, ``mlflow-start``, ``mlflow-end``, ``mlflow-ingest``."""
    p = add_command(
        sub,
        "config",
        "validate a config file and print it complete",
        "python -m dozerlab config config/quick.yaml",
    )
    p.add_argument(
        "config", nargs="?", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.set_defaults(func=_config)

    # Internal (the Snakefile's hooks call them): no help= keeps them out of `dozerlab --help`.
    p = add_command(
        sub,
        "mlflow-start",
        "start the parent MLflow run of a workflow; print its id",
        "python -m dozerlab mlflow-start --config config/quick.yaml --name workflow",
        listed=False,
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
    p.set_defaults(func=_mlflow_start)

    p = add_command(
        sub,
        "mlflow-end",
        "end a parent MLflow run, logging the artifacts it produced",
        "python -m dozerlab mlflow-end RUN_ID --status FINISHED --artifact results/report/index.html",
        listed=False,
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
    p.add_argument(
        "--metric",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="a headline figure of the sweep to log on the run (repeatable)",
    )
    p.set_defaults(func=_mlflow_end)

    p = add_command(
        sub,
        "mlflow-ingest",
        "log a workflow's spooled job runs (DOZERLAB_MLFLOW_SPOOL) to MLflow",
        "python -m dozerlab mlflow-ingest RUN_ID --follow",
        listed=False,
    )
    p.add_argument("run_id", help="the workflow's parent run id")
    p.add_argument(
        "--follow", action="store_true", help="go on logging them as jobs end, until SIGTERM"
    )
    p.set_defaults(func=_mlflow_ingest)


def _config(args: argparse.Namespace) -> int:
    import yaml

    from dozerlab.config import load_config

    print(yaml.safe_dump(load_config(args.config), sort_keys=False), end="")
    return 0


def _pairs(items: Sequence[str], flag: str) -> dict[str, str]:
    """``KEY=VALUE`` arguments of ``flag`` as a dict; a ValueError naming the flag if not."""
    out = {}
    for item in items:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ValueError(f"{flag} must be KEY=VALUE, got '{item}'")
        out[key] = value
    return out


def _mlflow_start(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.tracking import start_parent_run

    cfg = load_config(args.config)
    tags = _pairs(args.tag, "--tag")
    experiment = args.experiment or cfg["mlflow"]["experiment"]
    print(start_parent_run(experiment, args.name, config=cfg, tags=tags))
    return 0


def _mlflow_end(args: argparse.Namespace) -> int:
    from dozerlab.tracking import end_parent_run

    metrics = {}
    for key, value in _pairs(args.metric, "--metric").items():
        try:
            metrics[key] = float(value)
        except ValueError:
            raise ValueError(f"--metric {key} must be a number, got '{value}'") from None
    end_parent_run(args.run_id, args.status, args.artifact, metrics)
    return 0


def _mlflow_ingest(args: argparse.Namespace) -> int:
    from dozerlab import spool

    # before MLflow is imported: a SIGTERM while it loads, too, asks the follower to stop
    stop = spool.stop_on_signals() if args.follow else None
    from dozerlab.tracking import follow_parent, ingest_finished

    count = follow_parent(args.run_id, stop) if stop is not None else ingest_finished(args.run_id)
    print(f"logged {count} job runs of workflow run {args.run_id}", file=sys.stderr)
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dozerlab", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dozerlab {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    register(sub)
    for name in COMMAND_MODULES:
        importlib.import_module(name).register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(levelname)s %(name)s: %(message)s",
        stream=sys.stderr,
    )
    die_with_workflow()  # a workflow job stops when its snakemake is killed
    try:
        return int(args.func(args) or 0)
    except (ValueError, FileNotFoundError, DozerlabError) as exc:
        print(f"dozerlab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"dozerlab {args.command}: interrupted", file=sys.stderr)
        return 130


def run() -> int:
    """The entry of ``python -m dozerlab`` and of the ``dozerlab`` script: :func:`main`, then
    the heap frozen (:func:`dozerlab.runtime.freeze_heap`), its outputs closed by then, so that
    the process exits without walking every object once more (0.4 s with torch loaded)."""
    code = main()
    freeze_heap()
    return code
