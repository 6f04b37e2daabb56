"""The reduced loop driven by the replay model follows the NDEM store it replays."""

from __future__ import annotations

import dataclasses

import numpy as np

from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import open_store
from dozerlab.reduce.compare import compare_point
from dozerlab.reduce.models import ForcePredictor, ReplayFieldModel
from dozerlab.reduce.run import reduce_run
from dozerlab.scenarios.bed import Bed
from dozerlab.scenarios.trajectory import Trajectory


class _Still:
    """A field model that predicts a bed at rest: the baseline replay must beat."""

    name, history, horizon = "still", 1, 2

    def __init__(self, grid):
        self.grid = grid

    def check_run(self, run):
        pass

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


class _Uniform:
    """A field model that predicts one uniform velocity and records the history it was given."""

    name, history, horizon = "uniform", 1, 1
    u = np.array([0.4, 0.0, 0.1], np.float32)

    def __init__(self, grid):
        self.grid = grid
        self.seen: list[np.ndarray] = []
        self.seen_density: list[np.ndarray] = []

    def check_run(self, run):
        pass

    def predict(self, velocity, density, blade_velocity, row):
        self.seen.append(velocity[-1].copy())
        self.seen_density.append(density[-1].copy())
        v = np.broadcast_to(self.u, (1, *self.grid, 3)).copy()
        return v, density[-1:].copy()


def _rows_a_step(config, n):
    return {**config, "reduced": {**config["reduced"], "step_rows": n}}


def _uniform_run(tmp, config, name, model_name="uniform"):
    model = _Uniform(SamplingGrid.from_config(config).bins)
    model.name = model_name
    metrics = reduce_run(
        tmp / "bed.npz",
        tmp / "speed~0.5_depth~0.06.csv",
        config,
        model,
        ForcePredictor(tmp / "linear"),
        tmp / f"{name}.zarr",
        tmp / f"{name}.npz",
    )
    model.metrics = metrics
    return model, open_store(tmp / f"{name}.zarr")


def test_the_ridge_model_reads_its_own_velocity_and_the_sampled_density(ndem_run):
    tmp, config = ndem_run  # reduced.predicted_history: [ridge] by default
    model, stored = _uniform_run(tmp, _rows_a_step(config, 1), "own", "ridge")
    warm = int(stored.attrs["warmup_rows"])
    assert len(model.seen) > 3
    for k, (seen, rho) in enumerate(
        zip(model.seen[1:], model.seen_density[1:], strict=True), start=warm
    ):
        np.testing.assert_array_equal(seen, np.broadcast_to(model.u, seen.shape))
        np.testing.assert_array_equal(rho, stored["density"].values[k])
    moved = stored["velocity"].values[warm:, 1:, :, 1:]
    assert np.abs(moved - model.u).max() > 0.05  # what the grains did is not what it reads


def test_other_field_models_read_the_flow_they_gave_not_the_projected_motion(ndem_run):
    tmp, config = ndem_run
    model, stored = _uniform_run(tmp, _rows_a_step(config, 1), "flow")
    warm = int(stored.attrs["warmup_rows"])
    # every grain touching a bin off the volume's floor and blade face was carried by the field
    for k, seen in enumerate(model.seen[1:], start=warm):
        rho = stored["density"].values[k]
        inner = rho[1:, :, 1:] > 0
        np.testing.assert_allclose(
            seen[1:, :, 1:][inner],
            np.broadcast_to(model.u, seen[1:, :, 1:][inner].shape),
            atol=1e-5,
        )
    moved = stored["velocity"].values[warm:, 1:, :, 1:]
    assert np.abs(moved - model.u).max() > 0.05  # the projection did change the grains' motion


