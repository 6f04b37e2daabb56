"""Helpers the tests share: synthetic beds and field stores built without physics (fast).

Import them from here (``from tests.helpers import …``); conftest files hold only fixtures.
"""

from __future__ import annotations

import json
import re
import shutil
import sqlite3
from collections.abc import Callable
from contextlib import closing
from pathlib import Path
from typing import Any

import numpy as np

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.fields.store import write_store
from dozerlab.learn.data import StoreData, from_arrays
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.trajectory import Trajectory, plan_trajectory

#: A small sweep of one scenario: two training speeds, one interpolation and one
#: extrapolation point, one model.
SMALL_SWEEP = {
    "sweep": {
        "scenarios": ["hill"],
        "speeds": [0.5, 1.0],
        "depths": [0.1],
        "interpolation": [{"scenario": "hill", "speed": 0.75, "depth": 0.1}],
        "extrapolation": [{"scenario": "hill", "speed": 2.0, "depth": 0.1}],
    },
    "learn": {"models": ["linear"]},
}

#: The grid of the synthetic field stores, (Nx, Ny, Nz).
GRID = (8, 6, 4)


def copy_mlflow_store(template: Path, directory: Path) -> str:
    """A fresh SQLite MLflow store ``directory/mlflow.db`` copied from ``template``, an empty
    store MLflow made (creating its tables takes seconds, a copy milliseconds); its Default
    experiment keeps its artifacts in ``directory/mlruns/0``, as in a store made there. Returns
    the store's URI."""
    db = directory / "mlflow.db"
    shutil.copyfile(template, db)
    with closing(sqlite3.connect(db)) as con, con:
        con.execute(
            "UPDATE experiments SET artifact_location = ? WHERE experiment_id = 0",
            (str(directory / "mlruns" / "0"),),
        )
    return f"sqlite:///{db}"


def lattice_bed(
    scenario: str,
    profile: Callable[[float], float],
    *,
    length: float,
    width: float,
    radius: float,
    seed: int = 0,
    jitter: float = 0.0,
    material: dict[str, float] | None = None,
) -> Bed:
    """A bed of equal spheres stacked in columns up to ``profile(x)`` (m), on a cubic lattice of
    touching spheres over x ∈ [0, length], y ∈ [-width/2, width/2]; each sphere is shifted along
    x by up to ``jitter`` radii (uniform, seeded). No physics, so it is built at once."""
    rng = np.random.default_rng(seed)
    points = []
    for x in np.arange(radius, length - radius + 1e-9, 2 * radius):
        for y in np.arange(-width / 2 + radius, width / 2 - radius + 1e-9, 2 * radius):
            for z in np.arange(radius, max(profile(x) - radius, radius) + 1e-9, 2 * radius):
                points.append((x + rng.uniform(-jitter, jitter) * radius, y, z))
    pos = np.array(points)
    n = len(pos)
    material = dict(material or {"density": 2600.0})
    radii = np.full(n, radius)
    return Bed(
        scenario,
        length,
        width,
        pos,
        radii,
        material["density"] * 4.0 / 3.0 * np.pi * radii**3,
        np.zeros((n, 3)),
        np.zeros((n, 3)),
        material,
        seed,
    )


#: A run of a few seconds: a 0.8 m bed of 234 grains (:func:`tiny_bed`), 6×5×4 bins.
TINY_RUN = {
    "solver": {"dt": 0.01, "iterations": 30},
    "material": {"youngs_modulus": 0.0},
    "bed": {"length": 0.8, "width": 0.36, "radius": 0.03},
    "scenarios": {"hill": {"goal_height": 0.08}},
    "blade": {"width": 0.3, "height": 0.2, "thickness": 0.03, "start_gap": 0.05},
    "trajectory": {"subdivisions": [40, 4], "approach_steps": 3},
    "sampling": {
        "length": 0.3,
        "below_edge": 0.05,
        "bins": [6, 5, 4],
        "every": 2,
        "chunk_steps": 8,
        "vtk_every": 10,
    },
}


def tiny_bed(config: dict[str, Any]) -> Bed:
    """The bed of :data:`TINY_RUN`: a lattice of touching spheres 0.18 m high (234 of them)."""
    return lattice_bed(
        "hill",
        lambda x: 0.18,
        length=0.8,
        width=0.36,
        radius=0.03,
        seed=1,
        material=dict(config["material"]),
    )


