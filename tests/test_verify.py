"""``dozerlab verify`` and the checks it shares with the loaders: every damaged byte of every
artifact kind is refused by name, by ``verify`` and by the commands that read the artifact,
never read as changed numbers and never a traceback."""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import xarray as xr
import zarr
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from dozerlab.cli import main
from tests.helpers import TINY_RUN, results_folder


@pytest.fixture(scope="module")
def results(tmp_path_factory) -> dict[str, Path]:
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("DOZERLAB_MLFLOW", "0")
        yield results_folder(tmp_path_factory.mktemp("results"))


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


def run(*argv: str | Path) -> tuple[int, str]:
    """``python -m dozerlab ARGV…`` in this process: its exit status and its stdout + stderr.
    An exception other than the CLI's own refusals propagates: a traceback fails the test."""
    out = io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(out):
        code = main([str(a) for a in argv])
    return code, out.getvalue()


def flip(file: Path, at: int, mask: int = 0x01) -> None:
    data = bytearray(file.read_bytes())
    data[at % len(data)] ^= mask
    file.write_bytes(bytes(data))


def copy(src: Path, folder: Path) -> Path:
    dst = folder / src.name
    (shutil.copytree if src.is_dir() else shutil.copy2)(src, dst)
    return dst


def evaluate(model: Path, store: Path) -> tuple[int, str]:
    return run("evaluate", "--model", model, store)


def trajectory_from(bed: Path, folder: Path) -> tuple[int, str]:
    out = folder / "t.csv"
    code, text = run(
        "trajectory", "--bed", bed, "--speed", "0.5", "--depth", "0.06", "--out", out,
        "--config", json.dumps(TINY_RUN),
    )  # fmt: skip
    assert code != 0 or out.is_file()
    assert code == 0 or not out.exists()
    return code, text


def test_verify_passes_a_whole_results_folder(results):
    root = results["bed"].parents[1]
    code, text = run("verify", root)
    assert code == 0, text
    assert "DAMAGED" not in text and "UNCHECKED" not in text
    assert "verify: 7 checked, 7 whole, 0 damaged, 0 without checksums" in text


def test_verify_names_each_damaged_artifact_in_a_folder_once(results, tmp_path):
    root = copy(results["bed"].parents[1], tmp_path)
    flip(root / "fields" / "a.zarr" / "velocity" / "c" / "0" / "0" / "0" / "0" / "0", 100)
    (root / "models" / "linear" / "artifacts" / "weights.pt").write_bytes(b"")
    code, text = run("verify", root)
    assert code == 1
    damaged = [line for line in text.splitlines() if line.startswith("DAMAGED")]
    assert len(damaged) == 2, text
    assert "fields/a.zarr" in damaged[0] and "array 'velocity'" in damaged[0]
    assert "models/linear" in damaged[1] and "weights.pt is damaged" in damaged[1]
    assert "2 damaged" in text


def test_an_artifact_that_lost_its_metadata_file_is_damaged(results, tmp_path):
    root = copy(results["bed"].parents[1], tmp_path)
    (root / "fields" / "a.zarr" / "zarr.json").unlink()
    (root / "models" / "linear" / "MLmodel").unlink()
    code, text = run("verify", root)
    assert code == 1 and "2 damaged" in text
    assert f"DAMAGED {root / 'fields' / 'a.zarr'}:" in text
    assert f"{root / 'models' / 'linear' / 'MLmodel'} is missing" in text


def test_a_flipped_byte_in_a_compressed_velocity_chunk_is_refused_by_evaluate(results, tmp_path):
    """Read as velocities of 5.6e26 m/s (all finite) and evaluated with exit 0 before."""
    store = copy(results["store"], tmp_path)
    shard = store / "velocity" / "c" / "0" / "0" / "0" / "0" / "0"
    flip(shard, 200, 0x40)
    code, text = evaluate(results["model"], store)
    assert code == 2
    assert f"{store}" in text and "array 'velocity'" in text and "c/0/0/0/0/0" in text
    assert "CRC32C" in text and len(text.strip().splitlines()) == 1


