"""The fields layer's job: ``dozerlab simulate`` (load → run → record in MLflow → save).

:func:`simulate` loads the bed and the trajectory, labels the store, runs the stepping loop
(:func:`dozerlab.fields.run.drive`) inside a tracked MLflow run and logs the run's metrics
and plots.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from dozerlab import __version__, tracking
from dozerlab.fields.run import STATE_FILE, VTK_FOLDER, drive, load_inputs
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import FIELD_STORE, open_store
from dozerlab.runtime import OutputKind, freeze_heap, job_outputs
from dozerlab.sweep import fmt_number, point_name

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Jitter:
    """A twin run's start: every grain of the bed moved ``metres`` (m) in a direction drawn
    from ``seed`` (:meth:`dozerlab.scenarios.bed.Bed.jittered`)."""

    metres: float
    seed: int


def simulate(
    bed_path: str | Path,
    trajectory_path: str | Path,
    config: dict[str, Any],
    out: str | Path,
    *,
    scenario: str | None = None,
    speed: float | None = None,
    depth: float | None = None,
    vtk_dir: str | Path | None = None,
    plots_dir: str | Path | None = None,
    log_every: int | None = None,
    state_out: str | Path | None = None,
    jitter: Jitter | None = None,
) -> dict[str, float]:
    """Run NDEM along a trajectory and write the field store ``out``; return the run's metrics.

    ``config`` is a validated config. ``scenario``/``speed``/``depth`` label the store (the
    workflow passes its sweep point's; defaults: the bed's scenario, the trajectory's speed, no
    depth). File names are never parsed for them. VTK snapshots go to ``vtk_dir`` every
    ``sampling.vtk_every`` steps (when both are set); slice and force plots of the store to
    ``plots_dir`` and to MLflow; the final particle state to ``state_out`` (a bed file,
    ``Bed.load`` reads it) when given. With ``jitter``, the run is a twin: it starts from the
    bed with every grain moved (:class:`Jitter`; the store's ``jitter_m`` and ``jitter_seed``
    attributes say so; the MLflow run is ``simulate/twin/…``, rule ``twin``). The store's
    ``wall_time_s`` attribute is the stepping loop's wall time (s). Raises :class:`DozerlabError` when the
    simulation diverges, leaving no store. Every output is checked before the run
    (:func:`~dozerlab.runtime.job_outputs`), and a run that fails leaves none of them.
    """
    plots: OutputKind | None = None
    if plots_dir is not None:  # matplotlib is imported only for plots
        from dozerlab.fields.plots import FIELD_PLOTS

        plots = FIELD_PLOTS
    with job_outputs(
        ("--out", out, FIELD_STORE),
        ("--state", state_out, STATE_FILE),
        ("--vtk-dir", vtk_dir if config["sampling"]["vtk_every"] > 0 else None, VTK_FOLDER),
        ("--plots", plots_dir, plots),
    ):
        return _simulate(
            bed_path,
            trajectory_path,
            config,
            Path(out),
            scenario=scenario,
            speed=speed,
            depth=depth,
            vtk_dir=vtk_dir,
            plots_dir=plots_dir,
            log_every=log_every,
            state_out=state_out,
            jitter=jitter,
        )


def _simulate(
    bed_path: str | Path,
    trajectory_path: str | Path,
    config: dict[str, Any],
    out: Path,
    *,
    scenario: str | None,
    speed: float | None,
    depth: float | None,
    vtk_dir: str | Path | None,
    plots_dir: str | Path | None,
    log_every: int | None,
    state_out: str | Path | None,
    jitter: Jitter | None,
) -> dict[str, float]:
    bed, traj, dt = load_inputs(bed_path, trajectory_path, config)
    if jitter is not None:
        bed = bed.jittered(jitter.metres, jitter.seed)
    scenario = scenario or bed.scenario
    speed = speed if speed is not None else round(traj.speed, 6)
    s = config["sampling"]
    grid = SamplingGrid.from_config(config)
    attrs = {
        "scenario": scenario,
        "speed": speed,
        "depth": depth,
        **grid.attrs(),
        "dt": dt,
        "iterations": int(config["solver"]["iterations"]),
        "active_zone": dict(config["solver"]["active_zone"]),
        "sample_every": int(s["every"]),
        "particle_count": bed.count,
        "seed": int(config["seed"]),
        "dozerlab_version": __version__,
        "config": json.dumps(config, sort_keys=True),
    }
    if jitter is not None:
        attrs |= {"jitter_m": jitter.metres, "jitter_seed": jitter.seed}
    params = {k: config[k] for k in ("solver", "material", "sampling", "blade")}
    point = point_name(speed, depth) if depth is not None else f"speed~{fmt_number(speed)}"
    rule = "simulate" if jitter is None else "twin"
    name = tracking.run_name("simulate", None if jitter is None else "twin", scenario, point)
    freeze_heap()  # as the reduce job does: the two loops are timed against each other
    with tracking.job_run(
        config,
        name,
        rule=rule,
        # a twin's draws (reduced.twin.draws) share its name: their seeds tell them apart
        tags={"scenario": scenario, "speed": speed, "depth": depth}
        | ({} if jitter is None else {"jitter_seed": jitter.seed}),
        params=params,
    ) as run:
        stats = drive(bed, traj, config, grid, attrs, out, vtk_dir, log_every, state_out)
        metrics = stats.metrics(bed.count)
        log.info("run done: %s", ", ".join(f"{k}={v:.4g}" for k, v in metrics.items()))
        _plots_and_metrics(out, plots_dir, metrics, run)
    return metrics


def _plots_and_metrics(
    out: Path, plots_dir: str | Path | None, metrics: dict[str, float], run: tracking.JobRun | None
) -> None:
    """Log the metrics to the MLflow ``run``; with ``plots_dir``, plot the store there and log
    the plots too. Plots are drawn only on request: the report draws its own from the store."""
    if run is not None:
        run.log_metrics(metrics)
    if plots_dir is None:
        return
    from dozerlab.fields.plots import plot_run

    plot_run(open_store(out), Path(plots_dir), animation=False)
    if run is not None:
        run.log_artifacts(plots_dir, artifact_path="plots")