def write_tiny_run(
    directory: Path, trajectory_name: str = "speed~0.5_depth~0.06.csv"
) -> tuple[dict[str, Any], Bed, Trajectory]:
    """Save the tiny run's bed (``bed.npz``) and a 0.5 m/s, 0.06 m deep trajectory
    (``trajectory_name``) in ``directory``; return the validated config, the bed and the path."""
    config = load_config(TINY_RUN)
    bed = tiny_bed(config)
    bed.save(directory / "bed.npz")
    traj = plan_trajectory(bed, 0.5, 0.06, config)
    traj.save_csv(directory / trajectory_name)
    return config, bed, traj


def synthetic(
    speed: float,
    depth: float,
    *,
    steps: int = 100,
    grid=GRID,
    seed: int = 0,
    scenario: str = "hill",
) -> dict[str, np.ndarray]:
    """Fields of a pile whose fill grows with the depth; force = f(mass in front, speed)."""
    rng = np.random.default_rng(seed)
    t = np.arange(steps) * 0.02
    fill = np.clip(
        depth * 8 + 0.3 * np.sin(t * 3)[:, None, None, None] + rng.normal(0, 0.1, (steps, *grid)),
        0,
        None,
    )
    density = (1500 * fill).astype(np.float32)
    vb = np.zeros((steps, 3), np.float32)
    vb[:, 0] = speed * (1 + 0.1 * np.sin(t * 5))
    velocity = (0.8 * vb[:, None, None, None, :] * (fill[..., None] > 0)).astype(np.float32)
    velocity += rng.normal(0, 0.01, velocity.shape).astype(np.float32)
    mass = density.sum(axis=(1, 2, 3)) * 1e-3
    fx = -mass * (1 + vb[:, 0])  # the material pushes the blade back (−x)
    force = np.stack([fx, 0.1 * fx, 0.5 * mass], axis=1)
    torque = np.stack([0.2 * mass, -0.3 * fx, 0.05 * fx], axis=1)
    return {
        "time": t,
        "velocity": velocity,
        "density": density,
        "force": force,
        "torque": torque,
        "blade_velocity": vb,
        "blade_position": np.cumsum(vb, axis=0) * 0.02,
        "point": {"scenario": scenario, "speed": speed, "depth": depth},
    }


def in_memory(speed: float, depth: float, **kw) -> StoreData:
    a = synthetic(speed, depth, **kw)
    return from_arrays(
        a["velocity"],
        a["density"],
        a["blade_velocity"],
        a["force"],
        a["torque"],
        time=a["time"],
        point=a["point"],
    )


def write(path: Path, speed: float, depth: float, attrs: dict | None = None, **kw) -> Path:
    """A field store written with the fields layer's writer (``attrs`` added to its own)."""
    a = synthetic(speed, depth, **kw)
    grid = a["density"].shape[1:]
    attrs = {
        **a["point"],
        "bins": list(grid),
        "bin_size": [0.1, 0.1, 0.1],
        "dt": 0.02,
        "iterations": 10,
        "sample_every": 1,
        "particle_count": 100,
        "seed": 0,
        "dozerlab_version": "test",
        "config": json.dumps({}),
        **(attrs or {}),
    }
    coords = {k: (np.arange(n) + 0.5) * 0.1 for k, n in zip("xyz", grid, strict=False)}
    series = {
        k: a[k]
        for k in (
            "time",
            "velocity",
            "density",
            "force",
            "torque",
            "blade_velocity",
            "blade_position",
        )
    }
    return write_store(path, **coords, **series, attrs=attrs, chunk_steps=32)


# The report's material: what the workflow's jobs leave under results/, written without them.


def png_file(path: Path, title: str) -> Path:
    """A small PNG of an empty plot titled ``title`` at ``path`` (folders made)."""
    from matplotlib.figure import Figure

    fig = Figure(figsize=(3, 2))
    fig.subplots().set_title(title)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, format="png")
    return path


