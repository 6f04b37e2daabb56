"""A small end-to-end run: tiny bed, short trajectory, field store, plots, divergence handling."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.fields.store import FIELD_STORE, open_store
from tests.helpers import TINY_RUN as CONFIG
from tests.helpers import write_tiny_run


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    _, bed, traj = write_tiny_run(tmp)
    return tmp, bed, traj


def test_simulate_writes_a_store_with_fields_forces_and_attrs(inputs):
    import json

    tmp, bed, traj = inputs
    out = tmp / "f.zarr"
    argv = [
        "simulate",
        "--bed",
        str(tmp / "bed.npz"),
        "--trajectory",
        str(tmp / "speed~0.5_depth~0.06.csv"),
        "--config",
        json.dumps(CONFIG),
        "--out",
        str(out),
        "--threads",
        "1",
        "--vtk-dir",
        str(tmp / "vtk"),
        "--plots",
        str(tmp / "plots"),
        "--state",
        str(tmp / "final.npz"),
        # the labels are passed (the workflow passes its sweep point's), never parsed from names
        "--scenario",
        "hill",
        "--speed",
        "0.5",
        "--depth",
        "0.06",
    ]
    assert main(argv) == 0
    from dozerlab.scenarios.bed import Bed

    final = Bed.load(tmp / "final.npz")  # the final state, in the bed format
    assert final.count == bed.count and not np.allclose(final.positions, bed.positions)
    ds = open_store(out)
    assert ds.sizes["time"] == traj.steps // 2
    assert (ds.sizes["x"], ds.sizes["y"], ds.sizes["z"]) == (6, 5, 4)
    assert ds.attrs["scenario"] == "hill" and ds.attrs["speed"] == 0.5 and ds.attrs["depth"] == 0.06
    assert ds.attrs["particle_count"] == bed.count and ds.attrs["sample_every"] == 2
    assert ds.attrs["wall_time_s"] > 0  # the stepping loop's wall time, s
    assert json.loads(ds.attrs["config"])["sampling"]["bins"] == [6, 5, 4]
    np.testing.assert_allclose(ds["time"].values, traj.time[2::2][: ds.sizes["time"]])
    np.testing.assert_allclose(
        ds["blade_position"].values, traj.position[2::2][: ds.sizes["time"]], atol=1e-6
    )
    force = ds["force"].values
    assert np.isfinite(force).all() and np.abs(force).max() > 0  # the blade met the bed
    rho = ds["density"].values
    assert rho.max() > 0 and np.isfinite(ds["velocity"].values).all()
    # the blade pushes material: its mean force on the blade points backwards (−x) once it cuts
    assert force[len(force) // 2 :, 0].mean() < 0
    assert len(list((tmp / "vtk").glob("particles_*.vtu"))) == traj.steps // 10
    assert {"force.png", "slice_000000.png"} <= {p.name for p in (tmp / "plots").iterdir()}
    # A rerun replaces the store, snapshots and plots it wrote (each recognised as ours).
    assert FIELD_STORE.recognise(out)
    assert main(argv) == 0
    assert open_store(out).sizes["time"] == traj.steps // 2


@pytest.mark.parametrize(
    ("section", "message"),
    [
        ({"dt": 0.02}, "differs from solver.dt"),
        ({"max_overlap": 1e-4}, "simulation diverged at step"),
    ],
)
def test_bad_runs_are_refused_without_store(inputs, capsys, section, message):
    import json

    tmp, _, _ = inputs
    cfg = json.loads(json.dumps(CONFIG))
    cfg["solver"].update(section)
    argv = [
        "simulate",
        "--bed",
        str(tmp / "bed.npz"),
        "--trajectory",
        str(tmp / "speed~0.5_depth~0.06.csv"),
        "--config",
        json.dumps(cfg),
        "--out",
        str(tmp / "g.zarr"),
    ]
    assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (tmp / "g.zarr").exists()


def test_labels_come_from_arguments_not_file_names(inputs):
    import json
    import shutil

    tmp, _bed, traj = inputs
    renamed = tmp / "speed~9.0_depth~9.0.csv"  # a misleading name is not read
    shutil.copy(tmp / "speed~0.5_depth~0.06.csv", renamed)
    out = tmp / "unlabelled.zarr"
    argv = ["simulate", "--bed", str(tmp / "bed.npz"), "--trajectory", str(renamed)]
    assert main([*argv, "--config", json.dumps(CONFIG), "--out", str(out)]) == 0
    ds = open_store(out)
    assert ds.attrs["scenario"] == "hill" and ds.attrs["depth"] is None
    assert ds.attrs["speed"] == pytest.approx(traj.speed)
