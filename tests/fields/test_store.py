"""The zarr field store: schema, round trip, atomicity, validation."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr
import zarr

from dozerlab.fields.store import SCHEMA, FieldStoreWriter, open_store, write_store


def test_store_round_trip_opens_in_xarray_with_documented_names(tmp_path, store_arrays):
    path = write_store(tmp_path / "f.zarr", chunk_steps=64, **store_arrays)
    ds = xr.open_zarr(path)
    for name, dims in SCHEMA.items():
        assert ds[name].dims == dims
        assert ds[name].dtype == np.float32
        np.testing.assert_array_equal(ds[name].values, store_arrays[name])
    np.testing.assert_array_equal(ds["time"].values, store_arrays["time"])
    assert [str(c) for c in ds["component"].values] == ["x", "y", "z"]
    np.testing.assert_allclose(ds["x"].values, store_arrays["x"], rtol=1e-6)
    assert ds.attrs["scenario"] == "hill" and ds.attrs["bins"] == [4, 3, 2]
    assert float(ds["force"].sel(component="y")[3]) == pytest.approx(store_arrays["force"][3, 1])
    open_store(path)


def test_writer_buffers_one_chunk(tmp_path, store_arrays):
    a = store_arrays
    with FieldStoreWriter(
        tmp_path / "f.zarr", x=a["x"], y=a["y"], z=a["z"], attrs=a["attrs"], chunk_steps=8
    ) as w:
        for i in range(10):
            w.append(
                a["time"][i],
                a["velocity"][i],
                a["density"][i],
                a["force"][i],
                a["torque"][i],
                a["blade_velocity"][i],
                a["blade_position"][i],
            )
        assert w.steps == 8  # the first chunk was written, the rest is buffered
        assert not (tmp_path / "f.zarr").exists()  # only the temporary exists until close
    arr = zarr.open_array(tmp_path / "f.zarr" / "velocity", mode="r")
    assert arr.shape[0] == 10 and arr.shards[0] == 8


def test_failed_write_leaves_nothing(tmp_path, store_arrays):
    a = store_arrays
    writer = FieldStoreWriter(tmp_path / "f.zarr", x=a["x"], y=a["y"], z=a["z"], attrs={})

    def write_then_fail() -> None:
        with writer as w:
            w.append(0.0, a["velocity"][0], a["density"][0], *(np.zeros(3),) * 4)
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        write_then_fail()
    assert list(tmp_path.iterdir()) == []


def test_append_rejects_wrong_shape(tmp_path, store_arrays):
    a = store_arrays
    with (
        pytest.raises(ValueError, match=r"density must have shape \(4, 3, 2\)"),
        FieldStoreWriter(tmp_path / "f.zarr", x=a["x"], y=a["y"], z=a["z"], attrs={}) as w,
    ):
        w.append(0.0, a["velocity"][0], np.zeros((4, 3)), *(np.zeros(3),) * 4)
    assert not (tmp_path / "f.zarr").exists()


@pytest.mark.filterwarnings("ignore:Consolidated metadata")
def test_open_store_names_what_is_missing(tmp_path, store_arrays):
    a = dict(store_arrays)
    a["attrs"] = {"scenario": "hill"}
    path = write_store(tmp_path / "f.zarr", **a)
    with pytest.raises(ValueError, match=r"missing attributes \['speed'"):
        open_store(path)
    ds = xr.open_zarr(path).drop_vars("torque").rename({"force": "blade_force"})
    ds.to_zarr(tmp_path / "g.zarr", zarr_format=3, consolidated=True)
    with pytest.raises(ValueError, match=r"missing variable 'force'.*missing variable 'torque'"):
        open_store(tmp_path / "g.zarr")
