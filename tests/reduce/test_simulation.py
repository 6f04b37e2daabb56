"""The reduced loop: advection by the field, frozen and ballistic grains, and — with the replay
model (the NDEM run's own fields) — a run that follows the NDEM store; the CLI's outputs."""

from __future__ import annotations

import json

import mlflow
import numpy as np
import pytest
from tests.learn.dynamics.helpers import translating

from dozerlab.cli import main
from dozerlab.config import load_config
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import open_store
from dozerlab.learn.dynamics import pyfunc
from dozerlab.learn.dynamics.train import train_dynamics
from dozerlab.ndem.bodies import Bodies as NdemBodies
from dozerlab.reduce.compare import compare_point
from dozerlab.reduce.models import ForcePredictor, PyfuncFieldModel, ReplayFieldModel
from dozerlab.reduce.projection import Bodies
from dozerlab.reduce.run import reduce_run
from dozerlab.reduce.simulation import ReducedSettings, ReducedState
from dozerlab.scenarios.bed import Bed

CONFIG = {
    "solver": {"dt": 0.01, "iterations": 30},
    "material": {"youngs_modulus": 0.0},
    "bed": {"length": 0.8, "width": 0.36, "radius": 0.03},
    "scenarios": {"hill": {"goal_height": 0.08}},
    "blade": {"width": 0.3, "height": 0.2, "thickness": 0.03, "start_gap": 0.05},
    "trajectory": {"subdivisions": [40, 4], "approach_steps": 3},
    "sampling": {"length": 0.3, "below_edge": 0.05, "bins": [6, 5, 4], "chunk_steps": 8},
    "learn": {"epochs": 1, "history": 2, "validation_fraction": 0.2, "validation_block": 0},
    "reduced": {"projection": {"iterations": 8}},
}


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


def _state(positions, velocities, grid, settings=None) -> ReducedState:
    """Grains of radius 0.02 m over the ground z = 0 and a blade box 0.1 × 1 × 1 m behind the tip."""
    b = NdemBodies()
    b.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), 0.5)
    b.add_box((10.0, 0.0, 1.0), (0.05, 0.5, 0.5), True, 0.5, None)
    n = len(positions)
    return ReducedState(
        positions,
        velocities,
        np.full(n, 0.02),
        np.full(n, 0.1),
        Bodies(b.kind, b.center, b.rotations(), b.half, b.normal),
        np.array([0.05, 0.5, 0.5]),
        np.array([-0.05, 0.0, 0.5]),
        grid,
        np.array([0.0, 0.0, -9.81]),
        settings or ReducedSettings(),
        np.array([-1.0, -1.0, 0.0]),
        np.array([2.0, 1.0, 2.0]),
    )


def test_grains_in_the_volume_move_with_the_field_and_the_others_rest_or_fly():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    tip = np.array([0.0, 0.0, 0.5])
    inside = np.array([[0.05, -0.15, 0.55], [0.2, 0.05, 0.7], [0.33, 0.12, 0.82]])
    resting, flying = [1.0, 0.5, 0.3], [1.4, -0.5, 1.5]
    x = np.vstack([inside, [resting, flying]])
    v = np.zeros_like(x)
    v[4] = [0.5, 0.0, 1.0]
    cx, cy, cz = np.meshgrid(*grid.centres(), indexing="ij")
    field = np.stack([0.3 + 0.5 * cx, -0.2 * cz, 0.1 + cy], -1)  # linear: interpolation exact
    h = 0.01
    state = _state(x, v, grid)
    state.step(field, np.full(grid.bins, 1500.0), tip, h)
    local = inside - tip  # the blade frame, as the bin centres
    expect_v = np.stack([0.3 + 0.5 * local[:, 0], -0.2 * local[:, 2], 0.1 + local[:, 1]], -1)
    np.testing.assert_allclose(state.x[:3], inside + h * expect_v, atol=1e-12)
    np.testing.assert_allclose(state.v[:3], expect_v, atol=1e-9)
    np.testing.assert_array_equal(state.x[3], resting)  # at rest outside: frozen
    fly_v = np.array([0.5, 0.0, 1.0 - 9.81 * h])
    np.testing.assert_allclose(state.x[4], np.array(flying) + h * fly_v, atol=1e-12)


