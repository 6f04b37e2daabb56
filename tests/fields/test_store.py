"""The zarr field store: schema, round trip, atomicity, validation."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import zarr
from zarr.core import sync as zarr_sync

from dozerlab.fields.reader import DamagedStoreError, UncheckedStoreError
from dozerlab.fields.store import SCHEMA, UNITS, FieldStoreWriter, open_store, write_store
from dozerlab.learn.data import load_store


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
    group = zarr.open_group(path, mode="r")
    assert {name: group[name].attrs["units"] for name in UNITS} == UNITS
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


@pytest.mark.parametrize("announced", [70, 90, 50])
def test_a_writer_told_its_steps_holds_exactly_what_was_appended(tmp_path, store_arrays, announced):
    # made 70 steps long at once; made longer and cut at close; made shorter and grown
    a = store_arrays
    with FieldStoreWriter(
        tmp_path / "f.zarr",
        x=a["x"],
        y=a["y"],
        z=a["z"],
        attrs=a["attrs"],
        chunk_steps=64,
        steps=announced,
    ) as w:
        for i in range(70):
            w.append(a["time"][i], *(a[name][i] for name in SCHEMA))
    ds = open_store(tmp_path / "f.zarr")
    assert ds.sizes["time"] == 70
    for name in SCHEMA:
        np.testing.assert_array_equal(ds[name].values, a[name])
    np.testing.assert_array_equal(ds["time"].values, a["time"])
    with pytest.raises(ValueError, match="steps must be >= 0"):
        FieldStoreWriter(tmp_path / "g.zarr", x=a["x"], y=a["y"], z=a["z"], attrs={}, steps=-1)


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


def test_a_write_still_in_flight_is_waited_for_before_the_temporary_goes(tmp_path, store_arrays):
    """A signal that ends the wait for a zarr write (SIGTERM raising SystemExit) leaves the write
    running on zarr's IO thread: the temporary must go only once it is done, or it comes back."""
    a = store_arrays
    writer = FieldStoreWriter(tmp_path / "f.zarr", x=a["x"], y=a["y"], z=a["z"], attrs={})

    def interrupted_mid_write() -> None:
        with writer:
            (tmp,) = tmp_path.glob(".f.zarr.tmp-*")

            async def chunk_write() -> None:  # as zarr's local store writes: parents made
                await asyncio.sleep(0.3)
                (tmp / "density" / "c").mkdir(parents=True, exist_ok=True)
                (tmp / "density" / "c" / "0").write_bytes(b"late")

            asyncio.run_coroutine_threadsafe(chunk_write(), zarr_sync._get_loop())
            raise SystemExit(143)

    with pytest.raises(SystemExit):
        interrupted_mid_write()
    time.sleep(0.5)
    assert list(tmp_path.iterdir()) == []


def test_a_write_in_flight_when_the_closing_flush_is_interrupted_is_waited_for(
    tmp_path, store_arrays, monkeypatch
):
    """The signal may land in the block's closing work (the last rows' write): the temporary
    goes then too only once the write in flight is done (a killed workflow's simulate job left
    one behind, the CI of d474424)."""
    from dozerlab.fields import store

    a = store_arrays
    writer = FieldStoreWriter(tmp_path / "f.zarr", x=a["x"], y=a["y"], z=a["z"], attrs={})

    write_all = store._write_all

    def interrupted(parts, start=None) -> None:
        if start is None:  # the empty store's metadata, made on entering
            write_all(parts, start)
            return
        (tmp,) = tmp_path.glob(".f.zarr.tmp-*")

        async def chunk_write() -> None:
            await asyncio.sleep(0.3)
            (tmp / "density" / "c").mkdir(parents=True, exist_ok=True)
            (tmp / "density" / "c" / "0").write_bytes(b"late")

        asyncio.run_coroutine_threadsafe(chunk_write(), zarr_sync._get_loop())
        raise SystemExit(143)

    monkeypatch.setattr(store, "_write_all", interrupted)
    with pytest.raises(SystemExit), writer:
        writer.append(0.0, *(a[k][0] for k in SCHEMA))
    time.sleep(0.5)
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
    del ds.attrs["metadata_sha256"]  # another tool's store: the schema is named first
    ds.to_zarr(tmp_path / "g.zarr", zarr_format=3, consolidated=True)
    with pytest.raises(ValueError, match=r"missing variable 'force'.*missing variable 'torque'"):
        open_store(tmp_path / "g.zarr")


