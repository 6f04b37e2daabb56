"""The reduce and compare-reduced jobs: models loaded, runs tracked in MLflow, results written."""

from __future__ import annotations

import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.runtime import (
    DozerlabError,
    OutputKind,
    atomic_output,
    check_name,
    freeze_heap,
    job_outputs,
    json_with,
    marked_folder,
)

log = logging.getLogger(__name__)

#: Per-role summary of the comparison: how each figure is aggregated over the points.
#: What ``compare-reduced`` writes: the reduced runs measured against NDEM.
COMPARISON_JSON = OutputKind(
    "a dozerlab reduced-run comparison JSON",
    json_with(("dynamics_model", "points", "overall")),
    "compare-reduced",
)
#: ``compare-reduced``'s plots and animations: a folder built whole.
COMPARISON_PLOTS = marked_folder("a dozerlab folder of reduced-run comparisons", "compare-plots")
#: The figures measured against NDEM (dozerlab.reduce.compare.FIGURES), the twin's and the skills:
#: means over the points.
_FIGURES = (
    "height_accuracy",
    "surface_accuracy",
    "force_x_rel_rmse",
    "force_lp_rel_rmse",
    "force_mean_rel_err",
    "velocity_rel_l2",
    "density_rel_l2",
    "final_emd_m",
)
#: The smoothed surface's error and excess by region (dozerlab.reduce.compare.surface_errors),
#: the run's and the twin's: means over the points.
_REGIONS = tuple(
    f"{who}surface_{what}_{r}"
    for who in ("", "twin_")
    for what in ("error", "excess")
    for r in ("swath", "beside", "ahead")
)
#: Those measured against NDEM's expected run too (dozerlab.reduce.compare.EXPECTED_FIGURES).
_EXPECTED = ("surface_accuracy", "force_lp_rel_rmse")
AGGREGATE: dict[str, Callable[[list[float]], Any]] = {
    **dict.fromkeys(_FIGURES, np.mean),
    **{f"twin_{k}": np.mean for k in _FIGURES},
    **{f"{k}_skill": np.mean for k in _FIGURES},
    **dict.fromkeys(_REGIONS, np.mean),
    **{f"{who}{k}": np.mean for k in _EXPECTED for who in ("expected_", "ndem_expected_")},
    **{f"expected_{k}_skill": np.mean for k in _EXPECTED},
    "max_overlap_loop": np.max,
    "max_overlap_final": np.max,
    "body_depth_final_m": np.max,
    "left_bed": np.sum,
    "loop_speedup": np.min,
    "job_speedup": np.min,
}


def reduce_job(
    bed: str | Path,
    trajectory: str | Path,
    config: dict[str, Any],
    dynamics: str | Path,
    force_model: str | Path,
    out: str | Path,
    state: str | Path,
    *,
    ndem_store: str | Path | None = None,
    scenario: str | None = None,
    speed: float | None = None,
    depth: float | None = None,
) -> dict[str, float]:
    """Load the models and run :func:`dozerlab.reduce.run.reduce_run` as a tracked MLflow run
    (the heap frozen once the models are loaded, :func:`dozerlab.runtime.freeze_heap`)."""
    from dozerlab.fields.sampling import SamplingGrid
    from dozerlab.reduce.models import ForcePredictor, load_field_model
    from dozerlab.reduce.run import REDUCED_STATE, REDUCED_STORE

    with job_outputs(("--out", out, REDUCED_STORE), ("--state", state, REDUCED_STATE)):
        grid = SamplingGrid.from_config(config)
        field_model = load_field_model(dynamics, grid.bins, ndem_store)
        forces = ForcePredictor(force_model)
        freeze_heap()
        target = _Target(bed, trajectory, out, state, scenario, speed, depth)
        return _tracked_reduce("reduce", target, config, field_model, forces)


