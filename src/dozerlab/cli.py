"""Command-line interface: ``python -m dozerlab <command> …`` (or the ``dozerlab`` script).

Each layer registers its commands from its own ``cli`` module, whose top level imports only
argparse so that ``--help`` is instant; heavy imports happen inside the handlers. Every
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
from dozerlab.runtime import DozerlabError, die_with_workflow

# Modules that define ``register(subparsers)``; each adds its own commands.
COMMAND_MODULES = (
    "dozerlab.config_cli",
    "dozerlab.tracking_cli",
    "dozerlab.report.cli",
    "dozerlab.scenarios.cli",
    "dozerlab.fields.cli",
    "dozerlab.learn.cli",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="dozerlab", description=__doc__.splitlines()[0])
    parser.add_argument("--version", action="version", version=f"dozerlab {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
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