@pytest.mark.parametrize("cut", [0, 100], ids=["empty", "truncated"])
def test_an_empty_or_truncated_weights_file_is_refused_by_name(results, tmp_path, cut):
    """A torch traceback before."""
    model = copy(results["model"], tmp_path)
    weights = model / "artifacts" / "weights.pt"
    weights.write_bytes(weights.read_bytes()[:cut])
    code, text = evaluate(model, results["store"])
    assert code == 2
    assert f"{weights} is damaged" in text and len(text.strip().splitlines()) == 1


def test_model_metadata_that_is_not_json_is_named(results, tmp_path):
    model = copy(results["model"], tmp_path)
    meta = model / "artifacts" / "meta.json"
    meta.write_bytes(b"\x00\xff" + meta.read_bytes()[2:])
    code, text = evaluate(model, results["store"])
    assert code == 2
    assert f"{meta} is not valid JSON" in text and len(text.strip().splitlines()) == 1


def test_a_store_whose_dtype_was_changed_is_named(results, tmp_path):
    store = copy(results["store"], tmp_path)
    meta = store / "density" / "zarr.json"
    meta.write_text(meta.read_text().replace('"float32"', '"float64"'))
    code, text = evaluate(results["model"], store)
    assert code == 2
    assert f"{meta} gives data type 'float64'" in text and len(text.strip().splitlines()) == 1


@pytest.mark.filterwarnings("ignore:Consolidated metadata")
def test_a_store_without_checksums_is_refused_with_the_remedy(results, tmp_path):
    ds = xr.open_zarr(results["store"])
    del ds.attrs["metadata_sha256"]
    old = tmp_path / "old.zarr"
    ds.to_zarr(old, zarr_format=3, consolidated=True)
    code, text = evaluate(results["model"], old)
    assert code == 2 and "written without checksums" in text and "re-run" in text
    code, text = run("verify", old)
    assert code == 1 and text.startswith(f"UNCHECKED {old}")
    assert "1 without checksums" in text


@pytest.mark.parametrize("kind", ["bed", "state"])
@pytest.mark.parametrize("damage", ["truncated", "flipped"])
def test_a_damaged_bed_or_state_is_refused_by_name(results, tmp_path, kind, damage):
    """BadZipFile tracebacks before."""
    bed = copy(results[kind], tmp_path)
    if damage == "truncated":
        bed.write_bytes(bed.read_bytes()[:-300])
    else:
        flip(bed, 1000)
    code, text = trajectory_from(bed, tmp_path)
    assert code == 2 and f"{bed} is damaged" in text and len(text.strip().splitlines()) == 1
    assert run("verify", bed)[0] == 1


def test_a_bed_with_a_nan_position_is_refused_and_never_written(results, tmp_path):
    """Accepted, and a trajectory written from it, before."""
    from dozerlab.scenarios.bed import Bed

    bed = Bed.load(results["bed"])
    bed.positions[7, 2] = np.nan
    with pytest.raises(
        ValueError, match=r"nan.npz: 'positions' holds 1 NaN/inf value\(s\), first in row 7"
    ):
        bed.save(tmp_path / "nan.npz")
    assert not (tmp_path / "nan.npz").exists()
    arrays = dict(np.load(results["bed"], allow_pickle=False))
    arrays["positions"][7, 2] = np.nan
    np.savez(tmp_path / "nan.npz", **arrays)  # as another program would
    code, text = trajectory_from(tmp_path / "nan.npz", tmp_path)
    assert code == 2 and "'positions' holds 1 NaN/inf" in text


