"""Shared fixtures of the fields tests: a small random store's arrays."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.fields.store import ATTRS


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


@pytest.fixture
def store_arrays() -> dict:
    """Arrays of a 70-step store on a 4×3×2 grid (two chunks of 64 plus a partial one)."""
    rng = np.random.default_rng(0)
    t, grid = 70, (4, 3, 2)
    vec = lambda: rng.normal(size=(t, 3)).astype(np.float32)  # noqa: E731
    return {
        "x": np.linspace(0.05, 0.35, 4),
        "y": np.linspace(-0.2, 0.2, 3),
        "z": np.array([-0.05, 0.05]),
        "time": np.arange(t) * 0.01,
        "velocity": rng.normal(size=(t, *grid, 3)).astype(np.float32),
        "density": rng.uniform(0, 2600, size=(t, *grid)).astype(np.float32),
        "force": vec(),
        "torque": vec(),
        "blade_velocity": vec(),
        "blade_position": vec(),
        "attrs": dict.fromkeys(ATTRS) | {"scenario": "hill", "bins": [4, 3, 2]},
    }
