"""The live reduced simulation against NDEM on the held-out points: per dynamics model a table
of the comparison's figures (``results/reduced/{model}.json``) with the targets, and per point
the force, field-error and bed-profile plots and the side-by-side animation."""

from __future__ import annotations

import json
from typing import Any

from dozerlab.report import html
from dozerlab.report.sections import Context
from dozerlab.sweep import fmt_number, reduced_comparison_path

TITLE = "Reduced simulation against NDEM"
ORDER = 60


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
        p["role"],
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


def _gif(path: Any, caption: str) -> str:
    return (
        f'<figure><img src="{html.data_uri(path, "image/gif")}" alt="{html.esc(caption)}">'
        f"<figcaption>{html.esc(caption)}</figcaption></figure>"
    )


def render(ctx: Context) -> str | None:
    parts = []
    for model in ctx.cfg.get("reduced", {}).get("dynamics_models", []):
        path = reduced_comparison_path(ctx.results, model)
        if not path.is_file():
            continue
        doc = json.loads(path.read_text(encoding="utf-8"))
        t = doc["targets"]
        parts.append(f"<h3>{html.esc(model)}</h3>")
        if model == "replay":
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
                    figs.append(_gif(file, f"{label}: NDEM (left) and reduced (right)"))
                else:
                    figs.append(html.figure(file, f"{label}: {kind}"))
            summary = label + (f" — targets missed: {', '.join(missed)}" if missed else "")
            parts.append(html.details(summary, "".join(figs)))
    return "\n".join(parts) if parts else None
