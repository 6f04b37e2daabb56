"""``python -m dozerlab`` runs the command-line interface."""

from dozerlab.cli import run

raise SystemExit(run())
