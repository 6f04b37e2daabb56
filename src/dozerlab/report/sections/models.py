"""The models on the held-out sweep points: an error chart, the comparison table and each
model's validation (per-point errors, loss, parity and force-series plots), read from the
JSON and PNGs that ``dozerlab validate`` wrote."""

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
from dozerlab.sweep import fmt_number, validation_path

TITLE = "Models on held-out points"
ORDER = 50
QUESTION = "Best force model on held-out points"

#: The compared components (the blade's draft force, lift and pitch torque) and their units.
COMPARED = {"force_x": "kN", "force_z": "kN", "torque_y": "kN·m"}
#: The thesis's CNN, about 10 % force error, measured on its training data only.
THESIS_ERROR = 0.10


def _pct(value: float | None) -> str:
    return html.percent(value).removesuffix(" %")


def _r2(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value:.3f}"


def _kilo(value: float | None) -> str:
    return "–" if value is None or not math.isfinite(value) else f"{value / 1000:.3g}"


def _columns(first: str) -> list[html.Column]:
    cols = [html.Column(first, text=True), html.Column("held-out group", text=True)]
    for c, unit in COMPARED.items():
        cols += [
            html.Column(f"{c} rel. RMSE", "%", _pct),
            html.Column(f"{c} RMSE", unit, _kilo),
            html.Column(f"{c} R²", "", _r2),
        ]
    return cols


def _cells(m: dict[str, dict[str, float]]) -> list[Any]:
    return [m[c][k] for c in COMPARED for k in ("rel_rmse", "rmse", "r2")]


def render(ctx: Context) -> str | None:
    models = ctx.cfg["learn"]["models"]
    return model_comparison(ctx, models, validation_path, _compare, _model, "validation")


def verdict(ctx: Context) -> str | None:
    """The model with the lowest draft-force (force_x) relative RMSE over the held-out groups
    (their mean), its error per group and the runner-up's, against the thesis CNN's."""
    docs = {
        m: doc
        for m, (_, doc) in documents(ctx, ctx.cfg["learn"]["models"], validation_path).items()
    }
    scores = {}
    for m, doc in docs.items():
        errors = {
            g: doc["groups"][g]["overall"]["force_x"]["rel_rmse"]
            for g in GROUPS
            if g in doc["groups"]
        }
        if errors and all(math.isfinite(v) for v in errors.values()):
            scores[m] = errors
    if not scores:
        return None
    mean = {m: float(np.mean(list(errors.values()))) for m, errors in scores.items()}
    ranked = sorted(scores, key=mean.__getitem__)
    best = scores[ranked[0]]
    # the mean over the groups ranks them: say so, a runner-up can be ahead in a group
    text = (
        f"{ranked[0]} predicts the draft force best over the held-out groups (mean force_x "
        f"relative RMSE {html.percent(mean[ranked[0]])}): "
    )
    text += " and ".join(f"{html.percent(v)} on the {GROUP_LABELS[g]}" for g, v in best.items())
    text += " points"
    if len(ranked) > 1:
        text += f"; next best {ranked[1]} (mean {html.percent(mean[ranked[1]])}), " + " and ".join(
            html.percent(v) for v in scores[ranked[1]].values()
        )
    return text + f"; the thesis CNN reached {html.percent(THESIS_ERROR, 0)} on its training data."


def _compare(results: dict[str, dict[str, Any]]) -> Comparison:
    rows = group_rows(results, lambda m, g, overall: _cells(overall))
    chart = html.figure(
        error_chart(results),
        "Relative RMSE of each model on the held-out points, per group (lower is better). "
        "The dashed line is the thesis CNN's ≈ 10 % force error, measured on its training "
        "data only.",
    )
    caption = (
        "Relative RMSE: the RMSE of the prediction over the RMS of the measured value, over "
        "every step of the group's held-out runs; R² = 1 − SSE/SST. force_x is the draft "
        "force (along the blade's motion), force_z the vertical force, torque_y the pitch "
        "torque about the blade tip."
    )
    return Comparison(_best(results), chart, _columns("model"), rows, caption)


