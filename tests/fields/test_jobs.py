"""The simulate job: labels, the MLflow record of the run, and the stepping loop's statistics."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.fields.jobs import simulate
from dozerlab.fields.run import RunStats, drive
from dozerlab.fields.sampling import SamplingGrid
from dozerlab.fields.store import ATTRS, open_store
from dozerlab.runtime import DozerlabError
from tests.helpers import write_tiny_run


@pytest.fixture(scope="module")
def run_inputs(tmp_path_factory):
    """The tiny run's files, the trajectory named like no sweep point: labels come from flags."""
    tmp = tmp_path_factory.mktemp("job")
    return tmp, *write_tiny_run(tmp, "path.csv")


@pytest.mark.slow  # a simulation logged to MLflow; test_run covers simulate fast
def test_simulate_labels_the_store_and_records_the_run_in_mlflow(run_inputs, mlflow_store):
    tmp, config, bed, _ = run_inputs
    out = tmp / "f.zarr"
    metrics = simulate(
        tmp / "bed.npz",
        tmp / "path.csv",
        config,
        out,
        scenario="step",
        speed=0.5,
        depth=0.06,
        plots_dir=tmp / "plots",
    )
    ds = open_store(out)
    assert (ds.attrs["scenario"], ds.attrs["speed"], ds.attrs["depth"]) == ("step", 0.5, 0.06)
    assert metrics["particle_count"] == bed.count and metrics["force_mag_peak"] > 0
    assert metrics["force_x_mean"] == pytest.approx(float(ds["force"].values[:, 0].mean()))

    client = mlflow_store
    exp = client.get_experiment_by_name("dozerlab").experiment_id
    (run,) = client.search_runs([exp])
    assert (
        run.info.status == "FINISHED" and run.info.run_name == "simulate/step/speed~0.5_depth~0.06"
    )
    assert {k: run.data.tags[k] for k in ("rule", "role", "scenario", "speed", "depth")} == {
        "rule": "simulate",
        "role": "simulate",
        "scenario": "step",
        "speed": "0.5",
        "depth": "0.06",
    }
    assert run.data.params["sampling.bins"] == "[6, 5, 4]"
    assert run.data.metrics["steps_per_s"] == pytest.approx(metrics["steps_per_s"])
    logged = {a.path for a in client.list_artifacts(run.info.run_id, "plots")}
    assert {"plots/force.png", "plots/slice_000000.png"} <= logged
    assert {p.name for p in (tmp / "plots").iterdir()} == {p.split("/")[1] for p in logged}


def test_drive_counts_steps_samples_and_forces(run_inputs, monkeypatch):
    tmp, config, bed, traj = run_inputs
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")
    grid = SamplingGrid.from_config(config)
    attrs = dict.fromkeys(ATTRS, 0) | {"scenario": "hill", "bins": list(grid.bins)}
    stats = drive(bed, traj, config, grid, attrs, tmp / "d.zarr")
    every = config["sampling"]["every"]
    assert stats.steps == traj.steps
    assert len(stats.forces) == traj.steps // every == open_store(tmp / "d.zarr").sizes["time"]
    stored = open_store(tmp / "d.zarr")["force"].values  # float32 in the store
    np.testing.assert_array_equal(np.array(stats.forces, dtype=np.float32), stored)
    assert 0 < stats.step_time <= stats.wall_time and 0 < stats.sample_time < stats.wall_time
    m = stats.metrics(bed.count)
    assert m["steps_per_s"] == pytest.approx(traj.steps / stats.step_time)
    assert m["contact_iterations_per_s"] == pytest.approx(
        stats.contact_iterations / stats.step_time
    )


def test_drive_reports_the_active_zones_awake_fraction(run_inputs):
    tmp, config, bed, traj = run_inputs
    grid = SamplingGrid.from_config(config)
    attrs = dict.fromkeys(ATTRS, 0) | {"scenario": "hill", "bins": list(grid.bins)}
    full = drive(bed, traj, config, grid, attrs, tmp / "full.zarr")
    # at the tiny run's 30 sweeps a step, a grain the blade jams against the rigid sleepers of
    # its stiff lattice sinks past half a radius at some margins (0 and 0.06 m, and 0.06 and
    # 0.1 m before its bed slept from the first step); at the workflow's 80, at none of 0-0.3 m
    zone = {"enabled": True, "margin": 0.0}
    zoned_config = config | {"solver": config["solver"] | {"iterations": 80, "active_zone": zone}}
    zoned = drive(bed, traj, zoned_config, grid, attrs, tmp / "zone.zarr")
    assert full.metrics(bed.count)["active_fraction"] == 1.0
    assert 0.0 < zoned.metrics(bed.count)["active_fraction"] < 1.0


def test_drive_counts_the_steps_that_re_linearised(run_inputs):
    # the tiny run with Hertz contacts (E 1e8 Pa): at its 30 sweeps a step the grains the
    # blade jams sink past half a radius without the rounds
    tmp, config, bed, traj = run_inputs
    grid = SamplingGrid.from_config(config)
    attrs = dict.fromkeys(ATTRS, 0) | {"scenario": "hill", "bins": list(grid.bins)}
    hertz = config | {"material": config["material"] | {"youngs_modulus": 1e8}}

    def run(name: str, **solver: float) -> RunStats:
        cfg = hertz | {"solver": hertz["solver"] | solver}
        return drive(bed, traj, cfg, grid, attrs, tmp / f"{name}.zarr")

    with pytest.raises(DozerlabError, match="diverged"):
        run("never", relinearize=0)
    stats = run("past", relinearize=3, relinearize_above=0.2)
    assert 0 < stats.relinearized_steps < traj.steps
    assert stats.metrics(bed.count)["relinearized_steps"] == stats.relinearized_steps