def report_store(path: Path, point: Any, steps: int = 6, wall_time: float | None = None) -> None:
    """A field store of ``point`` (a :class:`dozerlab.sweep.SweepPoint`): 4×3×3 bins, ``steps``
    rows 0.01 s apart from t = 0.01 s, sample_every 2, 321 particles, force (1000, 0, 300) N
    except the last row's 2000 N along x."""
    rng = np.random.default_rng(0)
    x, y, z = np.linspace(0.05, 0.55, 4), np.linspace(-0.3, 0.3, 3), np.linspace(-0.05, 0.25, 3)
    t = 0.01 * np.arange(1, steps + 1)
    force = np.tile([1000.0, 0.0, 300.0], (steps, 1))
    force[-1, 0] = 2000.0
    write_store(
        path,
        x=x,
        y=y,
        z=z,
        time=t,
        velocity=rng.normal(size=(steps, 4, 3, 3, 3)).astype(np.float32),
        density=rng.uniform(0, 1600, size=(steps, 4, 3, 3)).astype(np.float32),
        force=force,
        torque=np.zeros((steps, 3)),
        blade_velocity=np.tile([point.speed, 0, 0], (steps, 1)),
        blade_position=np.zeros((steps, 3)),
        attrs={
            "scenario": point.scenario,
            "speed": point.speed,
            "depth": point.depth,
            "bins": [4, 3, 3],
            "bin_size": [0.15, 0.2, 0.1],
            "dt": 0.01,
            "iterations": 10,
            "sample_every": 2,
            "particle_count": 321,
            "seed": 1,
            "dozerlab_version": "test",
            "config": "{}",
        }
        | ({"wall_time_s": wall_time} if wall_time is not None else {}),
    )


def report_bed(results: Path) -> None:
    """A 1 m × 0.5 m hill bed of 40 grains at its place under ``results``."""
    rng = np.random.default_rng(1)
    n = 40
    pos = np.column_stack(
        [rng.uniform(0.05, 0.95, n), rng.uniform(-0.2, 0.2, n), rng.uniform(0.05, 0.3, n)]
    )
    zeros = np.zeros((n, 3))
    bed = Bed("hill", 1.0, 0.5, pos, np.full(n, 0.05), np.ones(n), zeros, zeros, {}, 1)
    P.bed_path(results, "hill").parent.mkdir(parents=True, exist_ok=True)
    bed.save(P.bed_path(results, "hill"))


def validation_json(results: Path, model: str) -> None:
    """``dozerlab validate``'s JSON of ``model`` (every relative RMSE 12.5 %) and its parity
    plot, at their places under ``results``."""
    metrics = {
        c: {"rmse": 10.0, "rel_rmse": 0.125, "r2": 0.5}
        for c in ("force_x", "force_y", "force_z", "torque_x", "torque_y", "torque_z")
    }
    point = {"name": "hill speed~0.75_depth~0.1", "metrics": metrics}
    plots = results / "validation" / model
    png_file(plots / "parity.png", "parity")
    doc = {
        "model": model,
        "summary": f"{model}: fine",
        "overall": metrics,
        "groups": {
            g: {"overall": metrics, "points": [point]} for g in ("interpolation", "extrapolation")
        },
        "training": {"epochs": 1, "best_epoch": 0, "samples": {"train": 10}, "seconds": 1.5},
        "plots": {"parity": f"{model}/parity.png", "series": {}},
    }
    path = P.validation_path(results, model)
    path.write_text(json.dumps(doc))


def dynamics_overall(velocity: float, density: float, mass: float) -> dict:
    """Metrics of a group whose velocity error grows linearly along the rollout: ``velocity``
    at one step, 5 × ``velocity`` at 50 steps."""
    return {
        "one_step": {"velocity": velocity, "density": density},
        "rollout_at": {
            k: {"steps": int(k), "velocity": velocity * int(k) / 10, "density": density}
            for k in ("10", "50", "100")
        },
        "rollout": {"velocity": [velocity * k / 10 for k in range(1, 101)]},
        "mass": {"max_abs_error": mass},
    }


def dynamics_json(results: Path, model: str, velocity: float, mass: float) -> None:
    """``dozerlab validate-dynamics``'s JSON of ``model`` on one interpolation point (velocity
    error ``velocity`` at one step, :func:`dynamics_overall`), at its place under ``results``."""
    point = {"name": "hill speed~0.75_depth~0.1", **dynamics_overall(velocity, 0.1, mass)}
    doc = {
        "summary": f"{model}: done",
        "history": 2,
        "horizon": 1,
        "groups": {
            "interpolation": {"overall": dynamics_overall(velocity, 0.1, mass), "points": [point]}
        },
    }
    path = P.dynamics_validation_path(results, model)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))


REDUCED_TARGETS = {
    "replay_surface_skill": 0.95,
    "surface_skill": 0.9,
    "force_skill": 0.8,
    "loop_speedup": 40,
    "job_speedup": 10,
    "max_overlap": 0.1,
}


