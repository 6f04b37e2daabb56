"""Field plots and the plot-fields / legacy commands."""

from __future__ import annotations

import numpy as np
from PIL import Image

from dozerlab.cli import main
from dozerlab.fields.store import write_store


def test_plot_fields_command_writes_slices_force_and_gif(tmp_path, store_arrays):
    store = write_store(tmp_path / "f.zarr", **store_arrays)
    assert (
        main(
            [
                "plot-fields",
                str(store),
                "--out",
                str(tmp_path / "plots"),
                "--steps",
                "0",
                "69",
                "--frames",
                "12",
            ]
        )
        == 0
    )
    names = sorted(p.name for p in (tmp_path / "plots").iterdir())
    assert names == ["fields.gif", "force.png", "slice_000000.png", "slice_000069.png"]
    with Image.open(tmp_path / "plots" / "fields.gif") as gif:
        assert gif.n_frames == 12
    assert main(["plot-fields", str(store), "--out", str(tmp_path / "p2"), "--steps", "70"]) == 2


def test_legacy_commands_round_trip(tmp_path, store_arrays):
    a = dict(store_arrays)
    a["attrs"] = a["attrs"] | {"bin_size": [0.1, 0.2, 0.1]}
    store = write_store(tmp_path / "f.zarr", **a)
    assert main(["export-legacy", str(store), str(tmp_path / "f.bin")]) == 0
    assert (
        main(
            [
                "import-legacy",
                str(tmp_path / "f.bin"),
                str(tmp_path / "g.zarr"),
                "--lower",
                "0",
                "-0.3",
                "-0.1",
            ]
        )
        == 0
    )
    import xarray as xr

    ds = xr.open_zarr(tmp_path / "g.zarr")
    np.testing.assert_array_equal(ds["velocity"].values, a["velocity"])
    np.testing.assert_allclose(ds["y"].values, [-0.2, 0.0, 0.2], atol=1e-7)
    (tmp_path / "bad.bin").write_bytes(b"\0" * 30)
    assert main(["import-legacy", str(tmp_path / "bad.bin"), str(tmp_path / "h.zarr")]) == 2
    assert not (tmp_path / "h.zarr").exists()
