"""The live reduced simulation against NDEM on the held-out points: per dynamics model a verdict
and tables of the comparison's figures (``results/reduced/{model}.json``), each beside NDEM's
twin's with the skill where the twins ran, with the targets, where the smoothed surface departs
from NDEM's, and per point the force, field-error, bed-profile and surface-difference plots and
the side-by-side animation (a file beside the page)."""

from __future__ import annotations

import json
import math
from functools import partial
from typing import Any

from dozerlab.report import html
from dozerlab.report.sections import GROUP_LABELS, Context, result_file
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


def _ratio(value: float | None) -> str:
    return html.fmt(value) if value is None or not math.isfinite(value) else f"{value:.2f}"


def _mm(value: float | None) -> str:
    return html.fmt(None if value is None else 1e3 * value)


#: The figures measured against NDEM (dozerlab.reduce.compare.FIGURES), in two tables: those on
#: the scales NDEM reproduces (each beside the twin's, with the skill but for the mean force's:
#: :func:`_skill_bounds`) and those of the grain scale and the fields (beside the twin's): (key,
#: heading, unit, format).
WELL_POSED = [
    ("surface_accuracy", "smoothed-surface accuracy", "%", _pct),
    ("force_lp_rel_rmse", "low-passed force x rel. RMSE", "%", _pct),
    ("force_mean_rel_err", "mean force x rel. error", "%", _pct),
]


def _skill_bounds(t: dict[str, Any], replay: bool) -> dict[str, float]:
    """The figures of :data:`WELL_POSED` shown with their skill, each with the target its skill is
    judged against (``reduced.targets``). One twin's mean-force error is a chance draw from near 0
    to several per cent, so a ratio over it says more of the twin than of the run: in a default
    sweep the twins' lay at 0.03–6.0 % over the five held-out points, and the ridge's 4.0 % at
    step 1.125 / 0.075 read as a skill of 120 (BENCHMARKS.md, "The default sweep on another
    processor")."""
    surface = t["replay_surface_skill"] if replay else t["surface_skill"]
    return {"surface_accuracy": surface, "force_lp_rel_rmse": t["force_skill"]}


#: Where the smoothed surface departs from NDEM's (dozerlab.reduce.compare.surface_errors): each
#: region's error and excess as shares of NDEM's change of the bed, beside the twin's.
REGIONS = [
    (f"surface_{what}_{region}", f"{what}, {name}", "%", _pct)
    for what in ("error", "excess")
    for region, name in (("swath", "swath"), ("beside", "beside it"), ("ahead", "ahead"))
]
GRAIN_SCALE = [
    ("height_accuracy", "height accuracy (grain cells)", "%", _pct),
    ("force_x_rel_rmse", "force x rel. RMSE", "%", _pct),
    ("velocity_rel_l2", "velocity rel. L2", "%", _pct),
    ("density_rel_l2", "density rel. L2", "%", _pct),
    ("final_emd_m", "EMD of moved grains", "mm", _mm),
]
#: The figures measured against NDEM's expected run (reduced.twin.draws > 1), each beside NDEM's
#: own run's and the skill, the run's over NDEM's run's.
EXPECTED = [
    ("surface_accuracy", "smoothed-surface accuracy", "%", _pct),
    ("force_lp_rel_rmse", "low-passed force x rel. RMSE", "%", _pct),
]
POINT_COLUMNS = [html.Column("point", text=True), html.Column("group", text=True)]


def _validity(t: dict[str, Any]) -> list[html.Column]:
    """The per-point table's checks, the overlap and the speed-ups to the precision that keeps
    each on its side of its target."""
    return [
        html.Column(
            "largest overlap after projection",
            "% of radius",
            lambda v: html.against(None if v is None else 100 * v, 100 * t["max_overlap"], 1),
        ),
        html.Column("grains that left", ""),
        html.Column(
            "loop speed-up", "×", partial(html.against, bound=t["loop_speedup"], decimals=1)
        ),
        html.Column("job speed-up", "×", partial(html.against, bound=t["job_speedup"], decimals=1)),
    ]


def _has_twin(points: list[dict[str, Any]]) -> bool:
    return any(k.startswith("twin_") for p in points for k in p)


