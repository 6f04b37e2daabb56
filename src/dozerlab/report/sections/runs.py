"""Each sweep point's run: its blade trajectory, a field slice and the blade force over time."""

from __future__ import annotations

from concurrent.futures import ProcessPoolExecutor
from itertools import repeat

from dozerlab.report import html
from dozerlab.report.collect import point_figures, summarize
from dozerlab.report.sections import Context
from dozerlab.report.sections.sweep import LABELS
from dozerlab.sweep import fmt_number

TITLE = "Runs"
ORDER = 40
#: The end of a run, as a fraction of its time, where its largest force should not be.
LATE = 0.1


def verdict(ctx: Context) -> str | None:
    """What each run shows, and where and when the largest blade force of the sweep was."""
    peaks = [s for s in (summarize(ctx.results, p) for p in ctx.points) if s.peak_force]
    if not peaks:
        return None
    top = max(peaks, key=lambda s: s.peak_force or 0.0)
    p = top.point
    text = (
        f"{len(peaks)} run{'s' if len(peaks) != 1 else ''}, each with its blade trajectory, a mid-run field slice and the blade "
        f"force over time; the sweep's largest |F|, {(top.peak_force or 0.0) / 1000:.2f} kN, is "
        f"that of {p.scenario} {fmt_number(p.speed)} m/s, {fmt_number(p.depth)} m at "
        f"t = {top.peak_time:.2f} s of {top.simulated:.2f} s"
    )
    # a run whose force peaks at its end pushed its pile against the far wall (quick.yaml)
    late = [s for s in peaks if (s.peak_time or 0.0) > (1 - LATE) * (s.simulated or 0.0)]
    if late:
        text += (
            f"; {len(late)} of {len(peaks)} runs peak in their last {html.percent(LATE, 0)}, where the pile "
            "ahead of the blade may press against the bed's far wall (trajectory.end_margin)"
        )
    return text + "."


def render(ctx: Context) -> str | None:
    blocks, missing = [], []
    if ctx.processes > 1 and len(ctx.points) > 1:
        with ProcessPoolExecutor(min(ctx.processes, len(ctx.points))) as pool:
            drawn = list(pool.map(point_figures, repeat(ctx.results), ctx.points))
    else:
        drawn = [point_figures(ctx.results, p) for p in ctx.points]
    for p, figures in zip(ctx.points, drawn, strict=True):
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
