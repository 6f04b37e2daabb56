"""The train-dynamics / validate-dynamics jobs: field stores in, a model directory or metrics
JSON and plots out, each an MLflow run (the force models' pattern, :mod:`dozerlab.learn.jobs`)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from dozerlab.learn.data import StoreData, check_grid
from dozerlab.learn.dynamics import plots, pyfunc
from dozerlab.learn.dynamics.metrics import combine, evaluate_store, public
from dozerlab.learn.dynamics.models import DynamicsModel
from dozerlab.learn.dynamics.pyfunc import FORMAT, MODEL_DIR
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.learn.dynamics.windows import frame_of
from dozerlab.learn.jobs import Family, held_out_params, record_validation, train_job
from dozerlab.learn.train import TrainResult
from dozerlab.learn.validate import GROUPS, check_no_leak, load_groups
from dozerlab.runtime import OutputKind, atomic_output, job_outputs, json_with, marked_folder
from dozerlab.tracking import job_run, run_name

#: What ``validate-dynamics`` writes: held-out one-step and rollout metrics.
VALIDATION_JSON = OutputKind(
    "a dozerlab evolution-model validation JSON",
    json_with(("model", "overall", "groups", "horizon")),
    "validate-dynamics",
)
#: ``validate-dynamics``'s plots: a folder built whole (the JSON's plot paths point into it).
DYNAMICS_PLOTS = marked_folder(
    "a dozerlab folder of evolution-model validation plots", "validate-dynamics-plots"
)


def _recorded(config: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    dyn = config["dynamics"]
    split = {k: config["learn"][k] for k in ("validation_fraction", "validation_block")}
    return {"dynamics": dyn, "split": split}, {"dynamics": dyn, "learn": split}


#: The field-evolution models: ``dozerlab train-dynamics``.
DYNAMICS = Family(
    "dynamics ",
    "train_dynamics",
    "val_rollout_loss",
    train_dynamics,
    FORMAT,
    _recorded,
    output=MODEL_DIR,
    family="evolution",
)


def train_dynamics_job(
    kind: str, train: list[str | Path], config: dict[str, Any], out: str | Path, **options: Any
) -> TrainResult:
    """Train evolution model ``kind`` on the stores ``train``; save the MLflow model directory
    at ``out`` and log the run (params, per-epoch losses, timing, loss plot, model): the force
    models' :func:`~dozerlab.learn.jobs.train_job` with the :data:`DYNAMICS` family
    (``options``: its ``device`` and ``progress``)."""
    return train_job(kind, train, config, out, family=DYNAMICS, **options)


def validate_dynamics(
    model: DynamicsModel,
    meta: dict[str, Any],
    held_out: dict[str, list[StoreData]],
    steps: int,
    starts: int,
    plots_dir: str | Path | None = None,
    json_dir: str | Path | None = None,
    plots_at: str | Path | None = None,
) -> dict[str, Any]:
    """Metrics of ``model`` on held-out stores grouped by ``GROUPS`` (``steps``-row rollouts
    from ``starts`` true states each), per point, per group and overall, with plots into
    ``plots_dir`` (their paths those in ``plots_at``, where the folder will be moved, default
    ``plots_dir``, relative to ``json_dir``). Refuses training points, other grids and
    other sampling frames."""
    stores = [s for g in GROUPS for s in held_out.get(g, [])]
    if not stores:
        raise ValueError("no held-out stores given (--interpolation, --extrapolation, --transfer)")
    check_grid(stores, model.grid)
    frame_of(stores, (model.row_dt, model.bin_size))
    check_no_leak(meta, stores)
    groups = {
        g: [evaluate_store(model, s, steps, starts) for s in held_out[g]]
        for g in GROUPS
        if held_out.get(g)
    }
    every = [p for pts in groups.values() for p in pts]
    result: dict[str, Any] = {
        "model": model.kind,
        "history": model.history,
        "horizon": model.horizon,
        "trained_on": meta.get("train_points", []),
        "train_seconds": meta.get("seconds"),
        "overall": combine(every),
        "groups": {
            g: {"overall": combine(p), "points": [public(x) for x in p]} for g, p in groups.items()
        },
        "plots": {},
    }
    result["summary"] = summary_line(result)
    if plots_dir is not None:
        result["plots"] = _plots(
            model.kind,
            groups,
            result,
            Path(plots_dir),
            Path(json_dir or plots_dir),
            Path(plots_at or plots_dir),
        )
    return result


def summary_line(result: dict[str, Any]) -> str:
    """One line: one-step and 50-step velocity errors and the mass error per group."""
    parts = []
    for g, data in result["groups"].items():
        o = data["overall"]
        parts.append(
            f"{g} velocity error one-step {o['one_step']['velocity']:.3f}, "
            f"{o['rollout_at']['50']['steps']}-step {o['rollout_at']['50']['velocity']:.3f}, "
            f"mass within {100 * o['mass']['max_abs_error']:.1f} % over {o['mass']['steps']} steps"
        )
    return f"{result['model']}: " + "; ".join(parts)


def _plots(
    kind: str,
    groups: dict[str, list[dict[str, Any]]],
    result: dict[str, Any],
    pdir: Path,
    base: Path,
    shown: Path,
) -> dict[str, Any]:
    rel = lambda p: os.path.relpath(shown / Path(p).name, base)  # noqa: E731
    series = {f"{g}: all": result["groups"][g]["overall"]["rollout"] for g in groups}
    series.update({f"{g}: {p['name']}": p["rollout"] for g, pts in groups.items() for p in pts})
    out: dict[str, Any] = {
        "rollout": rel(
            plots.rollout_curves(
                series, pdir / "rollout.png", f"{kind}: rollouts on held-out points"
            )
        )
    }
    out["slices"] = {}
    for g, pts in groups.items():
        for i, p in enumerate(pts):
            fields = p["_rollout"]["fields"][:, 0]
            length = fields.shape[1]
            steps = sorted({s for s in (1, 10, 50, length) if s <= length})
            png = plots.density_slices(
                fields, steps, pdir / f"{g}_{i:02d}_slices.png", f"{kind}, {g}: {p['name']}"
            )
            out["slices"][f"{g}: {p['name']}"] = rel(png)
    return out


def validate_dynamics_job(
    model_dir: str | Path,
    interpolation: list[str | Path],
    extrapolation: list[str | Path],
    out: str | Path,
    config: dict[str, Any],
    plots_dir: str | Path | None = None,
    transfer: list[str | Path] | tuple[()] = (),
) -> dict[str, Any]:
    """Validate a saved evolution model on held-out stores (``transfer``: those on unseen
    terrain): JSON at ``out``, plots (default:
    ``plots/{name}`` beside it, as :func:`dozerlab.sweep.dynamics_plots_path`; the folder named
    after the JSON is the model's, built whole: :data:`DYNAMICS_PLOTS`), and an MLflow
    validate_dynamics run. Both outputs are checked before any work; a failure leaves neither."""
    out = Path(out)
    pdir = Path(plots_dir) if plots_dir else out.parent / "plots" / out.stem
    with job_outputs(("--out", out, VALIDATION_JSON), ("--plots", pdir, DYNAMICS_PLOTS)):
        held = load_groups(interpolation, extrapolation, transfer)
        params = held_out_params(model_dir, interpolation, extrapolation, transfer)
        return _validate_dynamics(model_dir, held, params, out, config, pdir)


def _validate_dynamics(
    model_dir: str | Path,
    held: dict[str, list[StoreData]],
    held_params: dict[str, Any],
    out: Path,
    config: dict[str, Any],
    pdir: Path,
) -> dict[str, Any]:
    model, meta = pyfunc.load(model_dir)
    dyn = config["dynamics"]
    params = {
        **held_params,
        "rollout_steps": dyn["rollout_steps"],
        "rollout_starts": dyn["rollout_starts"],
    }
    tags = {"model": model.kind}
    with job_run(
        config,
        run_name("validate", DYNAMICS.family, model.kind),
        rule="validate_dynamics",
        tags=tags,
        params=params,
    ) as run:
        with atomic_output(pdir, DYNAMICS_PLOTS) as tmp:
            tmp.mkdir()
            result = validate_dynamics(
                model,
                meta,
                held,
                dyn["rollout_steps"],
                dyn["rollout_starts"],
                tmp,
                out.parent,
                plots_at=pdir,
            )
        record_validation(run, result, out, VALIDATION_JSON, flat_metrics(result), pdir)
    return result


def flat_metrics(result: dict[str, Any]) -> dict[str, float]:
    """``{group}.{metric}.{field}`` keys of the overall and per-group figures, finite only."""
    out = {}
    for label, o in [("overall", result["overall"])] + [
        (g, d["overall"]) for g, d in result["groups"].items()
    ]:
        for f, value in o["one_step"].items():
            out[f"{label}.one_step.{f}"] = value
        for k, at in o["rollout_at"].items():
            for f in ("velocity", "density"):
                out[f"{label}.rollout_{k}.{f}"] = at[f]
        out[f"{label}.mass.max_abs_error"] = o["mass"]["max_abs_error"]
    return {k: float(v) for k, v in out.items() if v == v and abs(v) != float("inf")}
