"""``dozerlab simulate``: drive the blade along a trajectory through a bed and record the fields.

Each solver step the blade gets the trajectory's velocity for that step; every
``sampling.every``-th step the fields in front of the blade, the blade force and torque (about
the tip), its velocity and tip position are appended to the field store, which is written while
the run goes (one chunk in memory) and appears only when the run succeeds.
"""

from __future__ import annotations

import json
import logging
import tempfile
import time as wallclock
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from dozerlab import __version__
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import FIELD_STORE, FieldStoreWriter, open_store
from dozerlab.runtime import (
    DozerlabError,
    OutputKind,
    atomic_output,
    check_output,
    text_starts_with,
)

log = logging.getLogger(__name__)
#: The particle snapshots of ``--vtk-dir`` (meshio's VTK XML unstructured grids).
VTK_FILE = OutputKind(
    "a VTK unstructured grid (.vtu)", text_starts_with('<VTKFile type="UnstructuredGrid"')
)


@dataclass
class RunStats:
    """Solver statistics gathered over a run (times in s, wall clock)."""

    steps: int = 0
    wall_time: float = 0.0
    step_time: float = 0.0
    sample_time: float = 0.0
    contact_iterations: float = 0.0
    forces: list[np.ndarray] = field(default_factory=list)

    def metrics(self, particles: int) -> dict[str, float]:
        """The MLflow metrics of the run."""
        f = np.array(self.forces).reshape(-1, 3)
        mag = np.linalg.norm(f, axis=1)
        out = {
            "wall_time_s": self.wall_time,
            "steps_per_s": self.steps / self.step_time if self.step_time > 0 else 0.0,
            "contact_iterations_per_s": self.contact_iterations / self.step_time
            if self.step_time > 0
            else 0.0,
            "sampling_fraction_of_step": self.sample_time / self.step_time
            if self.step_time > 0
            else 0.0,
            "particle_count": float(particles),
        }
        if len(f):
            out |= {
                "force_x_mean": float(f[:, 0].mean()),
                "force_x_peak": float(np.abs(f[:, 0]).max()),
                "force_mag_mean": float(mag.mean()),
                "force_mag_peak": float(mag.max()),
            }
        return out


def _write_vtk(vtk_dir: Path, step: int, world: Any) -> None:
    import meshio

    pos = np.asarray(world.positions)
    mesh = meshio.Mesh(
        points=pos,
        cells=[("vertex", np.arange(len(pos)).reshape(-1, 1))],
        point_data={"radius": np.asarray(world.radii), "velocity": np.asarray(world.velocities)},
    )
    with atomic_output(vtk_dir / f"particles_{step:06d}.vtu", VTK_FILE) as tmp:
        meshio.write(tmp, mesh, file_format="vtu")


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
) -> dict[str, float]:
    """Run NDEM along a trajectory and write the field store ``out``; return the run's metrics.

    ``config`` is a validated config. ``scenario``/``speed``/``depth`` label the store (the
    workflow passes its sweep point's; defaults: the bed's scenario, the trajectory's speed, no
    depth). File names are never parsed for them. VTK snapshots go to ``vtk_dir`` every ``sampling.vtk_every`` steps (when both are set);
    slice and force plots of the store to ``plots_dir`` and to MLflow. Raises :class:`DozerlabError` when the
    simulation diverges, leaving no store.
    """
    from dozerlab import tracking
    from dozerlab.scenarios.bed import Bed
    from dozerlab.scenarios.trajectory import Trajectory

    check_output(out, FIELD_STORE)  # before the run, not after it
    bed = Bed.load(bed_path)
    traj = Trajectory.load_csv(trajectory_path)
    dt = float(config["solver"]["dt"])
    if not np.isclose(traj.dt, dt, rtol=1e-6):
        raise ValueError(
            f"trajectory time step {traj.dt} s differs from solver.dt {dt} s; plan it with the same config"
        )
    scenario = scenario or bed.scenario
    speed = speed if speed is not None else round(traj.speed, 6)
    s = config["sampling"]
    grid = SamplingGrid.from_config(config)
    attrs = {
        "scenario": scenario,
        "speed": speed,
        "depth": depth,
        "bins": list(grid.bins),
        "bin_size": list(grid.bin_size),
        "dt": dt,
        "iterations": int(config["solver"]["iterations"]),
        "sample_every": int(s["every"]),
        "particle_count": bed.count,
        "seed": int(config["seed"]),
        "dozerlab_version": __version__,
        "config": json.dumps(config, sort_keys=True),
    }
    params = {k: config[k] for k in ("solver", "material", "sampling", "blade")}
    name = f"simulate {scenario} v={speed} d={depth}"
    with tracking.tracked_run(
        name,
        rule="simulate",
        tags={"scenario": scenario, "speed": speed, "depth": depth},
        params=params,
    ) as run:
        stats = _drive(bed, traj, config, grid, attrs, Path(out), vtk_dir, log_every)
        metrics = stats.metrics(bed.count)
        log.info("run done: %s", ", ".join(f"{k}={v:.4g}" for k, v in metrics.items()))
        _plots_and_metrics(Path(out), plots_dir, metrics, run)
    return metrics