def _figure_table(
    figures: list[tuple[str, str, str, Any]],
    points: list[dict[str, Any]],
    skill: dict[str, float] | None = None,
) -> str:
    """A row per point: each figure, beside it the twin's (when measured) and, for the figures
    in ``skill``, the run's over the twin's, to the precision that keeps it on its side of the
    target ``skill`` maps the figure to."""
    skill = skill or {}
    twin = _has_twin(points)
    columns, keys = list(POINT_COLUMNS), []
    for key, name, unit, form in figures:
        columns.append(html.Column(name, unit, form))
        keys.append(key)
        if twin:
            columns.append(html.Column("twin", unit, form))
            keys.append(f"twin_{key}")
            if key in skill:
                columns.append(html.Column("skill", "×", partial(html.against, bound=skill[key])))
                keys.append(f"{key}_skill")
    return html.table(columns, [[*_point_cells(p), *(p.get(k) for k in keys)] for p in points])


def _draws(points: list[dict[str, Any]]) -> int:
    """The twin draws behind NDEM's expected run (0: not measured, one twin or none)."""
    return max((int(p.get("twin_draws") or 0) for p in points), default=0)


def _expected_table(points: list[dict[str, Any]]) -> str:
    """A row per point: each of :data:`EXPECTED` against NDEM's expected run, beside NDEM's own
    run's and the skill."""
    columns, keys = list(POINT_COLUMNS), []
    for key, name, unit, form in EXPECTED:
        columns += [
            html.Column(name, unit, form),
            html.Column("NDEM's run", unit, form),
            html.Column("skill", "×", _ratio),
        ]
        keys += [f"expected_{key}", f"ndem_expected_{key}", f"expected_{key}_skill"]
    return html.table(columns, [[*_point_cells(p), *(p.get(k) for k in keys)] for p in points])


def _point_cells(p: dict[str, Any]) -> list[Any]:
    return [
        f"{p['scenario']} {fmt_number(p['speed'])} m/s, {fmt_number(p['depth'])} m",
        GROUP_LABELS.get(p["role"], p["role"]),
    ]


def _mean(points: list[dict[str, Any]], key: str) -> float | None:
    values = [p[key] for p in points if p.get(key) is not None and math.isfinite(p[key])]
    return sum(values) / len(values) if values else None


def _targets_said(points: list[dict[str, Any]]) -> str:
    """Which targets every point meets and which some miss (on how many points)."""
    n = len(points)
    missed: dict[str, int] = {}
    known: set[str] = set()
    for p in points:
        for k, ok in p["targets_met"].items():
            if ok is not None:
                known.add(k)
            if ok is False:
                missed[k] = missed.get(k, 0) + 1
    met = sorted(known - missed.keys())
    said = f"targets met on every point: {', '.join(met) or 'none'}"
    if missed:
        said += "; missed: " + ", ".join(f"{k} ({c} of {n})" for k, c in sorted(missed.items()))
    return said


def _targets_count(points: list[dict[str, Any]]) -> tuple[int, int]:
    """(targets met on every point, targets judged): a target counts once it is judged on some
    point (a speed-up without a measured NDEM wall time is not), met when no point misses it."""
    known = {k for p in points for k, ok in p["targets_met"].items() if ok is not None}
    missed = {k for p in points for k, ok in p["targets_met"].items() if ok is False}
    return len(known - missed), len(known)


def _force_models(points: list[dict[str, Any]]) -> str:
    return ", ".join(sorted({str(p.get("force_model")) for p in points}))


def _model_verdict(model: str, doc: dict[str, Any]) -> str:
    """One short sentence on one dynamics model's reduced runs: its force model, the number of
    held-out points and the targets met and missed; the figures are in the tables."""
    points = doc["points"]
    n = len(points)
    return (
        f"{model} fields and the {_force_models(points)} force model on {n} held-out "
        f"point{'s' if n != 1 else ''}: {_targets_said(points)}."
    )