def reduced_json(results: Path, model: str, gif: bytes = b"GIF89a") -> None:
    """``dozerlab compare-reduced``'s JSON of ``model`` on one interpolation point (smoothed
    surface 72 %, the twin's 90 %: skill 0.8, missed, its error 10 % in the swath, 8 % beside it
    (6 % too little there) and 10 % ahead; low-passed force 8 %, the twin's 10 %;
    height accuracy 90 %, loop 62×), its force plot and the animation ``gif`` (bytes), at their
    places under ``results``."""
    point = {
        "scenario": "hill",
        "speed": 0.75,
        "depth": 0.1,
        "role": "interpolation",
        "height_accuracy": 0.9,
        "surface_accuracy": 0.72,
        "force_x_rel_rmse": 0.3,
        "force_lp_rel_rmse": 0.08,
        "force_mean_rel_err": 0.02,
        "velocity_rel_l2": 0.2,
        "density_rel_l2": 0.1,
        "final_emd_m": 0.0042,
        "surface_error_swath": 0.1,
        "surface_error_beside": 0.08,
        "surface_error_ahead": 0.1,
        "surface_excess_swath": 0.02,
        "surface_excess_beside": -0.06,
        "surface_excess_ahead": 0.05,
        "twin_surface_error_swath": 0.05,
        "twin_surface_error_beside": 0.02,
        "twin_surface_error_ahead": 0.03,
        "twin_surface_excess_swath": 0.01,
        "twin_surface_excess_beside": -0.01,
        "twin_surface_excess_ahead": 0.0,
        "twin_height_accuracy": 0.75,
        "twin_surface_accuracy": 0.9,
        "twin_force_x_rel_rmse": 0.2,
        "twin_force_lp_rel_rmse": 0.1,
        "twin_force_mean_rel_err": 0.01,
        "twin_velocity_rel_l2": 0.3,
        "twin_density_rel_l2": 0.05,
        "twin_final_emd_m": 0.001,
        "surface_accuracy_skill": 0.8,
        "force_lp_rel_rmse_skill": 0.8,
        "force_mean_rel_err_skill": 2.0,
        "max_overlap_loop": 0.05,
        "left_bed": 0,
        "loop_speedup": 62.0,
        "job_speedup": None,
        "targets_met": (
            {"replay_surface_skill": False}
            if model == "replay"
            else {"surface_skill": False, "force_skill": True}
        )
        | {"loop_speedup": True, "job_speedup": None},
        "force_model": "linear-loop",
        "plots": ["hill_speed~0.75_depth~0.1_force.png", "hill_speed~0.75_depth~0.1.gif", "x.png"],
    }
    path = P.reduced_comparison_path(results, model)
    compare = path.with_suffix("") / "compare"
    png_file(compare / point["plots"][0], "force")
    (compare / point["plots"][1]).write_bytes(gif)
    path.write_text(json.dumps({"targets": REDUCED_TARGETS, "points": [point]}))


def table_cells(text: str, section: str, row: int) -> list[str]:
    """The cells of data row ``row`` (header rows not counted) of the tables in the report's
    section ``section``."""
    body = re.search(rf'<section id="{section}">(.*?)</section>', text, re.S)[1]
    rows = [r for r in re.findall(r"<tr>(.*?)</tr>", body) if "<td" in r]
    return re.findall(r"<td[^>]*>(.*?)</td>", rows[row])


def report_context(cfg: dict[str, Any], results: Path) -> Any:
    """The :class:`dozerlab.report.sections.Context` a section renders from."""
    from dozerlab.report.sections import Context

    return Context(cfg, results, tuple(P.sweep_points(cfg)), results / "report")


def import_entry(module: str) -> tuple[str, str]:
    """Import an MLflow models-from-code entry ``module`` in a fresh interpreter (warnings come
    once, when its class is defined); return the class name of the model it set, and stderr."""
    import subprocess
    import sys

    code = f"import {module}; import mlflow.models.model as m; print(type(m.__mlflow_model__).__name__)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.strip(), out.stderr