def test_grains_above_the_volume_ride_with_it_and_fall_once_it_lets_them_go():
    grid = SamplingGrid((4, 4, 4), (0.1, 0.1, 0.1), (0.0, -0.2, 0.0))
    above = np.array([[0.2, 0.0, 1.6]])  # over the volume (top 0.9 m) and its 2-bin margin
    field = np.zeros((*grid.bins, 3))
    field[..., 0] = 0.02  # slower than reduced.rest_speed
    h = 0.01
    state = _state(above, np.zeros_like(above), grid)
    state.step(field, np.full(grid.bins, 1500.0), np.array([0.0, 0.0, 0.5]), h)
    np.testing.assert_allclose(state.x[0], above[0] + [h * 0.02, 0.0, 0.0], atol=1e-12)
    # the blade has moved on: the grain the field carried falls, slow as it was
    z = state.x[0, 2]
    for _ in range(3):
        state.step(field, np.full(grid.bins, 1500.0), np.array([5.0, 0.0, 0.5]), h)
    assert state.x[0, 2] == pytest.approx(z - 6 * 9.81 * h * h, rel=1e-9)  # h·g·(1 + 2 + 3)·h


@pytest.fixture(scope="module")
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
    simulate(
        tmp / "bed.npz",
        tmp / "speed~0.5_depth~0.06.csv",
        config,
        tmp / "ndem.zarr",
        state_out=tmp / "ndem.npz",
    )
    with pytest.MonkeyPatch.context() as mp:  # the model's MLflow files stay in tmp
        mp.chdir(tmp)
        mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp / 'mlflow.db'}")
        train_job("linear", [tmp / "ndem.zarr"], config, tmp / "linear", progress=False)
    return tmp, config


class _Still:
    """A field model that predicts a bed at rest: the baseline replay must beat."""

    name, history, horizon = "still", 1, 2

    def __init__(self, grid):
        self.grid = grid

    def predict(self, velocity, density, blade_velocity, row):
        return np.zeros((2, *self.grid, 3), np.float32), np.repeat(density[-1:], 2, axis=0)


def test_with_the_replay_model_the_loop_follows_the_ndem_store(ndem_run):
    tmp, config = ndem_run
    forces = ForcePredictor(tmp / "linear")
    replay = ReplayFieldModel(tmp / "ndem.zarr")
    reduce_run(
        tmp / "bed.npz",
        tmp / "speed~0.5_depth~0.06.csv",
        config,
        replay,
        forces,
        tmp / "replay.zarr",
        tmp / "replay.npz",
    )
    grid = SamplingGrid.from_config(config).bins
    reduce_run(
        tmp / "bed.npz",
        tmp / "speed~0.5_depth~0.06.csv",
        config,
        _Still(grid),
        forces,
        tmp / "still.zarr",
        tmp / "still.npz",
    )
    args = (tmp / "bed.npz", tmp / "ndem.npz")
    m_replay, _ = compare_point(
        tmp / "ndem.zarr", tmp / "replay.zarr", args[0], args[1], tmp / "replay.npz", config
    )
    m_still, _ = compare_point(
        tmp / "ndem.zarr", tmp / "still.zarr", args[0], args[1], tmp / "still.npz", config
    )
    assert m_replay["velocity_rel_l2"] < 0.6 * m_still["velocity_rel_l2"]
    assert m_replay["density_rel_l2"] < m_still["density_rel_l2"]
    # (the height field of this 0.18 m lattice changes by about a grain: too little to score)
    assert m_replay["final_emd_m"] < m_still["final_emd_m"]
    assert m_replay["body_depth_final_m"] <= 1e-9 and m_replay["left_bed"] == 0


