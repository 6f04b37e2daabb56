"""A sweep's headline figures, read from its results: the workflow's closing summary on the
console and the metrics of its parent MLflow run (so that sweeps of two configs compare side by
side in MLflow's chart view).

Read from the files the rules write (paths from :mod:`dozerlab.sweep`); a result not built
(a model not configured, a sweep without held-out points) is left out:

- ``results/validation/{model}.json``: each force model's relative RMSE of the blade's force
  along x on all held-out points (``overall.force_x.rel_rmse``, a fraction);
- ``results/dynamics/{model}.json``: each evolution model's relative velocity error
  on the held-out points one step ahead and at the longest rollout (fractions);
- ``results/reduced/{model}.json``: the reduced simulation of each dynamics model against NDEM
  on the held-out points (means of accuracies and errors, beside the twin's with the skills;
  the least speed-ups) and which of ``reduced.targets`` each point meets.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from dozerlab import sweep as P

#: The reduced simulation's figures on the parent run: (key in the comparison's
#: ``overall.all``, what it is). On the scales NDEM reproduces each is followed by the twin's
#: (NDEM again from the bed moved by a micrometre) and the skill, the model's over the twin's,
#: and with more twin draws the force's skill against NDEM's expected run (their mean).
REDUCED_FIGURES = {
    "surface_accuracy": "smoothed-surface accuracy",
    "twin_surface_accuracy": "twin",
    "surface_accuracy_skill": "skill",
    "force_lp_rel_rmse": "low-passed force x rel. RMSE",
    "twin_force_lp_rel_rmse": "twin",
    "force_lp_rel_rmse_skill": "skill",
    "expected_force_lp_rel_rmse_skill": "skill against NDEM's expected run",
    "force_mean_rel_err": "mean force x rel. error",
    "twin_force_mean_rel_err": "twin",
    "height_accuracy": "height accuracy",
    "twin_height_accuracy": "twin",
    "force_x_rel_rmse": "force x rel. RMSE",
    "twin_force_x_rel_rmse": "twin",
    "loop_speedup": "least loop speed-up",
    "job_speedup": "least job speed-up",
}
#: The figures that are fractions (shown in %); the skills are ratios, the speed-ups factors.
PERCENT = tuple(k for k in REDUCED_FIGURES if not k.endswith(("_skill", "_speedup")))


def _read(path: Path) -> dict[str, Any] | None:
    if not path.is_file():
        return None
    doc: dict[str, Any] = json.loads(path.read_text(encoding="utf-8"))
    return doc


def force_errors(results: str | Path, cfg: Mapping[str, Any]) -> dict[str, float]:
    """Each validated force model's held-out force-x relative RMSE (fraction), by model."""
    out = {}
    for model in cfg["learn"]["models"]:
        doc = _read(P.validation_path(results, model))
        if doc is not None:
            out[model] = float(doc["overall"]["force_x"]["rel_rmse"])
    return out


