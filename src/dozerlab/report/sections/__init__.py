"""The report's sections, one module each; :mod:`dozerlab.report.build` composes them.

A section module defines

- ``TITLE``: its heading (str);
- ``ORDER``: its place on the page, smaller first (int; 20 sweep, 30 beds, 40 runs,
  50 models: leave gaps for new sections);
- ``render(ctx: Context) -> str | None``: its HTML fragment, built with the helpers of
  :mod:`dozerlab.report.html` (embedded images, tables with units, notes), or None when the
  results hold nothing for it yet, so the report leaves the section out;
- ``verdict(ctx: Context) -> str | None``: the one sentence, with its numbers, that answers the
  section's question; the build puts it at the top of the section;
- optionally ``QUESTION``: the question the section answers as the page's summary lists it
  (str); a section with one has its verdict in the summary at the top of the page.

To add a section, add a module to this package: the build finds it, no list to edit.
"""

from __future__ import annotations

import importlib
import json
import pkgutil
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

from dozerlab.report import html
from dozerlab.sweep import HELD_OUT_ROLES, SweepPoint

#: The held-out groups of a validation document, in the order the report shows them.
GROUPS = HELD_OUT_ROLES
#: What the report calls each group (``transfer``: the points on terrain of no training point).
GROUP_LABELS = {
    "interpolation": "interpolation",
    "extrapolation": "extrapolation",
    "transfer": "unseen terrain",
}


@dataclass(frozen=True)
class Comparison:
    """What a model-comparison section shows above its per-model blocks: a lead paragraph, a
    chart (an HTML figure), a table and the table's caption (plain text)."""

    lead: str
    chart: str
    columns: Sequence[html.Column]
    rows: list[list[Any]]
    caption: str


@dataclass(frozen=True)
class Context:
    """What every section reads: the validated config, the results directory (``results/``),
    the config's sweep points (training grid first, then the held-out points) and the folder
    the page is written to (its animations go beside it)."""

    cfg: Mapping[str, Any]
    results: Path
    points: tuple[SweepPoint, ...]
    page_dir: Path
    #: Processes that draw the per-point figures (the report is the sweep's last job).
    processes: int = 1


def modules() -> list[ModuleType]:
    """The section modules of this package, in page order."""
    found = []
    for info in pkgutil.iter_modules(__path__):
        module = importlib.import_module(f"{__name__}.{info.name}")
        for attr in ("TITLE", "ORDER", "render", "verdict"):
            if not hasattr(module, attr):
                raise TypeError(f"report section {module.__name__} defines no {attr}")
        found.append(module)
    return sorted(found, key=lambda m: (m.ORDER, m.__name__))


def documents(
    ctx: Context, models: Iterable[str], path_of: Callable[[Path, str], Path]
) -> dict[str, tuple[Path, dict[str, Any]]]:
    """The JSON document of each model the results hold one of (``path_of(results, model)``),
    with its path, in the order of ``models``."""
    found = {}
    for model in models:
        path = path_of(ctx.results, model)
        if path.is_file():
            found[model] = (path, json.loads(path.read_text(encoding="utf-8")))
    return found


def model_comparison(
    ctx: Context,
    models: Iterable[str],
    path_of: Callable[[Path, str], Path],
    compare: Callable[[dict[str, dict[str, Any]]], Comparison],
    detail: Callable[[Context, str, Path, dict[str, Any]], str],
    anchor: str,
) -> str | None:
    """A section comparing models by the JSON documents the results hold of them
    (``path_of(results, model)``; None when there is none yet): ``compare(documents)``'s lead
    paragraph, chart (an HTML figure), table and caption, then per model a collapsed block of
    ``detail(ctx, model, path, document)`` with the id ``{anchor}-{model}``."""
    found = documents(ctx, models, path_of)
    if not found:
        return None
    c = compare({m: doc for m, (_, doc) in found.items()})
    parts = [
        html.paragraph(c.lead),
        c.chart,
        html.table(c.columns, c.rows),
        html.paragraph(c.caption, "caption"),
    ]
    parts += [
        html.details(f"{m}: per-point errors and plots", detail(ctx, m, path, doc), f"{anchor}-{m}")
        for m, (path, doc) in found.items()
    ]
    return "\n".join(parts)


def group_rows(
    docs: dict[str, dict[str, Any]], cells: Callable[[str, str, dict[str, Any]], list[Any]]
) -> list[list[Any]]:
    """A table row per model and held-out group it was validated on: the model, the group, then
    ``cells(model, group, overall)`` of the group's overall figures."""
    return [
        [m, GROUP_LABELS[g], *cells(m, g, doc["groups"][g]["overall"])]
        for m, doc in docs.items()
        for g in GROUPS
        if g in doc["groups"]
    ]


def result_file(results: Path, folder: Path, name: Any, document: Path) -> Path | None:
    """The file a result JSON (``document``) names, ``name`` relative to ``folder``, or None
    with a warning on stderr when it is not a file inside ``results``: the report reads only
    what the sweep wrote, never where a damaged or hand-edited document points."""
    if isinstance(name, str) and name:
        file = (folder / name).resolve()
        if not file.is_relative_to(results.resolve()):
            why = "is outside the results folder"
        elif not file.is_file():
            why = "is not a file"
        else:
            return file
    else:
        why = "is not a file name"
    print(f"dozerlab report: {document} names {name!r}, which {why}: skipped", file=sys.stderr)
    return None


def result_figures(
    results: Path, folder: Path, images: Iterable[tuple[Any, str]], document: Path
) -> str:
    """The embedded figures of ``(name, caption)`` pairs a result JSON (``document``) lists,
    each name relative to ``folder`` (None: the document has no such figure); a name that is not
    a file inside ``results`` is skipped (:func:`result_file`)."""
    files = (
        (result_file(results, folder, name, document), caption)
        for name, caption in images
        if name is not None
    )
    return "".join(html.figure(file, caption) for file, caption in files if file)
