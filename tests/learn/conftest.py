"""Synthetic sweep points whose force and torque are known functions of the fields."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from dozerlab.fields.store import write_store
from dozerlab.learn.data import StoreData, from_arrays

GRID = (8, 6, 4)


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
    fx = mass * (1 + vb[:, 0])
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


def write(path: Path, speed: float, depth: float, **kw) -> Path:
    """A field store written with the fields layer's writer."""
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


TRAIN_POINTS = [(0.5, 0.05), (0.5, 0.15), (1.5, 0.05), (1.5, 0.15), (1.0, 0.05), (1.0, 0.15)]


@pytest.fixture(scope="session")
def train_stores() -> list[StoreData]:
    return [in_memory(s, d, steps=60, seed=i) for i, (s, d) in enumerate(TRAIN_POINTS)]


@pytest.fixture(scope="session")
def store_files(tmp_path_factory) -> dict[str, list[Path]]:
    """Training, interpolation and extrapolation stores on disk."""
    root = tmp_path_factory.mktemp("stores")
    files = {
        "train": [
            write(root / f"train{i}.zarr", s, d, seed=i)
            for i, (s, d) in enumerate(TRAIN_POINTS[:4])
        ]
    }
    files["interpolation"] = [write(root / "interp.zarr", 1.0, 0.1, seed=20)]
    files["extrapolation"] = [write(root / "extrap.zarr", 2.0, 0.2, seed=21)]
    files["other_grid"] = [write(root / "grid.zarr", 1.0, 0.1, seed=22, grid=(6, 6, 4))]
    return files


@pytest.fixture
def config():
    from dozerlab.config import load_config

    return load_config(
        {
            "learn": {"epochs": 20, "patience": 6, "learning_rate": 3e-3, "batch_size": 32},
            "mlflow": {"enabled": False},
        }
    )


@pytest.fixture(scope="module")
def tracking(tmp_path_factory):
    """One SQLite tracking store for the module (creating its tables takes seconds)."""
    root = tmp_path_factory.mktemp("tracking")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
        mp.setenv("DOZERLAB_MLFLOW", "1")
        mp.delenv("DOZERLAB_PARENT_RUN_ID", raising=False)
        yield root
