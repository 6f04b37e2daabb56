"""Figures of an adaptive sweep: the learning curve and each round's points on the sweep map."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.adaptive.curve import mean_by_size
from dozerlab.adaptive.design import Scored
from dozerlab.sweep import by_role, sweep_points

_STYLE = {"adaptive": ("C0", "o-"), "grid": ("k", "s"), "random": ("C1", "^--")}


def _save(fig: Any, path: Path) -> Path:
    from dozerlab.runtime import png_metadata

    fig.savefig(path, dpi=110, format="png", metadata=png_metadata())
    return path


def learning_curve(rows: Sequence[Mapping[str, Any]], path: Path) -> Path:
    """Write :func:`learning_curve_figure` as a PNG at ``path``."""
    return _save(learning_curve_figure(rows), path)


def learning_curve_figure(rows: Sequence[Mapping[str, Any]]) -> Any:
    """Held-out pushing-force error (%) against NDEM training runs: the adaptive design, the
    grid, the random designs' mean (and each seed, faint); with the reduced simulation's figures
    in the rows, a second panel: its low-passed pushing-force error on the held-out points'
    replay loops, and the twins' (NDEM's own reproducibility) as a line."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import MaxNLocator

    loop = any(np.isfinite(r["reduced_force_lp_rel_rmse"]) for r in rows)
    panels = [("heldout_force_rel_rmse", "force model", "held-out force_x rel. RMSE (%)")]
    if loop:
        panels.append(
            (
                "reduced_force_lp_rel_rmse",
                "reduced simulation (replay loop)",
                "low-passed force_x rel. RMSE (%)",
            )
        )
    fig = Figure(figsize=(5.5 * len(panels), 3.8))
    axes = np.atleast_1d(fig.subplots(1, len(panels)))
    for ax, (column, title, label) in zip(axes, panels, strict=True):
        for r in rows:
            if r["design"] == "random":
                ax.plot(r["runs"], 100 * r[column], ".", color="C1", alpha=0.35)
        for name, (color, style) in _STYLE.items():
            curve = mean_by_size(rows, name, column)
            if curve:
                text = "random (mean of seeds)" if name == "random" else name
                ax.plot(
                    list(curve), [100 * e for e in curve.values()], style, color=color, label=text
                )
        if column == "reduced_force_lp_rel_rmse":
            twin = [r["twin_force_lp_rel_rmse"] for r in rows]
            if np.isfinite(twin).any():
                ax.axhline(100 * float(np.nanmean(twin)), color="0.5", ls=":", label="twin NDEM")
        ax.set_title(title)
        ax.set_xlabel("NDEM training runs")
        ax.set_ylabel(label)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.grid(alpha=0.3)
        ax.legend()
    fig.tight_layout()
    return fig


def rounds_map(config: Mapping[str, Any], rounds: Sequence[Sequence[Scored]], path: Path) -> Path:
    """Write :func:`rounds_map_figure` as a PNG at ``path``."""
    return _save(rounds_map_figure(config, rounds), path)


def rounds_map_figure(config: Mapping[str, Any], rounds: Sequence[Sequence[Scored]]) -> Any:
    """The sweep map of each scenario (speed × depth): the grid (faint), the held-out points, and
    each round's points labelled with their round."""
    from matplotlib.figure import Figure

    scenarios = list(config["sweep"]["scenarios"])
    fig = Figure(figsize=(4.2 * len(scenarios) + 1.2, 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(scenarios)))
    points = sweep_points(config)
    for ax, s in zip(axes, scenarios, strict=True):
        grid = [p for p in by_role(points, "train") if p.scenario == s]
        ax.plot([p.speed for p in grid], [p.depth for p in grid], "+", color="0.7", label="grid")
        for role, marker in (("interpolation", "x"), ("extrapolation", "X")):
            held = [p for p in by_role(points, role) if p.scenario == s]
            if held:
                ax.plot(
                    [p.speed for p in held], [p.depth for p in held], marker, color="C3", label=role
                )
        for r, rows in enumerate(rounds):
            mine = [x.point for x in rows if x.point.scenario == s]
            if mine:
                ax.plot(
                    [p.speed for p in mine],
                    [p.depth for p in mine],
                    "o",
                    color=f"C{r % 10}",
                    alpha=0.8,
                    label=f"round {r}",
                )
                for p in mine:
                    ax.annotate(
                        str(r),
                        (p.speed, p.depth),
                        textcoords="offset points",
                        xytext=(5, 4),
                        fontsize=8,
                    )
        ax.set_title(s)
        ax.set_xlabel("speed (m/s)")
        ax.set_ylabel("depth (m)")
        ax.grid(alpha=0.3)
        ax.margins(0.12)  # points on the box's edges keep their round labels
    # One legend for every panel: a round may pick points on one scenario only.
    labelled: dict[str, Any] = {}
    for ax in axes:
        for handle, label in zip(*ax.get_legend_handles_labels(), strict=True):
            labelled.setdefault(label, handle)
    names = [k for k in labelled if not k.startswith("round ")]
    names += [f"round {r}" for r in range(len(rounds)) if f"round {r}" in labelled]
    fig.legend(
        [labelled[k] for k in names],
        names,
        fontsize=8,
        loc="outside right center",
    )
    return fig