def _reduce_argv(tmp, dynamics: str, out: str) -> list[str]:
    return [
        *("reduce", "--bed", str(tmp / "bed.npz")),
        *("--trajectory", str(tmp / "speed~0.5_depth~0.06.csv"), "--dynamics", dynamics),
        *("--ndem", str(tmp / "ndem.zarr"), "--force-model", str(tmp / "linear")),
        *("--config", json.dumps(CONFIG), "--out", str(tmp / f"{out}.zarr")),
        *("--state", str(tmp / f"{out}.npz")),
    ]


def test_reduce_command_writes_an_aligned_store_and_a_bed_file(ndem_run):
    tmp, _ = ndem_run
    assert main([*_reduce_argv(tmp, "replay", "cli"), "--depth", "0.06"]) == 0
    ds, nd = open_store(tmp / "cli.zarr"), open_store(tmp / "ndem.zarr")
    assert dict(ds.sizes) == dict(nd.sizes)
    np.testing.assert_allclose(ds["time"].values, nd["time"].values)
    np.testing.assert_allclose(ds["blade_position"].values, nd["blade_position"].values)
    assert ds.attrs["dynamics_model"] == "replay" and ds.attrs["force_model"] == "linear"
    assert ds.attrs["depth"] == 0.06
    assert ds.attrs["wall_time_s"] > 0 and nd.attrs["wall_time_s"] > 0
    assert np.isfinite(ds["force"].values).all()
    state = Bed.load(tmp / "cli.npz")
    assert state.count == Bed.load(tmp / "bed.npz").count == Bed.load(tmp / "ndem.npz").count


def test_a_missing_dynamics_model_is_refused(ndem_run, capsys):
    tmp, _ = ndem_run
    assert main(_reduce_argv(tmp, str(tmp / "nowhere"), "x")) == 2
    assert "not an MLflow model directory" in capsys.readouterr().err
    assert not (tmp / "x.zarr").exists()


def test_the_loops_direct_model_calls_match_the_pyfunc(ndem_run):
    tmp, _ = ndem_run
    forces = ForcePredictor(tmp / "linear")
    nd = open_store(tmp / "ndem.zarr")
    v, rho, vb = (
        nd[k].values.astype(np.float32) for k in ("velocity", "density", "blade_velocity")
    )
    k = 5  # the loop passes the rows up to the current one; the pyfunc predicts each of them
    force, torque = forces.predict(v[:k], rho[:k], vb[:k])
    frame = forces.model.predict({"velocity": v[:k], "density": rho[:k], "blade_velocity": vb[:k]})
    np.testing.assert_allclose(np.r_[force, torque], frame.to_numpy()[-1], rtol=1e-5, atol=1e-4)


def test_the_loops_direct_field_model_calls_match_the_pyfunc(tmp_path):
    cfg = load_config(
        {
            "mlflow": {"enabled": False},
            "learn": {"validation_block": 5},
            "dynamics": {"epochs": 1, "samples_per_epoch": 8, "history": 2, "horizon": 2},
        }
    )
    stores = [translating(i, rows=30) for i in range(2)]
    model = train_dynamics("unet", stores, cfg, progress=False).model
    arrays = {k: getattr(stores[0], k) for k in ("velocity", "density", "blade_velocity")}
    pyfunc.save(model, {"train_points": []}, tmp_path / "unet", arrays)
    held = translating(7, rows=30)
    loop = PyfuncFieldModel(tmp_path / "unet", held.grid)
    v, rho = loop.predict(held.velocity[3:5], held.density[3:5], held.blade_velocity[3:7], 4)
    want = mlflow.pyfunc.load_model(str(tmp_path / "unet")).predict(
        {
            "velocity": held.velocity[None, 3:5],
            "density": held.density[None, 3:5],
            "blade_velocity": held.blade_velocity[None, 3:7],
        }
    )
    np.testing.assert_allclose(v, want["velocity"][0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rho, want["density"][0], rtol=1e-5, atol=1e-5)