def _ndem(ctx: Context) -> str:
    """NDEM as the sweep ran it, which its speed-ups are over: the full solve, or with
    ``solver.active_zone`` the zone's NDEM (2.2–3.3× faster on the default sweep's points)."""
    return "NDEM with its active zone" if ctx.cfg["solver"]["active_zone"]["enabled"] else "NDEM"


def _headline(who: str, points: list[dict[str, Any]], ndem: str = "NDEM") -> str:
    """The headline of one model's runs (``who``: its name and what it is), means over the
    held-out points: the smoothed-surface
    and low-passed force skills against the twin (the figures alone without one), the loop and
    job speed-ups over ``ndem`` (:func:`_ndem`) and the targets met."""
    figures = []
    if _has_twin(points):
        figures.append(f"smoothed-surface skill {_ratio(_mean(points, 'surface_accuracy_skill'))}")
        force = _mean(points, "force_lp_rel_rmse_skill")
        figures.append(f"low-passed force error {_ratio(force)}× the twin's")
    else:
        figures.append(
            f"smoothed-surface accuracy {html.percent(_mean(points, 'surface_accuracy'))}"
        )
        force = _mean(points, "force_lp_rel_rmse")
        figures.append(f"low-passed force error {html.percent(force)}")
    speeds = [
        f"{name} {value:.1f}×"
        for key, name in (("loop_speedup", "loop"), ("job_speedup", "job"))
        if (value := _mean(points, key)) is not None
    ]
    if speeds:
        figures.append(" and ".join(speeds) + f" as fast as {ndem}")
    met, judged = _targets_count(points)
    # means, said as such: beside "met on every held-out point" a bare figure reads as each
    # point's (the default sweep's ridge: force skill 1.16 on average, 0.88-1.67 by point)
    over = (
        "on its one held-out point"
        if len(points) == 1
        else f"means over its {len(points)} held-out points"
    )
    return (
        f"{who}, {over}: {', '.join(figures)}; {met} of {judged} targets met on every held-out "
        "point."
    )


def verdict(ctx: Context) -> str | None:
    """The reduced simulation's headline: the best learned dynamics model (highest mean
    smoothed-surface skill, accuracy without twins) or, with none, the replay control; the
    table of the section holds every model's figures."""
    docs = _documents(ctx)
    learned = {m: d["points"] for m, d in docs.items() if m != REPLAY and d["points"]}
    if learned:
        key = (
            "surface_accuracy_skill"
            if any(map(_has_twin, learned.values()))
            else "surface_accuracy"
        )
        best = max(learned, key=lambda m: _mean(learned[m], key) or -math.inf)
        return _headline(
            f"{best} is the best learned evolution model in the loop", learned[best], _ndem(ctx)
        )
    if docs.get(REPLAY, {}).get("points"):
        who = f"{REPLAY} (NDEM's own fields: the loop's own error)"
        return _headline(who, docs[REPLAY]["points"], _ndem(ctx))
    return None


#: The models table's figures, means over a model's held-out points: (key, column); the twin's
#: and the skills only where twins ran.
MODEL_FIGURES = [
    ("surface_accuracy", html.Column("smoothed-surface accuracy", "%", _pct)),
    ("twin_surface_accuracy", html.Column("twin", "%", _pct)),
    ("surface_accuracy_skill", html.Column("surface skill", "×", _ratio)),
    ("force_lp_rel_rmse", html.Column("low-passed force error", "%", _pct)),
    ("twin_force_lp_rel_rmse", html.Column("twin", "%", _pct)),
    ("force_lp_rel_rmse_skill", html.Column("force skill", "×", _ratio)),
    ("expected_force_lp_rel_rmse_skill", html.Column("force skill, expected run", "×", _ratio)),
    ("loop_speedup", html.Column("loop speed-up", "×", _times)),
    ("job_speedup", html.Column("job speed-up", "×", _times)),
]


