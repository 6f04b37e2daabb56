"""``dozerlab report`` — the platform's HTML report of a finished (or partial) sweep."""

from __future__ import annotations

import argparse

from dozerlab.cliargs import add_command


def register(sub: argparse._SubParsersAction) -> None:
    p = add_command(
        sub,
        "report",
        "write the HTML report of the sweep's results",
        "python -m dozerlab report --config config/quick.yaml --results results \\\n"
        "      --out results/report/index.html",
    )
    p.add_argument(
        "--config",
        default=None,
        help="YAML file or inline JSON (the sweep and learn sections are read)",
    )
    p.add_argument("--results", default="results", help="the results directory (default: results)")
    p.add_argument("--out", default="results/report/index.html", help="the HTML file to write")
    p.add_argument(
        "--processes",
        type=int,
        default=1,
        choices=range(1, 257),
        metavar="N",
        help="processes drawing the per-point figures, 1–256 (default 1; the workflow passes "
        "threads.report)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from dozerlab.config import load_config
    from dozerlab.report.build import build_report

    build_report(load_config(args.config), args.results, args.out, args.processes)
    return 0