def _drive(bed, traj, config, grid, attrs, out, vtk_dir, log_every):  # type: ignore[no-untyped-def]
    """The stepping loop: move the blade, step, sample, append; returns the :class:`RunStats`."""
    from dozerlab.ndem import DivergenceError
    from dozerlab.scenarios.blade import BladeGeometry, add_blade
    from dozerlab.scenarios.build import make_world

    s = config["sampling"]
    every, vtk_every = int(s["every"]), int(s["vtk_every"])
    iterations = int(config["solver"]["iterations"])
    world, _handles = make_world(bed, config)
    blade = add_blade(world, traj.position[0], config)
    # the blade only translates, so (centre − tip) is constant: torque about the tip as it was
    # during the step = torque about the centre + (centre − tip) × force
    centre_minus_tip = BladeGeometry.from_config(config).tip_offset
    vtk = Path(vtk_dir) if vtk_dir is not None and vtk_every > 0 else None
    if vtk is not None:
        vtk.mkdir(parents=True, exist_ok=True)
    log_every = log_every or max(1, traj.steps // 20)
    stats = RunStats()
    x, y, z = grid.centres()
    start = wallclock.perf_counter()
    window: list[tuple[float, int, float, float]] = []
    with FieldStoreWriter(
        out, x=x, y=y, z=z, attrs=attrs, chunk_steps=int(s["chunk_steps"])
    ) as writer:
        for i in tqdm(
            range(traj.steps), desc=f"simulate {attrs['scenario']}", unit="step", disable=None
        ):
            world.set_velocity(blade, traj.velocity[i])
            t0 = wallclock.perf_counter()
            try:
                st = world.step()
            except DivergenceError as exc:
                raise DozerlabError(
                    f"simulation diverged at step {i} (t = {traj.time[i]:.4f} s): {exc}; "
                    "try a smaller solver.dt or more solver.iterations"
                ) from exc
            dt_wall = wallclock.perf_counter() - t0
            stats.steps += 1
            stats.step_time += dt_wall
            stats.contact_iterations += st.contacts * iterations
            window.append((dt_wall, st.contacts, st.residual, st.max_overlap))
            if (i + 1) % every == 0:
                t1 = wallclock.perf_counter()
                tip = traj.position[i + 1]
                vel, rho = grid.sample(
                    world.positions, world.velocities, world.radii, world.masses, tip
                )
                stats.sample_time += wallclock.perf_counter() - t1
                force = np.asarray(world.force_on(blade), dtype=np.float64)
                stats.forces.append(force)
                torque = world.torque_on(blade) + np.cross(centre_minus_tip, force)
                writer.append(
                    float(traj.time[i + 1]), vel, rho, force, torque, traj.velocity[i], tip
                )
            if vtk is not None and (i + 1) % vtk_every == 0:
                _write_vtk(vtk, i + 1, world)
            if (i + 1) % log_every == 0 or i + 1 == traj.steps:
                w = np.array(window)
                log.info(
                    "step %d/%d t=%.3f s: contacts %.0f, residual %.3g m/s, max overlap %.3g m, %.1f ms/step",
                    i + 1,
                    traj.steps,
                    traj.time[i + 1],
                    w[:, 1].mean(),
                    w[:, 2].mean(),
                    w[:, 3].max(),
                    1e3 * w[:, 0].mean(),
                )
                window.clear()
    stats.wall_time = wallclock.perf_counter() - start
    return stats


def _plots_and_metrics(
    out: Path, plots_dir: str | Path | None, metrics: dict[str, float], run: Any
) -> None:
    """Write the store's plots to ``plots_dir`` and log them and the metrics to the MLflow ``run``."""
    from dozerlab.fields.plots import plot_run

    if run is None and plots_dir is None:
        return
    ds = open_store(out)
    with tempfile.TemporaryDirectory() as tmp:
        target = Path(plots_dir) if plots_dir is not None else Path(tmp)
        plot_run(ds, target, animation=False)
        if run is not None:
            import mlflow

            mlflow.log_metrics(metrics)
            mlflow.log_artifacts(str(target), artifact_path="plots")