def reduce_points_job(
    results: str | Path,
    dynamics_model: str,
    points: list[P.SweepPoint],
    config: dict[str, Any],
    dynamics: str | Path,
    force_model: str | Path,
    rule: str = "reduce",
) -> list[dict[str, float]]:
    """Run several sweep points with one pair of models in one process: the workflow's rules
    ``reduce`` (a model's runs of the held-out points) and ``reduce_training_points`` (its runs
    of the training points, which its loop's force model learns from). A one-point reduce job
    spends about 3 s outside its loop (imports, models, compiled kernels) for 3–5 s of loop on the
    default sweep's points; here that is paid once.

    Inputs and outputs are the workflow's paths under ``results``: each point's bed, trajectory
    and NDEM store (replay's fields), its reduced store and state as
    ``results/reduced/{dynamics_model}/…`` (:func:`dozerlab.sweep.reduced_path`). Each point is
    its own MLflow run (tag ``rule``: ``rule``). Returns the points' metrics.
    Every point's outputs are checked before the first run; a failure leaves none of them.
    """
    from dozerlab.fields.sampling import SamplingGrid
    from dozerlab.reduce.models import REPLAY, ForcePredictor, load_field_model
    from dozerlab.reduce.run import REDUCED_STATE, REDUCED_STORE

    check_name(dynamics_model, "--dynamics-model")
    outputs = [
        (
            f"--points {p.scenario}/{p.name} ({ext})",
            P.reduced_path(results, dynamics_model, p, ext),
            kind,
        )
        for p in points
        for ext, kind in (("zarr", REDUCED_STORE), ("npz", REDUCED_STATE))
    ]
    with job_outputs(*outputs):
        grid = SamplingGrid.from_config(config)
        forces = ForcePredictor(force_model)
        # replay's fields are each point's own NDEM run; a learned model is loaded once
        shared = None if str(dynamics) == REPLAY else load_field_model(dynamics, grid.bins)
        freeze_heap()
        metrics = []
        for point in points:
            field_model = shared or load_field_model(
                REPLAY, grid.bins, P.field_path(results, point)
            )
            target = _Target(
                P.bed_path(results, point.scenario),
                P.trajectory_path(results, point),
                P.reduced_path(results, dynamics_model, point),
                P.reduced_path(results, dynamics_model, point, "npz"),
                point.scenario,
                point.speed,
                point.depth,
            )
            metrics.append(_tracked_reduce(rule, target, config, field_model, forces))
        return metrics


@dataclass(frozen=True)
class _Target:
    """One reduced run's inputs (bed, trajectory), outputs (store, final state) and labels
    (speed in m/s, depth in m; None when not given)."""

    bed: str | Path
    trajectory: str | Path
    out: str | Path
    state: str | Path
    scenario: str | None
    speed: float | None
    depth: float | None


def _tracked_reduce(
    rule: str, target: _Target, config: dict[str, Any], field_model: Any, forces: Any
) -> dict[str, float]:
    """:func:`dozerlab.reduce.run.reduce_run` of loaded models as an MLflow run of ``rule``."""
    from dozerlab import tracking
    from dozerlab.reduce.run import reduce_run
    from dozerlab.reduce.simulation import ReducedSettings

    scenario, speed, depth = target.scenario, target.speed, target.depth
    point = P.point_name(speed, depth) if speed is not None and depth is not None else None
    name = tracking.run_name("reduce", field_model.name, scenario, point)
    # the config's reduced section names the loops its crest and steering apply to; the tags
    # say what this loop ran with
    loop = ReducedSettings.from_config(config).for_model(field_model.name)
    tags = {
        "scenario": scenario,
        "speed": speed,
        "depth": depth,
        "model": field_model.name,
        "force_model": forces.name,
        "crest_bins": loop.crest_bins,
        "density_steered": loop.steers(field_model.name),
    }
    with tracking.tracked_run(
        name,
        rule=rule,
        tags={k: v for k, v in tags.items() if v is not None},
        params={"reduced": config["reduced"], "solver": config["solver"]},
        experiment=config["mlflow"]["experiment"],
    ) as run:
        metrics = reduce_run(
            target.bed,
            target.trajectory,
            config,
            field_model,
            forces,
            target.out,
            target.state,
            scenario=scenario,
            speed=speed,
            depth=depth,
        )
        if run is not None:
            run.log_metrics(metrics)
    return metrics


def _summary(points: list[dict[str, Any]]) -> dict[str, float]:
    out = {}
    for key, agg in AGGREGATE.items():
        values = [p[key] for p in points if p.get(key) is not None and np.isfinite(p[key])]
        if values:
            out[key] = float(agg(values))
    return out


def compare_job(
    dynamics_model: str,
    config: dict[str, Any],
    results: str | Path,
    out: str | Path,
    plots: str | Path,
    *,
    animation: bool = True,
) -> dict[str, Any]:
    """Compare the reduced runs of every held-out point with NDEM; write ``out`` (JSON) and plots.

    The JSON holds ``points`` (one entry per point: its role, metrics and which targets it
    meets, ``reduced.targets``), ``overall`` (per role and ``all``: means of the errors, worst
    overlaps, least speed-ups), ``targets`` and, with transfer points and twins, ``transfer``
    (:func:`dozerlab.reduce.compare.transfer_gap`: the surface skill on unseen terrain against
    the seen shapes'). With ``reduced.twin.enabled`` each point's twin
    NDEM run (``results/twins/…``) is measured too: the twin's figures and the skills
    (:func:`dozerlab.reduce.compare.skills`), and with ``reduced.twin.draws`` > 1 every draw,
    each run also against NDEM's expected run (their mean) beside NDEM's own run. Logged as an
    MLflow run with the plots.
    """
    check_name(dynamics_model, "--dynamics-model")
    with job_outputs(("--out", out, COMPARISON_JSON), ("--plots", plots, COMPARISON_PLOTS)):
        return _compare(dynamics_model, config, results, Path(out), Path(plots), animation)