@pytest.mark.parametrize(
    ("name", "chunk"),
    [
        ("velocity", "c/1/0/0/0/0"),
        ("density", "c/0/0/0/0"),
        ("force", "c/2/0"),
        ("blade_position", "c/0/0"),
        ("time", "c/1"),
    ],
)
def test_a_lost_chunk_is_refused_naming_array_and_piece(tmp_path, store_arrays, name, chunk):
    """zarr would read the lost chunk as zeros (its fill value); the store refuses to open."""
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    (path / name / chunk).unlink()
    with pytest.raises(DamagedStoreError, match=rf"damaged.*array '{name}': chunk {chunk} \(steps"):
        open_store(path)
    with pytest.raises(DamagedStoreError, match=f"array '{name}'"):
        load_store(path)


def test_empty_chunks_are_written_so_zeros_are_not_damage(tmp_path, store_arrays):
    store_arrays["force"][:40] = 0.0  # the blade before it meets the bed
    store_arrays["density"][:] = 0.0
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    ds = open_store(path)
    assert not ds["force"].values[:32].any()
    assert (path / "force" / "c" / "0" / "0").is_file()


def test_time_must_increase_and_series_be_finite(tmp_path, store_arrays):
    a = dict(store_arrays, time=store_arrays["time"].copy())
    a["time"][40] = a["time"][39]
    with pytest.raises(DamagedStoreError, match=r"'time' is not strictly increasing: step 40"):
        open_store(write_store(tmp_path / "t.zarr", **a))
    a = dict(store_arrays, torque=store_arrays["torque"].copy())
    a["torque"][12, 2] = np.inf
    with pytest.raises(
        DamagedStoreError, match=r"'torque' holds 1 NaN/inf value\(s\), first at step 12"
    ):
        open_store(write_store(tmp_path / "q.zarr", **a))


def _flip(file: Path, at: int) -> None:
    data = bytearray(file.read_bytes())
    data[at] ^= 0x01
    file.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("name", "chunk", "at"),
    [
        ("velocity", "c/1/0/0/0/0", 30),  # compressed shard: an inner chunk
        ("density", "c/0/0/0/0", 20),
        ("force", "c/0/0", 7),  # uncompressed
        ("time", "c/1", 3),
        ("x", "c/0", 1),
        ("component", "c/0", 2),
    ],
)
def test_a_flipped_byte_in_any_chunk_is_refused_naming_array_and_chunk(
    tmp_path, store_arrays, name, chunk, at
):
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    _flip(path / name / chunk, at)
    with pytest.raises(
        DamagedStoreError, match=rf"f.zarr is damaged.*array '{name}': .*{chunk}.* fails its CRC32C"
    ):
        open_store(path)


@pytest.mark.parametrize(
    ("file", "old", "new", "match"),
    [
        (
            "velocity/zarr.json",
            '"float32"',
            '"float64"',
            r"velocity/zarr.json gives data type 'float64'",
        ),
        (
            "force/zarr.json",
            '"shape": [\n    70',
            '"shape": [\n    60',
            r"force/zarr.json is damaged: array 'force'",
        ),
        (
            "zarr.json",
            '"speed": null',
            '"speed": 1.5',
            r"f.zarr/zarr.json is damaged: the store's attributes",
        ),
    ],
)
def test_changed_metadata_is_refused_naming_the_file(tmp_path, store_arrays, file, old, new, match):
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    text = (path / file).read_text()
    assert old in text
    (path / file).write_text(text.replace(old, new, 1))
    with pytest.raises(ValueError, match=match):
        open_store(path)


@pytest.mark.filterwarnings("ignore:Consolidated metadata")
def test_a_store_without_checksums_is_refused_with_the_remedy(tmp_path, store_arrays):
    """A store of a dozerlab older than checksums cannot be told from a damaged one."""
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    old = tmp_path / "old.zarr"
    ds = xr.open_zarr(path)
    del ds.attrs["metadata_sha256"]
    ds.to_zarr(old, zarr_format=3, consolidated=True)
    with pytest.raises(
        UncheckedStoreError, match=r"old.zarr was written without checksums.*re-run"
    ):
        open_store(old)


def test_the_group_document_not_json_is_named(tmp_path, store_arrays):
    path = write_store(tmp_path / "f.zarr", chunk_steps=32, **store_arrays)
    _flip(path / "zarr.json", 0)
    with pytest.raises(DamagedStoreError, match=r"f.zarr/zarr.json is not readable zarr metadata"):
        open_store(path)