def _models_table(docs: dict[str, dict[str, Any]]) -> str:
    """A row per dynamics model: its force model, the mean over its held-out points of each
    headline figure (beside the twin's, with the skill, where twins ran) and its targets met on
    every point of those judged."""
    twin = any(_has_twin(d["points"]) for d in docs.values())
    figures = [(k, c) for k, c in MODEL_FIGURES if twin or not k.startswith("twin_")]
    figures = [(k, c) for k, c in figures if twin or not k.endswith("_skill")]
    if not any(_draws(d["points"]) for d in docs.values()):
        figures = [(k, c) for k, c in figures if not k.startswith("expected_")]
    columns = [
        html.Column("model", text=True),
        html.Column("force model", text=True),
        *(c for _, c in figures),
        html.Column("targets met", text=True),
    ]
    transfer = any(d.get("transfer") for d in docs.values())
    if transfer:
        columns.append(html.Column("surface skill, unseen terrain / seen", text=True))
    rows = [
        [
            model,
            _force_models(doc["points"]),
            *(_mean(doc["points"], k) for k, _ in figures),
            "{} of {}".format(*_targets_count(doc["points"])),
            *([_transfer_cell(doc.get("transfer"))] if transfer else []),
        ]
        for model, doc in docs.items()
    ]
    return html.table(columns, rows)


def _transfer_cell(t: dict[str, Any] | None) -> str:
    """The comparison's ``transfer`` entry: unseen-terrain skill over the seen shapes', and
    whether the gap is within ``reduced.targets.transfer_skill_gap``."""
    if not t:
        return "–"
    verdict = "within" if t["met"] else "beyond"
    return (
        f"{t['surface_skill_unseen']:.2f} / {t['surface_skill_seen']:.2f} "
        f"({verdict} {t['target']:g})"
    )


def _caption(t: dict[str, Any], replay: bool) -> str:
    """The targets of one model's runs (``reduced.targets``)."""
    skills = (
        f"smoothed-surface skill ≥ {t['replay_surface_skill']:g}"
        if replay
        else f"smoothed-surface skill ≥ {t['surface_skill']:g}, low-passed force error ≤ "
        f"{t['force_skill']:g}× the twin's"
    )
    return (
        f"targets: {skills}, loop ≥ {t['loop_speedup']:g}×, job ≥ {t['job_speedup']:g}×, "
        f"overlap ≤ {t['max_overlap']:.0%} of a radius, nothing left the bed"
    )


def _documents(ctx: Context) -> dict[str, dict[str, Any]]:
    """The comparison document of each configured dynamics model the results hold one of."""
    docs = {}
    for model in ctx.cfg.get("reduced", {}).get("dynamics_models", []):
        path = reduced_comparison_path(ctx.results, model)
        if path.is_file():
            docs[model] = json.loads(path.read_text(encoding="utf-8"))
    return docs


