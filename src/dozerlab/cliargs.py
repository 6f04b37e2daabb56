"""Command-line arguments the layers' commands share, and the start every handler makes.

Each layer's ``cli`` module builds its parsers from these, so an option that several commands
take is spelled and explained once. Like the ``cli`` modules, this module imports only argparse
at its top level (``dozerlab --help`` stays instant); :func:`configure` imports the config and
runtime modules when a handler runs.
"""

from __future__ import annotations

import argparse
import importlib
from collections.abc import Callable
from typing import Any

CONFIG_HELP = "YAML file or inline JSON (default: all defaults)"


def add_command(
    sub: argparse._SubParsersAction,
    name: str,
    summary: str,
    example: str,
    *,
    listed: bool = True,
) -> argparse.ArgumentParser:
    """A command's parser: ``summary`` (one line, what it does) opens its ``--help`` and, when
    ``listed``, is its line in ``dozerlab --help``; ``example`` (a command line on the default
    results layout, lines joined by ``\\``) closes its ``--help`` as written."""
    layout: dict[str, Any] = {
        "description": summary,
        "epilog": f"example:\n  {example}",
        "formatter_class": argparse.RawDescriptionHelpFormatter,
    }
    if listed:  # without help=, the command is left out of `dozerlab --help`
        layout["help"] = summary
    return sub.add_parser(name, **layout)


def add_config(p: argparse.ArgumentParser, help: str = CONFIG_HELP) -> None:
    """``--config SOURCE``: the config (a YAML file or inline JSON; none: all defaults)."""
    p.add_argument("--config", default=None, help=help)


def schema_value(
    field: tuple[str | int, ...], kind: type[float] | type[int] = float
) -> Callable[[str], Any]:
    """An argparse ``type``: the flag's text as a ``kind`` within the bounds of the config
    field ``field`` (keys and list positions), so that a flag takes what the config takes and
    the schema stays the one source of ranges. The schema is read when the flag is given."""

    def parse(text: str) -> Any:
        from dozerlab.config import ConfigError, check_value

        try:
            value = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(
                f"'{text}' is not {'an integer' if kind is int else 'a number'}"
            ) from None
        try:
            check_value(field, value)
        except ConfigError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
        return value

    parse.__name__ = kind.__name__  # argparse names the type in its messages
    return parse


def add_threads(
    p: argparse.ArgumentParser, default: int | None = 1, help: str = "numba threads (default 1)"
) -> None:
    """``--threads N``: the job's thread budget (``None``: the config's ``threads`` entry),
    within the bounds of the config's ``threads`` fields."""
    p.add_argument(
        "--threads", type=schema_value(("threads", "train"), int), default=default, help=help
    )


def add_run_inputs(p: argparse.ArgumentParser) -> None:
    """``--bed`` and ``--trajectory``: what a run of a sweep point starts from."""
    p.add_argument("--bed", required=True, help="settled bed (.npz from `dozerlab bed`)")
    p.add_argument(
        "--trajectory", required=True, help="blade trajectory (.csv from `dozerlab trajectory`)"
    )


def add_point(p: argparse.ArgumentParser, speed: str, depth: str, required: bool = False) -> None:
    """``--speed`` (m/s) and ``--depth`` (m), a sweep point's numbers, explained by ``speed`` and
    ``depth``, within the bounds of the config's ``sweep.speeds`` and ``sweep.depths``."""
    for name, what in (("speed", speed), ("depth", depth)):
        field = ("sweep", f"{name}s", 0)
        p.add_argument(
            f"--{name}",
            type=schema_value(field),
            required=required,
            default=None,
            help=what,
        )


def add_labels(p: argparse.ArgumentParser) -> None:
    """``--scenario``, ``--speed``, ``--depth``: the labels of a run's store (passed by the
    workflow, never parsed from file names); :func:`labels` reads them."""
    p.add_argument("--scenario", default=None, help="label (default: the bed's scenario)")
    add_point(
        p,
        "label in m/s (default: from the trajectory)",
        "label in m (default: none; the workflow passes its sweep point's)",
    )


def labels(args: argparse.Namespace) -> dict[str, Any]:
    """The ``scenario``, ``speed`` and ``depth`` keywords of a job, from :func:`add_labels`."""
    return {"scenario": args.scenario, "speed": args.speed, "depth": args.depth}


def configure(args: argparse.Namespace, threads_key: str | None = None) -> dict[str, Any]:
    """A handler's start: the validated config of ``--config``, and the thread count set from
    ``--threads`` (or, when that is not given, the config's ``threads.<threads_key>``) before any
    numba or torch work."""
    from dozerlab.config import load_config
    from dozerlab.runtime import set_threads

    config = load_config(args.config)
    given = args.threads is not None
    set_threads(args.threads if given or not threads_key else config["threads"][threads_key])
    return config


def job(name: str) -> Callable[..., Any]:
    """The job function ``module:function``, imported when a handler runs (not for --help)."""
    module, _, function = name.partition(":")
    return getattr(importlib.import_module(module), function)
