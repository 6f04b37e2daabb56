"""The fields layer's commands: defaults and flags of plot-fields and import-legacy, and inputs
that are missing or bad named in a one-line error (exit 2)."""

from __future__ import annotations

import json

import numpy as np
import pytest
import xarray as xr

from dozerlab.cli import main
from dozerlab.fields.store import write_store
from dozerlab.runtime import FOLDER_MARK
from tests.helpers import TINY_RUN


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
