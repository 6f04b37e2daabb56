"""The sweep: a map of blade speed × cut depth with each point's mean blade force and role,
and the table of every point's numbers."""

from __future__ import annotations

from typing import Any

import numpy as np

from dozerlab.report import html
from dozerlab.report.collect import PointSummary, summarize
from dozerlab.report.sections import Context
from dozerlab.sweep import fmt_number

TITLE = "Sweep"
ORDER = 20
QUESTION = "What the sweep covered"

#: Marker of each role on the sweep map, its edge colour and width (pt), and the markers' area
#: (pt²).
MARKERS = {"train": "o", "interpolation": "D", "extrapolation": "s", "transfer": "^"}
EDGES = {
    "train": ("k", 0.8),
    "interpolation": ("crimson", 2.2),
    "extrapolation": ("crimson", 2.2),
    "transfer": ("crimson", 2.2),
}
MARKER_AREA = 170
LABELS = {
    "train": "training",
    "interpolation": "held out, interpolation",
    "extrapolation": "held out, extrapolation",
    "transfer": "held out, unseen terrain",
}


def _kn(newton: float | None) -> float | None:
    """A force in kN, the report's unit of force, from N."""
    return None if newton is None else newton / 1000.0


COLUMNS = [
    html.Column("scenario", text=True),
    html.Column("role", text=True),
    html.Column("speed", "m/s"),
    html.Column("depth", "m"),
    html.Column("particles"),
    html.Column("solver steps"),
    html.Column("simulated", "s", lambda v: "–" if v is None else f"{v:.2f}"),
    html.Column("stepping wall time", "s", lambda v: "–" if v is None else f"{v:.1f}"),
    html.Column("wall ÷ simulated time", "", lambda v: "–" if v is None else f"{v:.0f} ×"),
    html.Column("mean |F|", "kN", lambda v: "–" if v is None else f"{v:.2f}"),
    html.Column("peak |F|", "kN", lambda v: "–" if v is None else f"{v:.2f}"),
    html.Column("peak at", "s", lambda v: "–" if v is None else f"{v:.2f}"),
]


def _row(s: PointSummary) -> list[Any]:
    p = s.point
    return [
        p.scenario,
        LABELS[p.role],
        fmt_number(p.speed),
        fmt_number(p.depth),
        s.particles,
        s.steps,
        s.simulated,
        s.wall_time,
        s.slowdown,
        _kn(s.mean_force),
        _kn(s.peak_force),
        s.peak_time,
    ]


def verdict(ctx: Context) -> str | None:
    """The runs simulated out of the sweep's, their range of mean |F| (kN) and stepping time."""
    summaries = [summarize(ctx.results, p) for p in ctx.points]
    built = [s for s in summaries if s.built]
    if not built:
        return None
    held = sum(s.point.role != "train" for s in built)
    speeds = [p.speed for p in ctx.points]
    depths = [p.depth for p in ctx.points]
    text = (
        f"{len(built)} of {len(summaries)} NDEM runs simulated "
        f"({len(built) - held} training, {held} held out) on "
        f"{', '.join(dict.fromkeys(p.scenario for p in ctx.points))}, blade speeds "
        f"{_span(min(speeds), max(speeds), fmt_number)} m/s, cut depths "
        f"{_span(min(depths), max(depths), fmt_number)} m"
    )
    forced = [s for s in built if s.mean_force is not None]
    if forced:
        lo = min(forced, key=lambda s: s.mean_force or 0.0)
        hi = max(forced, key=lambda s: s.mean_force or 0.0)
        text += f"; mean |F| {_kn(lo.mean_force):.2f} kN ({_where(lo)})"
        if hi.mean_force != lo.mean_force:
            text += f" to {_kn(hi.mean_force):.2f} kN ({_where(hi)})"
    timed = [s.wall_time for s in built if s.wall_time is not None]
    if timed:
        text += f"; stepping took {_span(min(timed), max(timed), lambda v: f'{v:.0f}')} s a run"
    return text + "."


def _span(lo: float, hi: float, number: Any) -> str:
    """``lo–hi`` as ``number`` writes them, one number when they read the same."""
    a, b = number(lo), number(hi)
    return a if a == b else f"{a}–{b}"


def _where(s: PointSummary) -> str:
    return f"{s.point.scenario} {fmt_number(s.point.speed)} m/s, {fmt_number(s.point.depth)} m"


