"""The scenarios layer's jobs: ``dozerlab bed`` and ``dozerlab trajectory`` (load → compute →
record in MLflow → save), as :mod:`dozerlab.learn.jobs` is for the learning commands."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from dozerlab.runtime import ConfigError, job_outputs
from dozerlab.scenarios.bed import BED_FILE, Bed
from dozerlab.scenarios.build import build_bed
from dozerlab.scenarios.plots import BED_PLOT, TRAJECTORY_PLOT, plot_bed, plot_trajectory
from dozerlab.scenarios.trajectory import TRAJECTORY_FILE, Trajectory, plan_trajectory
from dozerlab.tracking import job_run


def bed_job(
    scenario: str,
    config: dict[str, Any],
    out: str | Path,
    *,
    plot: str | Path | None = None,
    progress: bool = True,
) -> Bed:
    """Build and settle ``scenario``'s bed, save it at ``out`` (.npz) and its plot at ``plot``,
    inside an MLflow run tagged with the scenario (particle count, settle time, kinetic energy
    per particle, wall time and steps as metrics). ``config`` is a validated config."""
    if scenario not in config["scenarios"]:
        raise ConfigError(
            f"--scenario {scenario!r} is not defined (allowed: one of {sorted(config['scenarios'])}, "
            "or a scenario added under the config's scenarios)"
        )
    params = {k: config[k] for k in ("bed", "material", "solver", "seed")}
    params["scenario"] = config["scenarios"][scenario]
    with (
        job_outputs(("--out", out, BED_FILE), ("--plot", plot or None, BED_PLOT)),
        job_run(
            config, f"bed/{scenario}", rule="bed", tags={"scenario": scenario}, params=params
        ) as run,
    ):
        bed = build_bed(scenario, config, progress=progress)
        bed.save(out)
        if plot:
            plot_bed(bed, plot)
        if run is not None:
            run.log_metrics(
                {
                    "particle_count": bed.count,
                    "settle_time": bed.info["time"],
                    "kinetic_energy_per_particle": bed.kinetic_energy_per_particle(),
                    "wall_time": bed.info["wall_time"],
                    "steps": bed.info["steps"],
                }
            )
            if plot:
                run.log_artifact(plot)
    return bed


def trajectory_job(
    bed_path: str | Path,
    speed: float,
    depth: float,
    config: dict[str, Any],
    out: str | Path,
    *,
    plot: str | Path | None = None,
) -> Trajectory:
    """Plan the blade path over the bed at ``bed_path`` for ``speed`` (m/s) and ``depth`` (m);
    save it at ``out`` (CSV) and its plot at ``plot``. ``config`` is a validated config."""
    with job_outputs(("--out", out, TRAJECTORY_FILE), ("--plot", plot or None, TRAJECTORY_PLOT)):
        traj = plan_trajectory(Bed.load(bed_path), speed, depth, config)
        traj.save_csv(out)
        if plot:
            plot_trajectory(traj, plot)
    return traj
