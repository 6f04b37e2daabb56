"""The field-evolution models on the held-out sweep points: one-step and rollout errors against
``persistence``, mass along the rollout, and each model's curves and density slices, read from
the JSON and PNGs that ``dozerlab validate-dynamics`` wrote."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab.report import html
from dozerlab.report.sections import (
    GROUP_LABELS,
    GROUPS,
    Comparison,
    Context,
    documents,
    group_rows,
    model_comparison,
    result_figures,
)
from dozerlab.report.sections.models import _point
from dozerlab.sweep import dynamics_validation_path

TITLE = "Field-evolution models on held-out points"
ORDER = 60
QUESTION = "Best field-evolution model"

#: Issue 15's targets: the best model's one-step and 50-step velocity errors at most this
#: fraction of persistence's, and mass within this fraction of the truth over 100 steps.
RATIO_TARGET, MASS_TARGET = 0.6, 0.05


def _num(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.3f}"


def _pct(value: float | None) -> str:
    return html.percent(value).removesuffix(" %")


COLUMNS = [
    html.Column("velocity, one step", "", _num),
    html.Column("density, one step", "", _num),
    html.Column("velocity, 10 steps", "", _num),
    html.Column("velocity, 50 steps", "", _num),
    html.Column("velocity, 100 steps", "", _num),
    html.Column("density, 50 steps", "", _num),
    html.Column("mass error, max over rollout", "%", _pct),
]


#: The comparison table's columns: model, group, the errors, and the ratios to persistence.
TABLE_COLUMNS = [
    html.Column("model", text=True),
    html.Column("held-out group", text=True),
    *COLUMNS,
    html.Column("one step / persistence", "", _num),
    html.Column("50 steps / persistence", "", _num),
]


def _cells(o: dict[str, Any]) -> list[Any]:
    at = o["rollout_at"]
    return [
        o["one_step"]["velocity"],
        o["one_step"]["density"],
        at["10"]["velocity"],
        at["50"]["velocity"],
        at["100"]["velocity"],
        at["50"]["density"],
        o["mass"]["max_abs_error"],
    ]


def render(ctx: Context) -> str | None:
    models = ctx.cfg["dynamics"]["models"]
    return model_comparison(ctx, models, dynamics_validation_path, _compare, _model, "dynamics")


def verdict(ctx: Context) -> str | None:
    """The learned model whose worse held-out group is closest to the targets: its velocity
    error against persistence's after one and 50 steps, its mass error and the targets."""
    found = documents(ctx, ctx.cfg["dynamics"]["models"], dynamics_validation_path)
    docs = {m: doc for m, (_, doc) in found.items()}
    if "persistence" not in docs:
        return None
    scored: dict[str, tuple[float, float, float]] = {}
    for m, doc in docs.items():
        groups = [g for g in GROUPS if g in doc["groups"] and g in docs["persistence"]["groups"]]
        if m == "persistence" or not groups:
            continue
        ratios = [_ratios(docs, m, g) for g in groups]
        scored[m] = (
            max(float(r[0] or 0.0) for r in ratios),
            max(float(r[1] or 0.0) for r in ratios),
            max(doc["groups"][g]["overall"]["mass"]["max_abs_error"] for g in groups),
        )
    if not scored:
        return None
    best = min(scored, key=lambda m: max(scored[m][:2]))
    one, fifty, mass = scored[best]
    ok = max(one, fifty) <= RATIO_TARGET and mass <= MASS_TARGET
    return (
        f"{best} evolves the fields best, started from NDEM's: its velocity error is {one:.2f}× "
        f"persistence's after one step and {fifty:.2f}× after 50 steps, mass within "
        f"{html.percent(mass)} (the worse held-out group); it {'meets' if ok else 'misses'} "
        f"the targets ≤ {RATIO_TARGET}× and ±{html.percent(MASS_TARGET, 0)}."
    )


def _compare(docs: dict[str, dict[str, Any]]) -> Comparison:
    rows = group_rows(docs, lambda m, g, overall: [*_cells(overall), *_ratios(docs, m, g)])
    chart = html.figure(
        rollout_chart(docs),
        "Velocity error along rollouts started from true fields, "
        "per model and held-out group (lower is better).",
    )
    caption = (
        "Velocity error: sqrt(Σ ρ|v − v_true|²) / sqrt(Σ ρ|v_true|²) in the world frame, "
        "weighted by the true density ρ (empty bins count for nothing); density error: the "
        "relative L2. One step: every window of the held-out runs; rollouts: the model fed "
        "its own output from true fields at a few rows of each run, with the run's blade "
        "velocity; a number of steps past a run's end reads at its end. Mass: Σ ρ V_bin in "
        "the sampling volume, predicted against true."
    )
    return Comparison(_verdict(docs), chart, TABLE_COLUMNS, rows, caption)


