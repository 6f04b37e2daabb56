"""The report's sections, one module each; :mod:`dozerlab.report.build` composes them.

A section module defines

- ``TITLE``: its heading (str);
- ``ORDER``: its place on the page, smaller first (int; 20 sweep, 30 beds, 40 runs,
  50 models: leave gaps for new sections);
- ``render(ctx: Context) -> str | None``: its HTML fragment, built with the helpers of
  :mod:`dozerlab.report.html` (embedded images, tables with units, notes), or None when the
  results hold nothing for it yet, so the report leaves the section out.

To add a section, add a module to this package: the build finds it, no list to edit.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from dozerlab.sweep import SweepPoint


@dataclass(frozen=True)
class Context:
    """What every section reads: the validated config, the results directory (``results/``)
    and the config's sweep points (training grid first, then the held-out points)."""

    cfg: Mapping[str, Any]
    results: Path
    points: tuple[SweepPoint, ...]


def modules() -> list[ModuleType]:
    """The section modules of this package, in page order."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        for attr in ("TITLE", "ORDER", "render"):
            if not hasattr(module, attr):
                raise TypeError(f"report section {module.__name__} defines no {attr}")
        found.append(module)
    return sorted(found, key=lambda m: (m.ORDER, m.__name__))
