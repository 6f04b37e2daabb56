"""The fields layer's commands: defaults and flags of plot-fields and import-legacy, and inputs
that are missing or bad named in a one-line error (exit 2)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import xarray as xr

from dozerlab.cli import main
from dozerlab.fields.store import write_store
from dozerlab.runtime import FOLDER_MARK
from tests.helpers import TINY_RUN, write_tiny_run


def test_plot_fields_defaults_to_four_spread_slices_and_no_animation_on_request(
    tmp_path, store_arrays, capsys
):
    store = write_store(tmp_path / "f.zarr", **store_arrays)
    assert main(["plot-fields", str(store), "--out", str(tmp_path / "p"), "--no-animation"]) == 0
    names = sorted(p.name for p in (tmp_path / "p").iterdir() if p.name != FOLDER_MARK)
    assert (tmp_path / "p" / FOLDER_MARK).is_file()  # the folder is marked as plot-fields'
    assert names == [
        "force.png",
        "slice_000000.png",
        "slice_000023.png",
        "slice_000046.png",
        "slice_000069.png",
    ]
    assert capsys.readouterr().out.split() == [
        str(tmp_path / "p" / n) for n in names[1:] + names[:1]
    ]


def test_import_legacy_default_volume_is_centred_across_the_blade(tmp_path, store_arrays):
    a = dict(store_arrays)
    a["attrs"] = a["attrs"] | {"bin_size": [0.1, 0.2, 0.1]}
    store = write_store(tmp_path / "f.zarr", **a)
    assert main(["export-legacy", str(store), str(tmp_path / "f.bin")]) == 0
    assert main(["import-legacy", str(tmp_path / "f.bin"), str(tmp_path / "g.zarr")]) == 0
    ds = xr.open_zarr(tmp_path / "g.zarr")
    # default lower corner (0, -width/2, 0): 3 bins of 0.2 m across a 0.6 m wide volume
    np.testing.assert_allclose(ds["x"].values, [0.05, 0.15, 0.25, 0.35], atol=1e-7)
    np.testing.assert_allclose(ds["y"].values, [-0.2, 0.0, 0.2], atol=1e-7)
    np.testing.assert_allclose(ds["z"].values, [0.05, 0.15], atol=1e-7)


def test_simulate_with_a_missing_bed_names_it_and_writes_nothing(tmp_path, capsys):
    argv = [
        "simulate",
        "--bed",
        str(tmp_path / "absent.npz"),
        "--trajectory",
        str(tmp_path / "absent.csv"),
        "--config",
        json.dumps(TINY_RUN),
        "--out",
        str(tmp_path / "f.zarr"),
    ]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("dozerlab simulate: error:") and "absent.npz" in err
    assert list(tmp_path.iterdir()) == []


def test_simulate_refuses_less_than_one_thread(tmp_path, capsys):
    argv = ["simulate", "--bed", "b.npz", "--trajectory", "t.csv", "--out", "f.zarr"]
    with pytest.raises(SystemExit) as exit_:  # argparse, with the config's bounds
        main([*argv, "--threads", "0"])
    assert exit_.value.code == 2
    assert "argument --threads: 0 is less than the minimum of 1" in capsys.readouterr().err


def test_simulate_with_jitter_runs_a_twin_in_ndems_formats(tmp_path, capsys, monkeypatch):
    """--jitter: NDEM from the bed with every grain moved that far, as simulate's own outputs
    (marked so; its MLflow run tagged with the jitter's seed, which tells a twin's draws apart);
    at the start the twin's grains move by the jitter's scale where NDEM's rest."""
    import mlflow

    from dozerlab.fields.run import STATE_FILE
    from dozerlab.fields.store import FIELD_STORE, open_store
    from dozerlab.scenarios.bed import Bed

    config = {**TINY_RUN, "solver": {**TINY_RUN["solver"], "iterations": 100}}
    write_tiny_run(tmp_path)  # the same path whatever the solver's sweeps
    base = ["simulate", "--bed", str(tmp_path / "bed.npz"), "--config", json.dumps(config)]
    base += ["--trajectory", str(tmp_path / "speed~0.5_depth~0.06.csv")]
    monkeypatch.setenv("DOZERLAB_MLFLOW", "1")
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.chdir(tmp_path)
    for name, extra in (("ndem", []), ("twin", ["--jitter", "1e-6", "--jitter-seed", "3"])):
        out = ["--out", str(tmp_path / f"{name}.zarr"), "--state", str(tmp_path / f"{name}.npz")]
        assert main([*base, *out, *extra]) == 0, capsys.readouterr().err
    runs = mlflow.search_runs(experiment_names=["dozerlab"], output_format="list")
    tags = {r.data.tags["rule"]: r.data.tags for r in runs}
    assert tags["twin"]["jitter_seed"] == "3" and "jitter_seed" not in tags["simulate"]
    ndem, twin = open_store(tmp_path / "ndem.zarr"), open_store(tmp_path / "twin.zarr")
    assert FIELD_STORE.recognise(tmp_path / "twin.zarr")
    assert STATE_FILE.recognise(tmp_path / "twin.npz")  # a rerun replaces them, as simulate's
    assert (twin.attrs["jitter_m"], twin.attrs["jitter_seed"]) == (1e-6, 3)
    assert "jitter_m" not in ndem.attrs and twin.sizes == ndem.sizes
    # the first row (one 0.01 s step): NDEM's lattice at rest, the twin's settling its µm overlaps
    v0_ndem, v0_twin = ndem["velocity"].values[0], twin["velocity"].values[0]
    assert np.abs(v0_ndem).max() < 1e-12
    assert 1e-7 < np.abs(v0_twin).max() < 1e-6 / 0.01
    ends = Bed.load(tmp_path / "ndem.npz"), Bed.load(tmp_path / "twin.npz")
    assert not np.array_equal(ends[0].positions, ends[1].positions)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--jitter", "0"], "argument --jitter: .*reduced.twin.jitter_m"),
        (["--jitter=-1e-6"], "argument --jitter: .*reduced.twin.jitter_m"),
        (["--jitter", "0.01"], "argument --jitter: .*reduced.twin.jitter_m"),
        (["--jitter", "nan"], "argument --jitter: .*reduced.twin.jitter_m"),
        (
            ["--jitter", "1e-6", "--jitter-seed", "-1"],
            "argument --jitter-seed: .*reduced.twin.seed",
        ),
    ],
)
def test_simulate_refuses_a_jitter_outside_the_configs_bounds(tmp_path, capsys, flags, message):
    argv = ["simulate", "--bed", "b.npz", "--trajectory", "t.csv", "--out", str(tmp_path / "f")]
    with pytest.raises(SystemExit) as exit_:
        main([*argv, *flags])
    assert exit_.value.code == 2
    assert re.search(message, capsys.readouterr().err)
    assert list(tmp_path.iterdir()) == []


def test_simulate_refuses_a_jitter_seed_without_a_jitter(tmp_path, capsys):
    argv = ["simulate", "--bed", "b.npz", "--trajectory", "t.csv", "--out", str(tmp_path / "f")]
    assert main([*argv, "--jitter-seed", "3"]) == 2
    assert "--jitter-seed needs --jitter" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
