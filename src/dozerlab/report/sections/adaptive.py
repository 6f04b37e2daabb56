"""An adaptive sweep (sweep.adaptive): each round's points on the sweep map, why each was
picked, and the learning curve against the grid and random designs of the same sizes."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from dozerlab import sweep as P
from dozerlab.report import html
from dozerlab.report.sections import Context

TITLE = "Adaptive sweep"
ORDER = 25
QUESTION = "Does the adaptive design reach the grid's accuracy with fewer NDEM runs?"


def _round_files(ctx: Context) -> list[Path]:
    """The rounds' points.csv the results hold, rounds 0, 1, … up to the first missing one."""
    files: list[Path] = []
    while (path := P.adaptive_path("adaptive_points", ctx.results, len(files))).is_file():
        files.append(path)
    return files


def _curve(ctx: Context) -> list[dict[str, Any]] | None:
    from dozerlab.adaptive.curve import read_curve

    path = ctx.results / P.PATHS["learning_curve"]
    return read_curve(path) if path.is_file() else None


def verdict(ctx: Context) -> str | None:
    """The adaptive design's last held-out error against the grid's and random designs' of its size."""
    from dozerlab.adaptive.curve import mean_by_size

    rows = _curve(ctx)
    if not rows:
        return None
    adaptive = mean_by_size(rows, "adaptive")
    n, err = list(adaptive.items())[-1]
    text = f"With {n} NDEM training runs the adaptive design's held-out force_x error is {100 * err:.1f} %"
    grid = mean_by_size(rows, "grid")
    rnd = mean_by_size(rows, "random").get(n)
    if grid:
        g_n, g_err = list(grid.items())[-1]
        reached = err <= 1.05 * g_err
        text += f"; the grid's {g_n} runs reach {100 * g_err:.1f} % ({'reached' if reached else 'not reached'} within 5 %)"
    if rnd is not None and not math.isnan(rnd):
        text += f"; random designs of {n} runs {100 * rnd:.1f} % on average"
    loop = mean_by_size(rows, "adaptive", "reduced_force_lp_rel_rmse").get(n, math.nan)
    if not math.isnan(loop):
        twin = mean_by_size(rows, "adaptive", "twin_force_lp_rel_rmse").get(n, math.nan)
        text += f". In the replay loop the reduced simulation's low-passed force_x error is {100 * loop:.1f} %"
        g_loop = list(mean_by_size(rows, "grid", "reduced_force_lp_rel_rmse").values())
        if g_loop:
            text += f" (the grid's {100 * g_loop[-1]:.1f} %"
            text += f", the twins' {100 * twin:.1f} %)" if not math.isnan(twin) else ")"
    return text + "."


def _curve_table(rows: list[dict[str, Any]]) -> str:
    """Each design's means per number of runs: the force model's held-out error, the reduced
    simulation's and its skill."""
    from dozerlab.adaptive.curve import mean_by_size

    columns = [
        html.Column("design", text=True),
        html.Column("NDEM training runs"),
        html.Column("held-out force_x rel. RMSE", "%"),
        html.Column("reduced: low-passed force_x rel. RMSE", "%"),
        html.Column(
            "reduced: skill (over the twin)",
            format=lambda v: html.fmt(v) if v is None or not math.isfinite(v) else f"{v:.2f}",
        ),
    ]
    table = []
    for name in ("adaptive", "grid", "random"):
        force = mean_by_size(rows, name)
        loop = mean_by_size(rows, name, "reduced_force_lp_rel_rmse")
        skill = mean_by_size(rows, name, "reduced_force_lp_rel_rmse_skill")
        for n, e in force.items():
            table.append([name, n, round(100 * e, 1), round(100 * loop[n], 1), skill[n]])
    return html.table(columns, table)


def render(ctx: Context) -> str | None:
    from dozerlab.adaptive.design import read_points
    from dozerlab.adaptive.plots import learning_curve_figure, rounds_map_figure

    files = _round_files(ctx)
    if not files:
        return None
    rounds = [read_points(f) for f in files]
    parts = []
    with html.figure_style():
        fig = rounds_map_figure(ctx.cfg, rounds)
    parts.append(
        html.figure(
            fig,
            "Each round's NDEM runs on the sweep map (labelled by round), the grid (+) and the held-out points (x).",
        )
    )
    columns = [
        html.Column("round"),
        html.Column("scenario", text=True),
        html.Column("speed", "m/s"),
        html.Column("depth", "m"),
        html.Column("score"),
        html.Column("why", text=True),
    ]
    rows = [
        [r, s.point.scenario, s.point.speed, s.point.depth, s.score, s.why]
        for r, rr in enumerate(rounds)
        for s in rr
    ]
    parts.append(html.table(columns, rows))
    parts.append(
        html.paragraph(
            "score: the ensemble's spread of a run summary over NDEM's run-to-run spread of it (round 0 is the initial design, unscored).",
            "caption",
        )
    )
    curve = _curve(ctx)
    if curve:
        with html.figure_style():
            fig = learning_curve_figure(curve)
        parts.append(
            html.figure(
                fig,
                "Held-out force_x rel. RMSE of the curve's force model against NDEM training runs: the adaptive design after each round, the grid, random designs of the same sizes drawn from the candidates (mean, and each seed). "
                "Where the held-out points' replay runs exist, right: the reduced simulation's pushing force, low-passed over 0.1 s, when the loop's force model (reduced.force_model) is the one fitted to each training set, against NDEM's on the held-out points; the dotted line is the twins' (NDEM's own reproducibility).",
            )
        )
        parts.append(_curve_table(curve))
        parts.append(
            html.paragraph(
                "Means over the random designs' seeds; the reduced simulation's figures are means over the held-out points, as compare-reduced reports them (skill: the error over the twin's, below 1 beats NDEM's reproducibility); empty without the replay runs.",
                "caption",
            )
        )
    else:
        parts.append(html.missing("The learning curve is not built yet."))
    return "\n".join(parts)
