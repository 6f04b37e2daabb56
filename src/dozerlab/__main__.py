"""``python -m dozerlab`` runs the command-line interface."""

from dozerlab.cli import main

raise SystemExit(main())
