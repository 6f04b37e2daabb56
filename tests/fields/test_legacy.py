"""The thesis's binary format: round trips and refusal of damaged files."""

from __future__ import annotations

import numpy as np
import pytest

from dozerlab.fields.legacy import HEADER_BYTES, export_legacy, import_legacy, read_header
from dozerlab.fields.store import open_store, write_store


@pytest.fixture
def legacy_file(tmp_path, store_arrays):
    a = dict(store_arrays)
    a["attrs"] = a["attrs"] | {"bin_size": [0.1, 0.2, 0.1]}
    store = write_store(tmp_path / "orig.zarr", **a)
    return export_legacy(store, tmp_path / "orig.bin")


def test_export_has_the_documented_layout(legacy_file, store_arrays):
    raw = legacy_file.read_bytes()
    t, nbins = 70, 4 * 3 * 2
    assert len(raw) == 4 * (6 + t * (10 + 4 * nbins))
    assert np.frombuffer(raw[:12], "<i4").tolist() == [4, 3, 2]
    words = np.frombuffer(raw[HEADER_BYTES:], "<f4").reshape(t, 10 + 4 * nbins)
    step = 5
    np.testing.assert_array_equal(words[step, 1:4], store_arrays["force"][step])
    cells = words[step, 10:].reshape(4, 3, 2, 4)  # x-major, z fastest
    np.testing.assert_array_equal(cells[2, 1, 0, :3], store_arrays["velocity"][step, 2, 1, 0])
    np.testing.assert_array_equal(cells[2, 1, 1, 3], store_arrays["density"][step, 2, 1, 1])


def test_export_import_round_trip_is_identical(tmp_path, legacy_file, store_arrays):
    ds = open_store(import_legacy(legacy_file, tmp_path / "back.zarr", chunk_steps=16))
    for name in ("velocity", "density", "force", "torque", "blade_velocity"):
        np.testing.assert_array_equal(ds[name].values, store_arrays[name])
    np.testing.assert_array_equal(ds["time"].values, store_arrays["time"].astype(np.float32))
    # blade position integrated from the velocity, from zero
    v, t = store_arrays["blade_velocity"], ds["time"].values
    np.testing.assert_allclose(
        ds["blade_position"].values[2], v[0] * (t[1] - t[0]) + v[1] * (t[2] - t[1]), rtol=1e-5
    )
    assert ds.attrs["bins"] == [4, 3, 2]
    # and back again, byte for byte
    again = export_legacy(tmp_path / "back.zarr", tmp_path / "again.bin")
    assert again.read_bytes() == legacy_file.read_bytes()


def test_truncated_file_is_refused_and_leaves_no_store(tmp_path, legacy_file):
    cut = tmp_path / "cut.bin"
    record = 4 * (10 + 4 * 24)
    cut.write_bytes(legacy_file.read_bytes()[: HEADER_BYTES + 3 * record + 17])
    with pytest.raises(
        ValueError, match=rf"truncated at step 3: .* byte offset {HEADER_BYTES + 3 * record}"
    ):
        import_legacy(cut, tmp_path / "cut.zarr")
    assert not (tmp_path / "cut.zarr").exists()
    (tmp_path / "head.bin").write_bytes(b"\x01\x00")
    with pytest.raises(ValueError, match="truncated header"):
        read_header(tmp_path / "head.bin")


def test_inconsistent_file_is_refused(tmp_path, legacy_file):
    raw = bytearray(legacy_file.read_bytes())
    bad_header = tmp_path / "bins.bin"
    bad_header.write_bytes(np.array([4, -3, 2], "<i4").tobytes() + raw[12:])
    with pytest.raises(ValueError, match="bin counts"):
        import_legacy(bad_header, tmp_path / "x.zarr")
    record = 4 * (10 + 4 * 24)
    raw[HEADER_BYTES + 10 * record : HEADER_BYTES + 10 * record + 4] = np.array(
        [-1.0], "<f4"
    ).tobytes()
    bad_time = tmp_path / "time.bin"
    bad_time.write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=f"step 10 \\(byte offset {HEADER_BYTES + 10 * record}\\)"):
        import_legacy(bad_time, tmp_path / "y.zarr")
    assert not (tmp_path / "x.zarr").exists() and not (tmp_path / "y.zarr").exists()


def test_nan_cells_and_header_only_files_are_refused(tmp_path, legacy_file):
    raw = bytearray(legacy_file.read_bytes())
    record = 4 * (10 + 4 * 24)
    cell = HEADER_BYTES + 5 * record + 4 * (10 + 4 * 7 + 3)  # step 5, bin 7's density
    raw[cell : cell + 4] = np.array([np.nan], "<f4").tobytes()
    (tmp_path / "nan.bin").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=r"step 5 .* NaN/inf in cells at bin \(1, 0, 1\)"):
        import_legacy(tmp_path / "nan.bin", tmp_path / "nan.zarr")
    assert not (tmp_path / "nan.zarr").exists()
    (tmp_path / "empty.bin").write_bytes(bytes(raw[:HEADER_BYTES]))
    with pytest.raises(ValueError, match=r"header .* but no steps"):
        import_legacy(tmp_path / "empty.bin", tmp_path / "empty.zarr")
    assert not (tmp_path / "empty.zarr").exists()