def render(ctx: Context) -> str | None:
    docs = _documents(ctx)
    if not docs:
        return None
    parts = [
        _models_table(docs),
        html.paragraph(
            "Means over the held-out points. The skill is the run's figure over NDEM's twin's "
            "(NDEM again from the bed moved by a micrometre: its own reproducibility); a target "
            "counts once judged on some point and is met when every point meets it. replay "
            "feeds the loop NDEM's own fields: a control, the loop's own error. A speed-up "
            "divides NDEM's time by the run's, each taken in its own job beside whatever else "
            "the sweep ran, so it moves with the machine; benchmarks/reduce_loop.py --repeat "
            "measures the two side by side. "
            + (
                "NDEM ran with its active zone (solver.active_zone: the grains at rest "
                f"beyond {ctx.cfg['solver']['active_zone']['margin']} m of the blade asleep), "
                "so the speed-ups are over that NDEM, not over the full solve."
                if ctx.cfg["solver"]["active_zone"]["enabled"]
                else "NDEM ran the full solve: every grain stepped."
            )
            + (
                " Force skill, expected run: the low-passed force error against the mean of the "
                "twin draws over NDEM's own run's against it."
                if any(_draws(d["points"]) for d in docs.values())
                else ""
            ),
            "caption",
        ),
    ]
    reduced = ctx.cfg["reduced"]
    for model, doc in docs.items():
        path = reduced_comparison_path(ctx.results, model)
        t = doc["targets"]
        parts.append(f"<h3>{html.esc(model)}</h3>")
        parts.append(html.paragraph(_model_verdict(model, doc)))
        steered = model in reduced["density_models"] and reduced["density_gain"] > 0
        crest = model in reduced["crest_models"] and reduced["crest_bins"] > 0
        if model == REPLAY:
            parts.append(
                html.paragraph(
                    "replay feeds the loop NDEM's own fields, its velocity moving the grains"
                    + (" and its density steering them" if steered else "")
                    + (", the pile's crest lifted over the blade's top" if crest else "")
                    + ": its errors are the loop's (advection, projection, what the fields cannot "
                    "carry) alone."
                )
            )
        else:
            if steered:
                parts.append(
                    html.paragraph(f"The grains are steered towards {model}'s density too.")
                )
            if crest:
                parts.append(html.paragraph("The pile's crest is lifted over the blade's top too."))
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
        points = doc["points"]
        twin = _has_twin(points)
        parts.append(
            html.paragraph(
                "On the scales NDEM reproduces: the surface smoothed at one grain diameter and "
                "the pushing force low-passed over 0.1 s"
                + (
                    ", each beside NDEM's twin (NDEM again from the bed moved by a micrometre: "
                    "its own reproducibility) and the skill, the run's figure over the twin's. "
                    "The mean force has no skill: one twin's error of it is a chance draw from "
                    "near 0 to several per cent, and a ratio over it would say more of the twin "
                    "than of the run."
                    if twin
                    else " (no twin runs: reduced.twin.enabled is false)."
                ),
                "caption",
            )
        )
        parts.append(_figure_table(WELL_POSED, points, _skill_bounds(t, model == REPLAY)))
        if draws := _draws(points):
            parts.append(
                html.paragraph(
                    f"Against NDEM's expected run, the mean of {draws} twin draws (their "
                    "low-passed pushing forces and smoothed surfaces), beside NDEM's own run "
                    "against it, and the skill, the run's figure over NDEM's run's: NDEM's run "
                    "is one draw of its chaos, so a run that predicts the expected run scores "
                    "below 1 on the force (the twin columns above are the means over the draws).",
                    "caption",
                )
            )
            parts.append(_expected_table(points))
        if any("surface_error_swath" in p for p in points):
            parts.append(
                html.paragraph(
                    "Where the smoothed surface departs from NDEM's: the swath the blade cut, the "
                    "strips beside it (the windrows) and the bed ahead of the blade's last "
                    "position (the pile it carries). Error: the region's Σ|h − h_NDEM|, excess: "
                    "its Σ(h − h_NDEM) (below 0: too little material there), both as shares of "
                    "NDEM's change of the whole bed, Σ|h_NDEM − h_bed|; the errors add up to "
                    "100 % less the accuracy. Each point's surface plot maps them.",
                    "caption",
                )
            )
            parts.append(_figure_table(REGIONS, points))
        parts.append(html.paragraph("The grain scale and the fields around the blade:", "caption"))
        parts.append(_figure_table(GRAIN_SCALE, points))
        parts.append(
            html.table(
                POINT_COLUMNS + _validity(t),
                [
                    [
                        *_point_cells(p),
                        p["max_overlap_loop"],
                        p["left_bed"],
                        p["loop_speedup"],
                        p["job_speedup"],
                    ]
                    for p in points
                ],
                caption=_caption(t, model == REPLAY),
            )
        )
        plots = path.with_suffix("") / "compare"
        for p in doc["points"]:
            label = f"{p['scenario']}: speed {fmt_number(p['speed'])} m/s, depth {fmt_number(p['depth'])} m"
            missed = [k for k, ok in p["targets_met"].items() if ok is False]
            figs = []
            for name in p["plots"]:
                file = result_file(ctx.results, plots, name, path)
                if file is None:
                    continue
                kind = name.rsplit("_", 1)[-1].split(".")[0]
                if name.endswith(".gif"):
                    figs.append(
                        html.animation(
                            file,
                            ctx.page_dir,
                            f"reduced_{model}_{file.name}",
                            f"{label}: NDEM (left) and reduced (right)",
                        )
                    )
                else:
                    figs.append(html.figure(file, f"{label}: {kind}"))
            summary = label + (f" — targets missed: {', '.join(missed)}" if missed else "")
            parts.append(html.details(summary, "".join(figs)))
    return "\n".join(parts)
