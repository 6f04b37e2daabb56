"""Each sweep point's run: its blade trajectory, a field slice and the blade force over time."""

from __future__ import annotations

from dozerlab.report import html
from dozerlab.report.collect import point_figures
from dozerlab.report.sections import Context
from dozerlab.report.sections.sweep import LABELS
from dozerlab.sweep import fmt_number

TITLE = "Runs"
ORDER = 40


def render(ctx: Context) -> str | None:
    blocks, missing = [], []
    for p in ctx.points:
        figures = point_figures(ctx.results, p)
        label = (
            f"{p.scenario}: speed {fmt_number(p.speed)} m/s, depth {fmt_number(p.depth)} m "
            f"({LABELS[p.role]})"
        )
        if figures:
            blocks.append(html.details(label, "".join(figures)))
        else:
            missing.append(f"{p.scenario} {p.name}")
    if not blocks:
        return None
    if missing:
        blocks.append(html.missing("Not built yet: " + ", ".join(missing) + "."))
    return "\n".join(blocks)
