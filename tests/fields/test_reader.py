"""The fast field reader gives exactly what zarr gives, and refuses corrupt shards."""

from __future__ import annotations

import numpy as np
import pytest
import zarr
from zarr.codecs import BloscCodec, Crc32cCodec

from dozerlab.fields.reader import (
    DamagedStoreError,
    UncheckedStoreError,
    damaged_pieces,
    read_field,
)
from dozerlab.fields.store import write_store

WINDOWS = [
    (0, None),
    (0, 1),
    (3, 21),
    (8, 16),
    (60, 70),
    (63, 66),
    (69, None),
    (-5, None),
    (40, 30),
]


@pytest.mark.parametrize("codec", ["default", "none"])
@pytest.mark.parametrize("threads", [1, 2])
def test_read_field_equals_zarr(tmp_path, store_arrays, codec, threads):
    options = {} if codec == "default" else {"codec": ()}
    path = write_store(
        tmp_path / "f.zarr", chunk_steps=16, inner_steps=4, **options, **store_arrays
    )
    for name in ("velocity", "density", "force", "time"):
        arr = zarr.open_array(path / name, mode="r")
        for start, stop in WINDOWS:
            got = read_field(path, name, start, stop, threads=threads)
            want = arr[slice(start, stop)]
            assert got.shape == want.shape and got.dtype == want.dtype
            np.testing.assert_array_equal(got, want)
    np.testing.assert_array_equal(read_field(path, "velocity"), store_arrays["velocity"])


@pytest.mark.parametrize(
    "compressors",
    [[Crc32cCodec()], [BloscCodec(), Crc32cCodec()]],
    ids=["fast path", "through zarr"],
)
def test_unwritten_chunks_are_refused_not_read_as_fill(tmp_path, compressors):
    """zarr reads an absent chunk as its fill value; our stores write every chunk, so an absent
    one is damage (a lost file), named with its steps."""
    arr = zarr.create_array(
        tmp_path / "a",
        shape=(20, 2, 3),
        shards=(8, 2, 3),
        chunks=(4, 2, 3),
        dtype="f4",
        fill_value=0.0,
        compressors=compressors,
    )
    arr[9:11] = 5.0  # touches inner chunks 2 and 3 only; the rest of the shards stay unwritten
    with pytest.raises(DamagedStoreError, match=r"array 'a' is damaged.*(steps 0-7|steps 12-15)"):
        read_field(tmp_path, "a")
    missing = damaged_pieces(tmp_path, "a")
    assert "chunk c/0/0/0 (steps 0-7) is missing" in missing
    assert "inner chunk 1 of shard c/1/0/0 (steps 12-15) is missing" in missing


def test_nan_in_a_field_is_refused_naming_the_step(tmp_path, store_arrays):
    store_arrays["density"][33, 1, 2, 0] = np.nan
    path = write_store(tmp_path / "f.zarr", chunk_steps=16, **store_arrays)
    with pytest.raises(DamagedStoreError, match=r"array 'density'.*NaN/inf.*step 33"):
        read_field(path, "density")
    np.testing.assert_array_equal(read_field(path, "density", 0, 32), store_arrays["density"][:32])


def test_corrupt_shard_index_is_refused(tmp_path, store_arrays):
    path = write_store(tmp_path / "f.zarr", chunk_steps=64, **store_arrays)
    shard = path / "velocity" / "c" / "0" / "0" / "0" / "0" / "0"
    data = bytearray(shard.read_bytes())
    data[-10] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(ValueError, match="CRC32C"):
        read_field(path, "velocity")
    shard.write_bytes(bytes(data[:10]))
    with pytest.raises(ValueError, match="shorter than its index"):
        read_field(path, "velocity")


def test_missing_array_is_named(tmp_path, store_arrays):
    path = write_store(tmp_path / "f.zarr", **store_arrays)
    with pytest.raises(FileNotFoundError, match="no array 'pressure'"):
        read_field(path, "pressure")


@pytest.mark.parametrize("codec", ["default", "none"])
def test_a_flipped_byte_in_a_field_chunk_is_refused_naming_array_and_chunk(
    tmp_path, store_arrays, codec
):
    """A flip inside a compressed chunk decoded to finite velocities of 1e26 m/s; the CRC32C of
    every inner chunk refuses it before decoding, naming the array, the chunk and its steps."""
    options = {} if codec == "default" else {"codec": ()}
    path = write_store(
        tmp_path / "f.zarr", chunk_steps=16, inner_steps=4, **options, **store_arrays
    )
    shard = path / "velocity" / "c" / "1" / "0" / "0" / "0" / "0"
    data = bytearray(shard.read_bytes())
    data[40] ^= 0x10  # inside inner chunk 0 of shard 1 (steps 16-19)
    shard.write_bytes(bytes(data))
    with pytest.raises(
        DamagedStoreError,
        match=r"array 'velocity' is damaged: inner chunk 0 of shard .*c/1/0/0/0/0 "
        r"\(steps 16-19\) fails its CRC32C checksum",
    ):
        read_field(path, "velocity")
    assert damaged_pieces(path, "velocity") == [
        "inner chunk 0 of shard c/1/0/0/0/0 (steps 16-19) fails its CRC32C checksum"
    ]
    np.testing.assert_array_equal(
        read_field(path, "velocity", 0, 16), store_arrays["velocity"][:16]
    )


def test_an_array_without_checksums_is_refused(tmp_path):
    arr = zarr.create_array(tmp_path / "a", shape=(4, 2), dtype="f4", compressors=None)
    arr[:] = 1.0
    with pytest.raises(
        UncheckedStoreError, match=r"array 'a' was written without checksums.*re-run"
    ):
        read_field(tmp_path, "a")