def _best(results: dict[str, dict[str, Any]]) -> str:
    best = []
    for g in GROUPS:
        scores = {
            m: doc["groups"][g]["overall"]["force_x"]["rel_rmse"]
            for m, doc in results.items()
            if g in doc["groups"]
        }
        scores = {m: v for m, v in scores.items() if math.isfinite(v)}
        if scores:
            m = min(scores, key=scores.__getitem__)
            best.append(f"on the {GROUP_LABELS[g]} points {m}, {html.percent(scores[m])}")
    return "Lowest force_x relative RMSE: " + "; ".join(best) + "." if best else ""


def _model(ctx: Context, model: str, path: Path, doc: dict[str, Any]) -> str:
    train = doc.get("training") or {}
    facts = [doc.get("summary", "")]
    if train.get("epochs"):
        facts.append(
            "closed-form fit (no epochs)"
            if train["epochs"] == 1
            # best_epoch counts from 0; epochs are numbered from 1, as the loss plot shows them
            else f"{train['epochs']} epochs, best at epoch {train['best_epoch'] + 1}"
        )
    if train.get("seconds") is not None:
        facts.append(f"training took {train['seconds']:.0f} s")
    rows: list[list[Any]] = []
    for g, data in doc["groups"].items():
        n = len(data["points"])
        rows.append([html.Group(f"{GROUP_LABELS[g]}: {n} point{'s' if n != 1 else ''}")])
        if n > 1:
            rows.append(["all", GROUP_LABELS[g], *_cells(data["overall"])])
        rows += [[_point(p), GROUP_LABELS[g], *_cells(p["metrics"])] for p in data["points"]]
    plots = doc.get("plots") or {}
    images = [
        (plots.get("loss"), f"{model}: training and validation loss"),
        (plots.get("parity"), f"{model}: predicted vs measured force on the held-out points"),
        *(
            (p, f"{model}, {label}: force over time")
            for label, p in plots.get("series", {}).items()
        ),
    ]
    return (
        html.paragraph("; ".join(f for f in facts if f) + ".")
        + html.table(_columns("point"), rows)
        + result_figures(ctx.results, path.parent, images, path)
    )


def _point(entry: dict[str, Any]) -> str:
    """A validated point as the report spells it: ``hill, 1.25 m/s, 0.06 m``."""
    p = entry.get("point") or {}
    if {"scenario", "speed", "depth"} <= p.keys():
        return f"{p['scenario']}, {fmt_number(p['speed'])} m/s, {fmt_number(p['depth'])} m"
    return str(entry["name"])


def error_chart(results: dict[str, dict[str, Any]]) -> Any:
    """Grouped bars of the relative RMSE (%) per model and held-out group, one panel per
    compared component."""
    from matplotlib.figure import Figure

    models = list(results)
    groups = [g for g in GROUPS if any(g in d["groups"] for d in results.values())]
    width = 0.8 / max(len(groups), 1)
    with html.figure_style():
        fig = Figure(figsize=(12, 4.4), layout="constrained")
        axes = fig.subplots(1, len(COMPARED), sharey=True)
        x = np.arange(len(models))
        for ax, comp in zip(axes, COMPARED, strict=True):
            for k, g in enumerate(groups):
                values = [
                    100 * d["groups"][g]["overall"][comp]["rel_rmse"]
                    if g in d["groups"]
                    else np.nan
                    for d in results.values()
                ]
                bars = ax.bar(
                    x + (k - (len(groups) - 1) / 2) * width, values, width, label=GROUP_LABELS[g]
                )
                ax.bar_label(
                    bars, labels=[f"{v:.1f}" if np.isfinite(v) else "" for v in values], fontsize=10
                )
            if comp.startswith("force"):
                ax.axhline(
                    100 * THESIS_ERROR,
                    color="0.3",
                    ls="--",
                    lw=1,
                    label="thesis CNN ≈ 10 % (training data)" if comp == "force_x" else None,
                )
            ax.set_xticks(x, models)
            ax.set_title(comp)
            ax.grid(axis="y", alpha=0.3)
            ax.margins(y=0.12)
        axes[0].set_ylabel("relative RMSE (%)")
        handles, labels = axes[0].get_legend_handles_labels()
        fig.legend(handles, labels, loc="outside lower center", ncols=len(labels), frameon=False)
    return fig
