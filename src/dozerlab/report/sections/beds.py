"""The settled beds: every particle drawn to scale, the surface height seen from above and
the settle log, drawn from the bed files by :func:`dozerlab.scenarios.plots.bed_figure`."""

from __future__ import annotations

from dozerlab.report import html
from dozerlab.report.sections import Context
from dozerlab.sweep import bed_path

TITLE = "Beds"
ORDER = 30


def verdict(ctx: Context) -> str | None:
    """How many beds were settled, of how many particles."""
    from dozerlab.scenarios.bed import Bed

    counts = {}
    for scenario in dict.fromkeys(p.scenario for p in ctx.points):
        path = bed_path(ctx.results, scenario)
        if path.is_file():
            counts[scenario] = Bed.load(path).count
    if not counts:
        return None
    beds = ", ".join(f"{s} ({n} particles)" for s, n in counts.items())
    return f"{len(counts)} settled bed{'s' if len(counts) != 1 else ''}, one per scenario: {beds}."


def render(ctx: Context) -> str | None:
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.plots import bed_figure

    figures = []
    for scenario in dict.fromkeys(p.scenario for p in ctx.points):
        path = bed_path(ctx.results, scenario)
        if not path.is_file():
            continue
        bed = Bed.load(path)
        with html.figure_style():
            fig = bed_figure(bed)
        figures.append(
            html.figure(
                fig,
                f"The settled {scenario} bed, which every run of the scenario starts from: "
                f"{bed.count} particles in a {bed.length:g} m × {bed.width:g} m box.",
            )
        )
    return "\n".join(figures) or None
