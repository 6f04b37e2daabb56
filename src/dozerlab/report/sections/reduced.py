"""The live reduced simulation against NDEM on the held-out points: per dynamics model a verdict
and a table of the comparison's figures (``results/reduced/{model}.json``) with the targets,
and per point the force, field-error and bed-profile plots and the side-by-side animation (a
file beside the page)."""

from __future__ import annotations

import json
import math
from typing import Any

from dozerlab.report import html
from dozerlab.report.sections import GROUP_LABELS, Context
from dozerlab.sweep import fmt_number, reduced_comparison_path

TITLE = "Reduced simulation against NDEM"
ORDER = 60
QUESTION = "Reduced simulation against NDEM"
#: The dynamics model that feeds the loop NDEM's own fields: a control, not a reduced model.
REPLAY = "replay"


def _pct(value: float | None) -> str:
    return html.percent(value).removesuffix(" %")


def _times(value: float | None) -> str:
    return html.fmt(value) if value is None else f"{value:.1f}"


COLUMNS = [
    html.Column("point", text=True),
    html.Column("group", text=True),
    html.Column("height accuracy", "%", _pct),
    html.Column("force x rel. RMSE", "%", _pct),
    html.Column("velocity rel. L2", "%", _pct),
    html.Column("density rel. L2", "%", _pct),
    html.Column("EMD of moved grains", "mm", lambda v: html.fmt(None if v is None else 1e3 * v)),
    html.Column("largest overlap after projection", "% of radius", _pct),
    html.Column("grains that left", ""),
    html.Column("loop speed-up", "×", _times),
    html.Column("job speed-up", "×", _times),
]


def _row(p: dict[str, Any]) -> list[Any]:
    return [
        f"{p['scenario']} {fmt_number(p['speed'])} m/s, {fmt_number(p['depth'])} m",
        GROUP_LABELS.get(p["role"], p["role"]),
        p["height_accuracy"],
        p["force_x_rel_rmse"],
        p["velocity_rel_l2"],
        p["density_rel_l2"],
        p["final_emd_m"],
        p["max_overlap_loop"],
        p["left_bed"],
        p["loop_speedup"],
        p["job_speedup"],
    ]


def _mean(points: list[dict[str, Any]], key: str) -> float | None:
    values = [p[key] for p in points if p.get(key) is not None and math.isfinite(p[key])]
    return sum(values) / len(values) if values else None


def _model_verdict(model: str, doc: dict[str, Any]) -> str:
    """One sentence on one dynamics model's reduced runs: the mean height accuracy, force error
    and speed-ups over the held-out points, and on how many points every target is met."""
    points = doc["points"]
    n = len(points)
    forces = ", ".join(sorted({str(p.get("force_model")) for p in points}))
    figures = [
        f"height accuracy {html.percent(_mean(points, 'height_accuracy'))}",
        f"draft force rel. RMSE {html.percent(_mean(points, 'force_x_rel_rmse'))}",
    ]
    for key, name in (("loop_speedup", "loop"), ("job_speedup", "job")):
        if (value := _mean(points, key)) is not None:
            figures.append(f"{name} {value:.1f}× as fast as NDEM's")
    met = sum(all(ok is not False for ok in p["targets_met"].values()) for p in points)
    missed = sorted({k for p in points for k, ok in p["targets_met"].items() if ok is False})
    text = (
        f"{model} fields and the {forces} force model: {', '.join(figures)} (mean of {n} "
        f"held-out point{'s' if n != 1 else ''}); every target met on {met} of {n}"
    )
    return text + (f" (missed: {', '.join(missed)})." if missed else ".")


def verdict(ctx: Context) -> str | None:
    """The reduced simulation's verdict: that of each learned dynamics model, then the replay
    control's height and force figures, which bound what the loop alone can reach."""
    docs = _documents(ctx)
    learned = [_model_verdict(m, d) for m, d in docs.items() if m != REPLAY]
    if REPLAY in docs:
        points = docs[REPLAY]["points"]
        control = (
            f"Control, replay (NDEM's own fields: the loop's own error): height accuracy "
            f"{html.percent(_mean(points, 'height_accuracy'))}, draft force rel. RMSE "
            f"{html.percent(_mean(points, 'force_x_rel_rmse'))}."
        )
        learned.append(control if learned else _model_verdict(REPLAY, docs[REPLAY]))
    return " ".join(learned) or None


def _documents(ctx: Context) -> dict[str, dict[str, Any]]:
    """The comparison document of each configured dynamics model the results hold one of."""
    docs = {}
    for model in ctx.cfg.get("reduced", {}).get("dynamics_models", []):
        path = reduced_comparison_path(ctx.results, model)
        if path.is_file():
            docs[model] = json.loads(path.read_text(encoding="utf-8"))
    return docs


def render(ctx: Context) -> str | None:
    parts = []
    for model, doc in _documents(ctx).items():
        path = reduced_comparison_path(ctx.results, model)
        t = doc["targets"]
        parts.append(f"<h3>{html.esc(model)}</h3>")
        parts.append(html.paragraph(_model_verdict(model, doc)))
        if model == REPLAY:
            parts.append(
                html.paragraph(
                    "replay feeds the loop NDEM's own fields: its errors are the loop's "
                    "(advection, projection, what the fields cannot carry) alone."
                )
            )
        forces = sorted({str(p.get("force_model")) for p in doc["points"]})
        parts.append(
            html.paragraph(
                f"force model: {', '.join(forces)}"
                + (
                    " (trained on the fields this model's loop makes at the training points)"
                    if any(f.endswith("-loop") for f in forces)
                    else ""
                )
            )
        )
        parts.append(
            html.table(
                COLUMNS,
                [_row(p) for p in doc["points"]],
                caption=(
                    f"targets: height accuracy ≥ {t['height_accuracy']:.0%}, force x rel. RMSE ≤ "
                    f"{t['force_rmse']:.0%}, loop ≥ {t['loop_speedup']:g}×, job ≥ "
                    f"{t['job_speedup']:g}×, overlap ≤ {t['max_overlap']:.0%} of a radius, "
                    "nothing left the bed"
                ),
            )
        )
        plots = path.with_suffix("") / "compare"
        for p in doc["points"]:
            label = f"{p['scenario']}: speed {fmt_number(p['speed'])} m/s, depth {fmt_number(p['depth'])} m"
            missed = [k for k, ok in p["targets_met"].items() if ok is False]
            figs = []
            for name in p["plots"]:
                file = plots / name
                if not file.is_file():
                    continue
                kind = name.rsplit("_", 1)[-1].split(".")[0]
                if name.endswith(".gif"):
                    figs.append(
                        html.animation(
                            file,
                            ctx.page_dir,
                            f"reduced_{model}_{name}",
                            f"{label}: NDEM (left) and reduced (right)",
                        )
                    )
                else:
                    figs.append(html.figure(file, f"{label}: {kind}"))
            summary = label + (f" — targets missed: {', '.join(missed)}" if missed else "")
            parts.append(html.details(summary, "".join(figs)))
    return "\n".join(parts) if parts else None
