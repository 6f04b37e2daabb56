"""Fixtures of the reduce tests: one small NDEM run and a force model trained on it."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.config import load_config
from dozerlab.scenarios.bed import Bed
from tests.helpers import REDUCED_RUN as CONFIG


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


@pytest.fixture(scope="session")
def ndem_run(tmp_path_factory):
    """A small NDEM run (bed, trajectory, store, final state) and a linear force model."""
    from dozerlab.fields.jobs import simulate
    from dozerlab.learn.jobs import train_job
    from dozerlab.scenarios.trajectory import plan_trajectory

    tmp = tmp_path_factory.mktemp("reduce")
    config = load_config(CONFIG)
    r = 0.03
    xs = np.arange(r, 0.8 - r + 1e-9, 2 * r)
    ys = np.arange(-0.18 + r, 0.18 - r + 1e-9, 2 * r)
    zs = np.arange(r, 0.18, 2 * r)
    pos = np.array(np.meshgrid(xs, ys, zs, indexing="ij")).reshape(3, -1).T
    radii = np.full(len(pos), r)
    bed = Bed(
        "hill",
        0.8,
        0.36,
        pos,
        radii,
        2600.0 * 4 / 3 * np.pi * radii**3,
        np.zeros_like(pos),
        np.zeros_like(pos),
        dict(config["material"]),
        1,
    )
    bed.save(tmp / "bed.npz")
    traj = plan_trajectory(bed, 0.5, 0.06, config)
    traj.save_csv(tmp / "speed~0.5_depth~0.06.csv")
    with pytest.MonkeyPatch.context() as mp:  # the runs' MLflow files stay in tmp
        mp.chdir(tmp)
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
        simulate(
            tmp / "bed.npz",
            tmp / "speed~0.5_depth~0.06.csv",
            config,
            tmp / "ndem.zarr",
            state_out=tmp / "ndem.npz",
        )
        train_job("linear", [tmp / "ndem.zarr"], config, tmp / "linear", progress=False)
    return tmp, config
