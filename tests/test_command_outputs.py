"""``python -m dozerlab``: every command that writes refuses to replace what it did not write."""

from __future__ import annotations

import json

import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.fields.store import ATTRS, write_store


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


@pytest.fixture
def store(tmp_path):
    """A tiny field store of ours (20 steps on a 3×2×2 grid)."""
    rng = np.random.default_rng(0)
    t, grid = 20, (3, 2, 2)
    vec = lambda: rng.normal(size=(t, 3)).astype(np.float32)  # noqa: E731
    attrs = dict.fromkeys(ATTRS) | {
        "scenario": "hill",
        "bins": list(grid),
        "bin_size": [0.1, 0.1, 0.1],
        "dozerlab_version": "test",
    }
    return write_store(
        tmp_path / "in" / "store.zarr",
        x=np.array([0.05, 0.15, 0.25]),
        y=np.array([-0.05, 0.05]),
        z=np.array([0.05, 0.15]),
        time=np.arange(1, t + 1) * 0.01,
        velocity=rng.normal(size=(t, *grid, 3)).astype(np.float32),
        density=rng.uniform(0, 2600, size=(t, *grid)).astype(np.float32),
        force=vec(),
        torque=vec(),
        blade_velocity=vec(),
        blade_position=vec(),
        attrs=attrs,
        chunk_steps=8,
    )


def _argv(command: str, store, tmp_path, out: str) -> list[str]:
    legacy = tmp_path / "in" / "store.bin"
    if command == "import-legacy":
        assert main(["export-legacy", str(store), str(legacy)]) == 0
    return {
        "report": ["report", "--results", str(tmp_path / "results"), "--out", out],
        "import-legacy": ["import-legacy", str(legacy), out],
        "export-legacy": ["export-legacy", str(store), out],
        "plot-fields": ["plot-fields", str(store), "--out", out, "--no-animation"],
        "bed": ["bed", "--scenario", "hill", "--out", out],
        "trajectory": [
            "trajectory",
            "--bed",
            "b.npz",
            "--speed",
            "1",
            "--depth",
            "0.1",
            "--out",
            out,
        ],
        "simulate": ["simulate", "--bed", "b.npz", "--trajectory", "t.csv", "--out", out],
        "train": ["train", "--model", "linear", "--train", str(store), "--out", out],
        "validate": ["validate", "--model", str(tmp_path / "m"), "--out", out],
    }[command]


COMMANDS = [
    "report",
    "import-legacy",
    "export-legacy",
    "plot-fields",
    "bed",
    "trajectory",
    "simulate",
    "train",
    "validate",
]


@pytest.mark.parametrize("command", COMMANDS)
def test_an_unrelated_directory_at_out_survives(command, store, tmp_path, capsys):
    """The reproduced data loss: `--out results` (or any directory of the user's) was deleted."""
    out = tmp_path / "results"
    (out / "beds").mkdir(parents=True)
    (out / "beds" / "hill.npz").write_bytes(b"a week of settling")
    (out / "notes.txt").write_text("mine")
    # plot-fields writes into its directory: a foreign file where a figure goes is refused.
    (out / "force.png").write_bytes(b"\x89PNG\r\n\x1a\n a user's figure")
    argv = _argv(command, store, tmp_path, str(out))
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"dozerlab {command}: error: refusing to replace {out}" in err
    assert "left untouched" in err and "Traceback" not in err
    assert (out / "beds" / "hill.npz").read_bytes() == b"a week of settling"
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "force.png").read_bytes() == b"\x89PNG\r\n\x1a\n a user's figure"
    assert not list(tmp_path.rglob(".*tmp-*"))


@pytest.mark.parametrize(
    ("command", "name"),
    [
        ("report", "index.html"),
        ("import-legacy", "imported.zarr"),
        ("export-legacy", "exported.bin"),
        ("plot-fields", "plots"),
    ],
)
def test_its_own_output_is_replaced(command, name, store, tmp_path):
    out = tmp_path / "out" / name
    argv = _argv(command, store, tmp_path, str(out))
    assert main(argv) == 0
    first = sorted(p.name for p in out.iterdir()) if out.is_dir() else None
    # the legacy format has no room for a mark: only --overwrite replaces an existing file
    assert main(argv + ["--overwrite"] if command == "export-legacy" else argv) == 0
    assert (sorted(p.name for p in out.iterdir()) if out.is_dir() else None) == first
    assert not list(out.parent.glob(".*tmp-*"))


def test_a_validation_json_of_another_tool_is_refused(tmp_path, capsys):
    out = tmp_path / "linear.json"
    out.write_text(json.dumps({"accuracy": 0.9}))
    assert main(["validate", "--model", str(tmp_path / "m"), "--out", str(out)]) == 2
    assert "not a dozerlab validation JSON" in capsys.readouterr().err
    assert json.loads(out.read_text()) == {"accuracy": 0.9}