def _compare(
    dynamics_model: str,
    config: dict[str, Any],
    results: str | Path,
    out: Path,
    plots: Path,
    animation: bool,
) -> dict[str, Any]:
    from dozerlab import tracking
    from dozerlab.fields.store import open_store
    from dozerlab.reduce import plots as rp
    from dozerlab.reduce.compare import (
        compare_point,
        job_seconds,
        job_shares,
        targets_met,
        transfer_gap,
    )

    held_out = [p for p in P.sweep_points(config) if p.role != "train"]
    if not held_out:
        raise DozerlabError("the config's sweep has no held-out points to compare on")
    targets = config["reduced"]["targets"]
    twins = bool(config["reduced"]["twin"]["enabled"])
    n_draws = int(config["reduced"]["twin"]["draws"])
    entries: list[dict[str, Any]] = []
    # one reduce job ran every held-out point (rule reduce): each point's share of it
    shares = job_shares(
        job_seconds(P.reduce_benchmark_path(results, dynamics_model)),
        [
            open_store(P.reduced_path(results, dynamics_model, p)).attrs.get("wall_time_s")
            for p in held_out
        ],
    )
    with tracking.tracked_run(
        tracking.run_name("compare", dynamics_model),
        rule="compare_reduced",
        tags={"model": dynamics_model},
        params={"reduced": config["reduced"]},
        experiment=config["mlflow"]["experiment"],
    ) as run:
        with atomic_output(plots, COMPARISON_PLOTS) as tmp_plots:
            tmp_plots.mkdir(parents=True)
            for point, share in zip(held_out, shares, strict=True):
                ndem_store = P.field_path(results, point)
                reduced_store = P.reduced_path(results, dynamics_model, point)
                twin, *draws = P.twin_draws(results, point, n_draws)
                metrics, series = compare_point(
                    ndem_store,
                    reduced_store,
                    P.bed_path(results, point.scenario),
                    P.state_path(results, point),
                    P.reduced_path(results, dynamics_model, point, "npz"),
                    config,
                    ndem_benchmark=P.simulate_benchmark_path(results, point),
                    reduced_job_s=share,
                    twin=twin if twins else None,
                    draws=draws if twins else (),
                )
                stem = f"{point.scenario}_{point.name}"
                files = [
                    rp.plot_force(series, metrics, tmp_plots / f"{stem}_force.png"),
                    rp.plot_errors(series, metrics, tmp_plots / f"{stem}_fields.png"),
                    rp.plot_height(series, metrics, tmp_plots / f"{stem}_height.png"),
                    rp.plot_surface(series, metrics, tmp_plots / f"{stem}_surface.png"),
                ]
                if animation:
                    files.append(
                        rp.animate_pair(
                            open_store(ndem_store),
                            open_store(reduced_store),
                            tmp_plots / f"{stem}.gif",
                        )
                    )
                entries.append(
                    {
                        "role": point.role,
                        **metrics,
                        # replay (reduce.models.REPLAY, which imports torch): NDEM's own fields
                        "targets_met": targets_met(
                            metrics, targets, replay=dynamics_model == "replay"
                        ),
                        "plots": [f.name for f in files],
                    }
                )
                log.info("%s %s: %s", point.scenario, point.name, metrics)
        overall = {
            role: _summary([e for e in entries if e["role"] == role]) for role in P.HELD_OUT_ROLES
        }
        overall["all"] = _summary(entries)
        summary = {
            "dynamics_model": dynamics_model,
            "targets": targets,
            "points": entries,
            "overall": {k: v for k, v in overall.items() if v},
        }
        if (gap := transfer_gap(entries, targets["transfer_skill_gap"])) is not None:
            summary["transfer"] = gap
        with atomic_output(out, COMPARISON_JSON) as tmp:
            tmp.write_text(json.dumps(summary, indent=1, allow_nan=True))
        if run is not None:
            for role, agg in summary["overall"].items():
                run.log_metrics({f"{role}.{k}": v for k, v in agg.items()})
            if gap is not None:
                run.log_metrics(
                    {f"transfer.{k}": float(v) for k, v in gap.items() if k != "target"}
                )
            run.log_artifacts(plots, artifact_path="plots")
            run.log_artifact(out)
    return summary