def test_two_rows_a_step_move_the_grains_once_and_fill_the_row_between_from_either_side(ndem_run):
    tmp, config = ndem_run
    model, stored = _uniform_run(tmp, _rows_a_step(config, 2), "two")
    warm, rows = int(stored.attrs["warmup_rows"]), int(stored.sizes["time"])
    assert rows - warm >= 6
    assert model.metrics["reduced_rows"] == rows - warm == len(model.seen)  # a call a row
    assert model.metrics["reduced_steps"] == -(-(rows - warm) // 2)
    # every step's projection tested the contacts of the grains it moved, in one sweep or more
    assert model.metrics["projection_tests_mean"] > model.metrics["projection_sweeps_mean"] >= 1
    v, rho = stored["velocity"].values, stored["density"].values
    for k in range(warm, rows - 1, 2):  # the first row of each step: the grains skip it
        np.testing.assert_allclose(rho[k], 0.5 * (rho[k - 1] + rho[k + 1]), rtol=1e-5, atol=1e-3)
        np.testing.assert_allclose(v[k], 0.5 * (v[k - 1] + v[k + 1]), rtol=1e-5, atol=1e-6)
        # until the step's end the model read its own prediction of the row (here: the last
        # row's density), then the filled row
        np.testing.assert_array_equal(
            model.seen_density[k - warm + 1], model.seen_density[k - warm]
        )
        if k + 2 < rows:
            np.testing.assert_array_equal(model.seen_density[k - warm + 2], rho[k + 1])
    one_model, _ = _uniform_run(tmp, _rows_a_step(config, 1), "one")
    assert one_model.metrics["reduced_steps"] == rows - warm
    # the same uniform field moves the grains as far in half the steps
    a, b = (Bed.load(tmp / f"{n}.npz").positions for n in ("two", "one"))
    moved = np.linalg.norm(b - Bed.load(tmp / "bed.npz").positions, axis=1) > 0.01
    assert moved.sum() > 20
    assert np.median(np.linalg.norm(a - b, axis=1)[moved]) < 0.5 * np.median(
        np.linalg.norm(b - Bed.load(tmp / "bed.npz").positions, axis=1)[moved]
    )


class _Looser(_Uniform):
    """The uniform velocity, and a density a fifth below the grains' (a bed that dilates)."""

    def predict(self, velocity, density, blade_velocity, row):
        v, rho = super().predict(velocity, density, blade_velocity, row)
        return v, 0.8 * rho


def _steered(config, models, gain):
    return {
        **config,
        "reduced": {**config["reduced"], "density_models": models, "density_gain": gain},
    }


def test_a_model_in_density_models_steers_the_grains_towards_its_density(ndem_run):
    tmp, config = ndem_run
    finals = {}
    for name, models, gain in [
        ("unlisted", ["replay"], 0.5),
        ("off", ["looser"], 0.0),
        ("steered", ["looser"], 0.5),
    ]:
        model = _Looser(SamplingGrid.from_config(config).bins)
        model.name = "looser"
        reduce_run(
            tmp / "bed.npz",
            tmp / "speed~0.5_depth~0.06.csv",
            _steered(config, models, gain),
            model,
            ForcePredictor(tmp / "linear"),
            tmp / f"{name}.zarr",
            tmp / f"{name}.npz",
        )
        finals[name] = Bed.load(tmp / f"{name}.npz").positions
    # unlisted or at gain 0 the loop is the one without steering, to the bit
    np.testing.assert_array_equal(finals["unlisted"], finals["off"])
    # steered towards a looser bed, the grains the field carried stand taller
    start = Bed.load(tmp / "bed.npz").positions
    moved = np.linalg.norm(finals["off"] - start, axis=1) > 0.01
    assert moved.sum() > 20
    rise = finals["steered"][moved, 2] - finals["off"][moved, 2]
    assert rise.mean() > 0.003


def test_a_blade_clear_of_the_bed_leaves_the_warm_up_rows_the_bed_as_it_lies(ndem_run):
    tmp, config = ndem_run  # the planned blade starts 10 cm before the bed
    _, stored = _uniform_run(tmp, config, "clear")
    warm = int(stored.attrs["warmup_rows"])
    assert stored.attrs["warmup_stepped"] is False
    bed, grid = Bed.load(tmp / "bed.npz"), SamplingGrid.from_config(config)
    for k in range(warm):
        tip = stored["blade_position"].values[k]
        v, rho = grid.sample(bed.positions, bed.velocities, bed.radii, bed.masses, tip)
        np.testing.assert_allclose(stored["density"].values[k], rho, rtol=1e-6)
        np.testing.assert_allclose(stored["velocity"].values[k], v, atol=1e-7)
        assert not stored["force"].values[k].any()
    ndem = open_store(tmp / "ndem.zarr")  # NDEM's own run agrees: nothing moved yet
    np.testing.assert_allclose(
        stored["density"].values[:warm], ndem["density"].values[:warm], atol=1.0
    )


def test_a_blade_that_starts_at_the_bed_is_stepped_by_ndem_through_the_warm_up(ndem_run):
    tmp, config = ndem_run
    traj = Trajectory.load_csv(tmp / "speed~0.5_depth~0.06.csv")
    n = int(np.argmax(traj.position[:, 0] > -0.003))  # the blade's face 3 mm from the grains
    inside = dataclasses.replace(
        traj,
        time=np.arange(traj.time.size - n) * traj.dt,
        position=traj.position[n:],
        velocity=traj.velocity[n:],
    )
    inside.save_csv(tmp / "inside.csv")
    reduce_run(
        tmp / "bed.npz",
        tmp / "inside.csv",
        config,
        _Uniform(SamplingGrid.from_config(config).bins),
        ForcePredictor(tmp / "linear"),
        tmp / "inside.zarr",
        tmp / "inside.npz",
    )
    stored = open_store(tmp / "inside.zarr")
    warm = int(stored.attrs["warmup_rows"])
    assert stored.attrs["warmup_stepped"] is True
    assert np.abs(stored["force"].values[:warm, 0]).max() > 0  # NDEM's blade pushed the grains


class _Lifter(_Uniform):
    """A uniform field that lifts the material faster than it pushes it."""

    name = "lifter"
    u = np.array([0.3, 0.0, 0.8], np.float32)


def test_only_the_loops_of_crest_models_lift_the_piles_crest(ndem_run):
    tmp, config = ndem_run
    tops = {}
    for name, models, bins in [
        ("unlisted", ["replay"], 0.5),
        ("off", ["lifter"], 0.0),
        ("lifted", ["lifter"], 0.5),
    ]:
        model = _Lifter(SamplingGrid.from_config(config).bins)
        reduce_run(
            tmp / "bed.npz",
            tmp / "speed~0.5_depth~0.06.csv",
            {
                **config,
                "reduced": {**config["reduced"], "crest_models": models, "crest_bins": bins},
            },
            model,
            ForcePredictor(tmp / "linear"),
            tmp / f"{name}.zarr",
            tmp / f"{name}.npz",
        )
        tops[name] = Bed.load(tmp / f"{name}.npz").positions[:, 2]
    # a model not in crest_models runs the loop without the crest, to the bit
    np.testing.assert_array_equal(tops["unlisted"], tops["off"])
    # with it, the grains the top bins lift over the volume's top keep rising with them
    assert tops["lifted"].max() > tops["off"].max() + 0.01