def _ratios(docs: dict[str, dict[str, Any]], model: str, group: str) -> list[float | None]:
    base = docs.get("persistence", {}).get("groups", {}).get(group)
    if base is None:
        return [None, None]
    o, b = docs[model]["groups"][group]["overall"], base["overall"]
    return [
        o["one_step"]["velocity"] / b["one_step"]["velocity"],
        o["rollout_at"]["50"]["velocity"] / b["rollout_at"]["50"]["velocity"],
    ]


def _verdict(docs: dict[str, dict[str, Any]]) -> str:
    """Which model meets the targets against persistence, per group."""
    if "persistence" not in docs:
        return "No persistence baseline validated: the targets are relative to it."
    lines = []
    for g in GROUPS:
        scored: dict[str, tuple[float, float]] = {}
        for m in docs:
            if m != "persistence" and g in docs[m]["groups"]:
                one, fifty = _ratios(docs, m, g)
                if one is not None and fifty is not None:
                    scored[m] = (one, fifty)
        if not scored:
            continue
        best = min(scored, key=lambda m: max(scored[m]))
        r = scored[best]
        mass = docs[best]["groups"][g]["overall"]["mass"]["max_abs_error"]
        ok = max(r) <= RATIO_TARGET and mass <= MASS_TARGET
        lines.append(
            f"{GROUP_LABELS[g]}: {best}, velocity error {r[0]:.2f}× persistence's one step and {r[1]:.2f}× at "
            f"50 steps, mass within {html.percent(mass)} "
            f"({'meets' if ok else 'misses'} the targets ≤ {RATIO_TARGET}× and "
            f"±{html.percent(MASS_TARGET, 0)})"
        )
    return "Best model per held-out group — " + "; ".join(lines) + "." if lines else ""


def _model(ctx: Context, model: str, path: Path, doc: dict[str, Any]) -> str:
    facts = [doc.get("summary", ""), f"history {doc['history']} rows, horizon {doc['horizon']}"]
    if doc.get("train_seconds") is not None:
        facts.append(f"training took {doc['train_seconds']:.0f} s")
    rows: list[list[Any]] = []
    for g, data in doc["groups"].items():
        rows.append([html.Group(f"{GROUP_LABELS[g]}: {len(data['points'])} point(s)")])
        rows += [[_point(p), GROUP_LABELS[g], *_cells(p)] for p in data["points"]]
    plots = doc.get("plots") or {}
    images = [(plots.get("rollout"), f"{model}: errors and mass along the rollouts")]
    images += [
        (p, f"{model}, {label}: density on the centre plane, predicted over true")
        for label, p in (plots.get("slices") or {}).items()
    ]
    columns = [html.Column("point", text=True), html.Column("held-out group", text=True), *COLUMNS]
    return (
        html.paragraph("; ".join(f for f in facts if f) + ".")
        + html.table(columns, rows)
        + result_figures(ctx.results, path.parent, images, path)
    )


def rollout_chart(docs: dict[str, dict[str, Any]]) -> Any:
    """Velocity error against rollout step per model, one panel per held-out group."""
    from matplotlib.figure import Figure

    groups = [g for g in GROUPS if any(g in d["groups"] for d in docs.values())]
    with html.figure_style():
        fig = Figure(figsize=(6 * len(groups), 4.2), layout="constrained")
        axes = np.atleast_1d(fig.subplots(1, len(groups), sharey=True))
        for ax, g in zip(axes, groups, strict=True):
            for m, d in docs.items():
                if g in d["groups"]:
                    curve = d["groups"][g]["overall"]["rollout"]["velocity"]
                    ax.plot(np.arange(1, len(curve) + 1), curve, label=m)
            ax.set(title=GROUP_LABELS[g], xlabel="rollout step", yscale="log")
            ax.grid(alpha=0.3)
        axes[0].set_ylabel("velocity error (mass-weighted)")
        axes[0].legend()
    return fig