def test_a_changed_trajectory_row_is_refused_by_name(results, tmp_path):
    traj = copy(results["trajectory"], tmp_path)
    lines = traj.read_text().splitlines()
    cells = lines[5].split(",")
    cells[2] = repr(float(cells[2]) + 1e-3)  # x of step 4
    lines[5] = ",".join(cells)
    traj.write_text("\n".join(lines) + "\n")
    code, text = run("verify", traj)
    assert code == 1 and f"{traj} is damaged: its bytes differ from the SHA-256" in text
    traj.write_text("\n".join(lines[:-1]) + "\n")  # without its checksum line
    code, text = run("verify", traj)
    assert code == 1 and f"{traj} has no '# sha256' line at its end" in text


# The property: random damage to every artifact kind.

#: Artifact kind → (the artifact in the results folder, the file inside it to damage).
TARGETS = {
    "compressed store chunk": ("store", "velocity/c/1/0/0/0/0"),
    "uncompressed store chunk": ("store", "force/c/0/0"),
    "store time chunk": ("store", "time/c/0"),
    "store attributes (JSON)": ("store", "zarr.json"),
    "store array metadata (JSON)": ("store", "density/zarr.json"),
    "bed": ("bed", ""),
    "state": ("state", ""),
    "trajectory": ("trajectory", ""),
    "model weights": ("model", "artifacts/weights.pt"),
    "model metadata (JSON)": ("model", "artifacts/meta.json"),
    "MLmodel": ("model", "MLmodel"),
}


def _content(kind: str, path: Path) -> Any:
    """What a reader gets from an artifact: equal for two artifacts with the same numbers."""
    if kind == "store":
        group = zarr.open_group(path, mode="r")
        return dict(group.attrs), {n: a[...] for n, a in group.arrays()}
    if kind in ("bed", "state"):
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    if kind == "trajectory":
        return np.loadtxt(path, delimiter=",", skiprows=1)
    meta = json.loads((path / "artifacts" / "meta.json").read_text())
    return meta, (path / "artifacts" / "weights.pt").read_bytes(), (path / "MLmodel").read_bytes()


def _equal(a: Any, b: Any) -> bool:
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_equal(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_equal(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return bool(a == b)


def _reader(kind: str, results: dict[str, Path]) -> Callable[[Path, Path], tuple[int, str]]:
    """The command that reads an artifact of ``kind`` (given it and a scratch folder)."""
    if kind == "store":
        return lambda p, _: evaluate(results["model"], p)
    if kind == "model":
        return lambda p, _: evaluate(p, results["store"])
    if kind in ("bed", "state"):
        return trajectory_from
    return lambda p, _: run("verify", p)


damage = st.one_of(
    st.tuples(st.just("flip"), st.integers(0, 2**31), st.integers(1, 255)),
    st.tuples(st.just("cut"), st.floats(0.0, 0.999), st.just(0)),
)


@pytest.mark.parametrize("target", list(TARGETS))
@settings(
    max_examples=8,
    deadline=None,
    derandomize=True,
    suppress_health_check=[HealthCheck.function_scoped_fixture],
)
@given(how=damage)
def test_random_damage_is_refused_naming_the_path_or_changes_no_number(results, target, how):
    kind, inside = TARGETS[target]
    with tempfile.TemporaryDirectory() as tmp:
        artifact = copy(results[kind], Path(tmp))
        file = artifact / inside if inside else artifact
        op, where, mask = how
        if op == "flip":
            flip(file, where, mask)
        else:
            file.write_bytes(file.read_bytes()[: int(where * file.stat().st_size)])
        code, text = run("verify", artifact)
        read_code, read_text = _reader(kind, results)(artifact, Path(tmp))
        if code == 0:  # the damage changed nothing a reader sees (JSON whitespace, a zip date)
            assert _equal(_content(kind, artifact), _content(kind, results[kind])), text
            assert read_code == 0, read_text
        else:
            assert code == 1 and f"DAMAGED {artifact}:" in text, text
            assert read_code != 0 and str(artifact) in read_text, read_text
            assert "Traceback" not in read_text