def render(ctx: Context) -> str | None:
    summaries = [summarize(ctx.results, p) for p in ctx.points]
    if not any(s.built for s in summaries):
        return None
    parts = [
        html.figure(
            sweep_map(summaries),
            "Mean blade force magnitude |F| over each run, by blade speed and cut depth; the "
            "held-out points (diamonds, squares, triangles on unseen terrain, red edges) are never "
            "seen in training. Hollow "
            "grey: not simulated yet.",
        ),
        html.table(COLUMNS, [_row(s) for s in summaries]),
        html.paragraph(
            "Stepping wall time: the simulation's stepping loop (solver, field sampling, store "
            "writes) on one job's threads, without loading the bed or Snakemake's overhead; – for "
            "stores written before it was recorded. Forces are the particles' contact forces on "
            "the blade; peak at: when in the run |F| was largest (in a run's last steps it can "
            "be the pile pressed against the bed's far wall; Runs counts such runs).",
            "caption",
        ),
    ]
    return "\n".join(parts)


def sweep_map(summaries: list[PointSummary]) -> Any:
    """A figure per scenario of the points on the speed (m/s) × depth (m) plane, coloured by
    mean |F| (kN, one colour scale), marked by role and labelled with their force."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D

    scenarios = list(dict.fromkeys(s.point.scenario for s in summaries))
    # a scenario of transfer points only: terrain no model trained on
    unseen = {
        c
        for c in scenarios
        if all(s.point.role == "transfer" for s in summaries if s.point.scenario == c)
    }
    forces = [s.mean_force / 1000 for s in summaries if s.mean_force is not None]
    norm = Normalize(min(forces), max(forces) if max(forces) > min(forces) else min(forces) + 1)
    speeds = [s.point.speed for s in summaries]
    depths = [s.point.depth for s in summaries]
    pad_v = 0.12 * (max(speeds) - min(speeds) or 1.0)
    pad_d = 0.12 * (max(depths) - min(depths) or 0.1)
    with html.figure_style():
        fig = Figure(figsize=(5.2 * len(scenarios) + 1.6, 4.6), layout="constrained")
        axes = np.atleast_1d(fig.subplots(1, len(scenarios), sharey=True, squeeze=False)[0])
        for ax, scenario in zip(axes, scenarios, strict=True):
            for s in summaries:
                p = s.point
                if p.scenario != scenario:
                    continue
                style: dict[str, Any] = {"marker": MARKERS[p.role], "s": MARKER_AREA, "zorder": 3}
                if s.mean_force is None:
                    ax.scatter(p.speed, p.depth, facecolors="none", edgecolors="0.6", **style)
                    continue
                ax.scatter(
                    p.speed,
                    p.depth,
                    c=[s.mean_force / 1000],
                    cmap="viridis",
                    norm=norm,
                    edgecolors=EDGES[p.role][0],
                    linewidths=EDGES[p.role][1],
                    **style,
                )
                ax.annotate(
                    f"{s.mean_force / 1000:.2f} kN",
                    (p.speed, p.depth),
                    xytext=(0, 12),
                    textcoords="offset points",
                    ha="center",
                    fontsize=10,
                )
            ax.set(
                xlim=(min(speeds) - pad_v, max(speeds) + pad_v),
                ylim=(min(depths) - pad_d, max(depths) + 1.6 * pad_d),
                xlabel="blade speed (m/s)",
                title=scenario + (" (unseen terrain)" if scenario in unseen else ""),
            )
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("cut depth (m)")
        fig.colorbar(
            ScalarMappable(norm=norm, cmap="viridis"), ax=list(axes), label="mean |F| (kN)"
        )
        # the legend's markers drawn as the points are: filled from the colour scale (its
        # middle), edged by role, at the points' size (scatter's s is the area in pt²)
        size, fill = float(np.sqrt(MARKER_AREA)), colormaps["viridis"](0.5)
        handles = [
            Line2D(
                [], [], marker=MARKERS[r], ls="", ms=size, mfc=fill, mec=c, mew=w, label=LABELS[r]
            )
            for r, (c, w) in EDGES.items()
        ]
        if any(s.mean_force is None for s in summaries):
            handles.append(
                Line2D(
                    [],
                    [],
                    marker="o",
                    ls="",
                    ms=size,
                    mfc="none",
                    mec="0.6",
                    label="not simulated yet",
                )
            )
        # as many columns as the figure's width holds (a role's label and marker take about
        # 2.6 in): three on one scenario's panel ran past both edges, "unseen terrain" cut off
        width = float(fig.get_figwidth())
        columns = max(1, min(len(handles), 3, int(width // 2.6)))
        fig.legend(handles=handles, loc="outside lower center", ncols=columns, frameon=False)
    return fig
