"""Fixtures of the learn tests: synthetic sweep points whose force and torque are known
functions of the fields (built by :mod:`tests.helpers`)."""

from __future__ import annotations

from pathlib import Path

import pytest

from dozerlab.learn.data import StoreData
from tests.helpers import copy_mlflow_store, in_memory, write

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
def tracking(tmp_path_factory, mlflow_template):
    """One SQLite tracking store for the module, a copy of the session's empty one."""
    root = tmp_path_factory.mktemp("tracking")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(root)
        mp.setenv("MLFLOW_TRACKING_URI", copy_mlflow_store(mlflow_template, root))
        mp.setenv("DOZERLAB_MLFLOW", "1")
        mp.delenv("DOZERLAB_PARENT_RUN_ID", raising=False)
        yield root