def evolution_errors(results: str | Path, cfg: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """Each validated evolution model's held-out velocity errors (fractions): ``one_step`` and
    ``rollout_<n>`` (the longest rollout validated), by model."""
    out = {}
    for model in cfg["dynamics"]["models"]:
        doc = _read(P.dynamics_validation_path(results, model))
        if doc is None:
            continue
        o = doc["overall"]
        figures = {"one_step": float(o["one_step"]["velocity"])}
        if o["rollout_at"]:
            steps = max(o["rollout_at"], key=int)
            figures[f"rollout_{steps}"] = float(o["rollout_at"][steps]["velocity"])
        out[model] = figures
    return out


def reduced_outcomes(results: str | Path, cfg: Mapping[str, Any]) -> dict[str, dict[str, Any]]:
    """Per dynamics model of the reduced simulation: ``figures`` (:data:`REDUCED_FIGURES` over
    all held-out points), ``points`` (how many), ``met`` / ``missed`` (target: points)."""
    out = {}
    for model in cfg["reduced"]["dynamics_models"]:
        doc = _read(P.reduced_comparison_path(results, model))
        if doc is None:
            continue
        overall = doc["overall"].get("all", {})
        met: dict[str, int] = {}
        missed: dict[str, int] = {}
        for point in doc["points"]:
            for target, ok in point["targets_met"].items():
                if ok is not None:
                    tally = met if ok else missed
                    tally[target] = tally.get(target, 0) + 1
        out[model] = {
            "figures": {
                k: float(overall[k]) for k in REDUCED_FIGURES if overall.get(k) is not None
            },
            "points": len(doc["points"]),
            "met": met,
            "missed": missed,
        }
    return out


def metrics(results: str | Path, cfg: Mapping[str, Any]) -> dict[str, float]:
    """The parent run's metrics: ``force_x_rel_rmse/<model>`` and ``/best``,
    ``evolution_velocity_error/<model>_<one_step|rollout_n>``, ``reduced_<model>/<figure>``
    with ``targets_met`` / ``targets_missed`` (point-target pairs). The part before the slash
    is the chart section MLflow groups them in."""
    out: dict[str, float] = {}
    forces = force_errors(results, cfg)
    out.update({f"force_x_rel_rmse/{m}": v for m, v in forces.items()})
    if forces:
        out["force_x_rel_rmse/best"] = min(forces.values())
    for model, figures in evolution_errors(results, cfg).items():
        out.update({f"evolution_velocity_error/{model}_{k}": v for k, v in figures.items()})
    for model, o in reduced_outcomes(results, cfg).items():
        out.update({f"reduced_{model}/{k}": v for k, v in o["figures"].items()})
        out[f"reduced_{model}/targets_met"] = float(sum(o["met"].values()))
        out[f"reduced_{model}/targets_missed"] = float(sum(o["missed"].values()))
    return out


def _pct(value: float) -> str:
    return f"{100 * value:.0f} %"


#: The figures said in brackets after the model's own: the twin's and the skill.
_BESIDE = tuple(k for k in REDUCED_FIGURES if k.startswith("twin_") or k.endswith("_skill"))


def _said(key: str, f: Mapping[str, float]) -> str:
    """One reduced figure on the console, e.g. ``smoothed-surface accuracy 71 % (twin 90 %,
    skill 0.79)``; the twin's and the skill where the figures hold them."""
    text = f"{REDUCED_FIGURES[key]} " + (_pct(f[key]) if key in PERCENT else f"{f[key]:.1f}x")
    beside = []
    if (twin := f.get(f"twin_{key}")) is not None:
        beside.append(f"twin {_pct(twin)}")
    if (skill := f.get(f"{key}_skill")) is not None:
        beside.append(f"skill {skill:.2f}")
    if (skill := f.get(f"expected_{key}_skill")) is not None:
        beside.append(f"{skill:.2f} against NDEM's expected run")
    return text + (f" ({', '.join(beside)})" if beside else "")


def _duration(seconds: float) -> str:
    minutes, secs = divmod(round(seconds), 60)
    return f"{minutes} min {secs} s" if minutes else f"{secs} s"


def summary_lines(results: str | Path, cfg: Mapping[str, Any], wall_s: float) -> list[str]:
    """The workflow's closing summary: wall time, the report, the best force and evolution
    models on the held-out points, and the targets the reduced simulation meets and misses."""
    lines = [f"dozerlab: finished in {_duration(wall_s)}"]
    report = Path(results) / "report" / "index.html"
    if report.is_file():
        lines.append(f"  report    {report}")
    forces = force_errors(results, cfg)
    if forces:
        ranked = sorted(forces, key=forces.__getitem__)
        others = ", ".join(f"{m} {_pct(forces[m])}" for m in ranked[1:])
        lines.append(
            f"  force     best on held-out points: {ranked[0]}, force x rel. RMSE "
            f"{_pct(forces[ranked[0]])}" + (f" ({others})" if others else "")
        )
    evolution = evolution_errors(results, cfg)
    base = evolution.pop("persistence", None)
    if evolution and base:
        # each over persistence's (which keeps the fields as they are): one step and the
        # longest rollout
        ratios = {m: {k: e[k] / base[k] for k in e if base.get(k)} for m, e in evolution.items()}
        # the figures, not a winner: the report ranks them per held-out group (its summary)
        said = "; ".join(
            f"{m} " + ", ".join(f"{v:.2f}x {k.replace('_', ' ')}" for k, v in r.items())
            for m, r in sorted(ratios.items())
        )
        lines.append(f"  evolution velocity error over persistence's, held-out points: {said}")
    # with the active zone the speed-ups are over the zone's NDEM (2-3x the full solve's)
    zone = bool(cfg["solver"]["active_zone"]["enabled"])
    for model, o in reduced_outcomes(results, cfg).items():
        f = o["figures"]
        shown = [_said(k, f) for k in REDUCED_FIGURES if k in f and k not in _BESIDE]
        if zone and any(k.endswith("_speedup") for k in f):
            shown.append("speed-ups over NDEM with its active zone")
        lines.append(f"  reduced   {model} on {o['points']} held-out points: " + ", ".join(shown))
        met = [t for t in o["met"] if t not in o["missed"]]
        missed = [f"{t} ({n} of {o['points']})" for t, n in o["missed"].items()]
        lines.append(
            "            targets met: "
            + (", ".join(met) or "none")
            + "; missed: "
            + (", ".join(missed) or "none")
        )
    return lines
