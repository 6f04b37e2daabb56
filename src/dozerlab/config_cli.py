"""``dozerlab config`` — validate a configuration and print it with defaults filled in."""

from __future__ import annotations

import argparse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("config", help="validate a config file and print it complete")
    p.add_argument(
        "config", nargs="?", default=None, help="YAML file or inline JSON (default: all defaults)"
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    import yaml

    from dozerlab.config import load_config

    print(yaml.safe_dump(load_config(args.config), sort_keys=False), end="")
    return 0