def lazy_model_class(module: str, name: str) -> list[str]:
    """In a fresh interpreter: whether importing ``module`` imported MLflow, then the name of
    its attribute ``name`` (a PythonModel class, as an older model directory imports it) and
    whether MLflow is imported then."""
    import subprocess
    import sys

    code = (
        f"import sys, {module} as m\n"
        "print('mlflow' in sys.modules)\n"
        f"print(m.{name}.__name__, 'mlflow' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return out.stdout.split()


#: The reduce tests' run: the tiny run's bed, blade and path sampled at every step, and a linear
#: force model of one epoch.
REDUCED_RUN = {
    **TINY_RUN,
    "sampling": {"length": 0.3, "below_edge": 0.05, "bins": [6, 5, 4], "chunk_steps": 8},
    "learn": {"epochs": 1, "history": 2, "validation_fraction": 0.2, "validation_block": 0},
    "reduced": {"projection": {"iterations": 8}},
}


def expected_job_runs(cfg: dict[str, Any]) -> dict[str, int]:
    """The MLflow child runs a sweep of ``cfg`` records, per rule (trajectories and the report
    record none)."""
    points = P.sweep_points(cfg)
    models, dynamics = cfg["learn"]["models"], cfg["dynamics"]["models"]
    reduced = cfg["reduced"]["dynamics_models"]
    held_out = [p for p in points if p.role != "train"]
    # reduced.force_fields loop: each learned dynamics model's loop also runs the training points
    looped = (
        [m for m in reduced if m != "replay"] if cfg["reduced"]["force_fields"] == "loop" else []
    )
    training = len(points) - len(held_out)
    return {
        "bed": len(cfg["sweep"]["scenarios"]),
        "simulate": len(points),
        "twin": len(held_out) if cfg["reduced"]["twin"]["enabled"] else 0,
        "train": len(models),
        "validate": len(models),
        "train_dynamics": len(dynamics),
        "validate_dynamics": len(dynamics),
        "reduce": len(reduced) * len(held_out),
        "reduce_training_points": len(looped) * training,  # one job per model, a run per point
        "train_loop_force": len(looped),
        "compare_reduced": len(reduced),
    }


def expected_jobs(cfg: dict[str, Any]) -> dict[str, int]:
    """The jobs of :func:`expected_job_runs`' rules a sweep of ``cfg`` runs: one run each, but a
    ``reduce`` job records a run per held-out point and a ``reduce_training_points`` job one per
    training point."""
    jobs = expected_job_runs(cfg)
    points = P.sweep_points(cfg)
    training = len(P.by_role(points, "train"))
    jobs["reduce"] //= max(len(points) - training, 1)
    jobs["reduce_training_points"] //= max(training, 1)
    return jobs


def imported_by(code: str, libraries: tuple[str, ...]) -> list[str]:
    """Which of the top-level ``libraries`` a fresh interpreter has imported after running
    ``code`` (sorted)."""
    import subprocess
    import sys

    probe = (
        f"{code}\nimport json, sys\n"
        f"print(json.dumps(sorted({{m.split('.')[0] for m in sys.modules}} & set({libraries!r}))))\n"
    )
    out = subprocess.run([sys.executable, "-c", probe], check=True, capture_output=True, text=True)
    return list(json.loads(out.stdout.strip().splitlines()[-1]))


def results_folder(root: Path) -> dict[str, Path]:
    """A small results folder holding one artifact of every kind ``dozerlab verify`` checks,
    written by the package's own writers and commands: a bed, a final state, a trajectory, two
    field stores, a force model trained on them (``dozerlab train``) and a results JSON.
    Returns their paths by kind."""
    from dozerlab.cli import main

    _, bed, _ = write_tiny_run(root / "run")
    (root / "states").mkdir()
    bed.save(root / "states" / "final.npz")
    fields = root / "fields"
    paths = {
        "bed": root / "run" / "bed.npz",
        "state": root / "states" / "final.npz",
        "trajectory": root / "run" / "speed~0.5_depth~0.06.csv",
        "store": write(fields / "a.zarr", 1.0, 0.1, seed=1, steps=40),
        "train": write(fields / "b.zarr", 0.5, 0.05, seed=2, steps=40),
        "model": root / "models" / "linear",
        "json": root / "validation" / "linear.json",
    }
    learn = {"learn": {"epochs": 2, "batch_size": 16}, "mlflow": {"enabled": False}}
    code = main(
        ["train", "--model", "linear", "--train", str(paths["store"]), str(paths["train"])]
        + ["--config", json.dumps(learn), "--out", str(paths["model"]), "--threads", "1"]
    )
    assert code == 0
    paths["json"].parent.mkdir()
    paths["json"].write_text(json.dumps({"overall": {"force_rmse": 1.5}}))
    return paths
