"""``python -m dozerlab``: every output is checked before the work, only what the same command
wrote is replaced, a refused or failed command leaves nothing, and names stay names
(:func:`dozerlab.runtime.job_outputs`, :func:`dozerlab.runtime.check_name`)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from dozerlab.cli import main
from dozerlab.fields.legacy import export_legacy
from dozerlab.runtime import DozerlabError
from tests.helpers import TINY_RUN, write, write_tiny_run


@pytest.fixture(autouse=True)
def _no_mlflow(monkeypatch):
    monkeypatch.setenv("DOZERLAB_MLFLOW", "0")


@pytest.fixture
def store(tmp_path):
    """A small NDEM field store of ours (written as ``simulate`` writes it)."""
    return write(tmp_path / "in" / "ndem.zarr", 1.0, 0.1, steps=12)


def snapshot(root: Path) -> dict[str, bytes | None]:
    """Every entry under ``root`` and the bytes of its files: what a refusal must not change."""
    return {
        str(p.relative_to(root)): p.read_bytes() if p.is_file() else None
        for p in sorted(root.rglob("*"))
    }


def refused(argv: list[str], capsys, *expected: str) -> str:
    """Run the command, assert exit 2 with one error line holding ``expected``; return it."""
    capsys.readouterr()
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err
    (line,) = err.strip().splitlines()
    assert line.startswith(f"dozerlab {argv[0]}: error: ")
    for text in expected:
        assert text in line, line
    return line


def model_dir(path: Path, evolution: bool) -> Path:
    """A model directory as ``train`` (``evolution`` False) or ``train-dynamics`` writes one."""
    (path / "artifacts").mkdir(parents=True)
    (path / "MLmodel").write_text("flavors: {}\n")
    (path / "artifacts" / "weights.pt").write_bytes(b"weights")
    meta = {"kind": "ridge" if evolution else "linear", "grid": [8, 6, 4]}
    (path / "artifacts" / "meta.json").write_text(
        json.dumps(meta | ({"horizon": 4} if evolution else {}))
    )
    return path


def users_folder(path: Path) -> Path:
    path.mkdir(parents=True)
    (path / "keep.txt").write_text("a user's notes")
    return path


# 1. Nothing replaced that the command did not write itself.


def test_export_legacy_refuses_a_users_thesis_file_unless_overwrite(store, tmp_path, capsys):
    thesis = tmp_path / "thesis_run7.bin"
    ours = export_legacy(store, tmp_path / "ours.bin").read_bytes()
    record = (len(ours) - 24) // 12
    thesis.write_bytes(ours[:24] + bytes(record))  # a user's run in the thesis format: 1 step
    before = thesis.read_bytes()
    refused(["export-legacy", str(store), str(thesis)], capsys, str(thesis), "--overwrite")
    assert thesis.read_bytes() == before
    assert main(["export-legacy", str(store), str(thesis), "--overwrite"]) == 0
    assert thesis.read_bytes() == ours
    notes = tmp_path / "notes.bin"
    notes.write_bytes(b"not a legacy field file")
    refused(["export-legacy", str(store), str(notes), "--overwrite"], capsys, "refusing")
    assert notes.read_bytes() == b"not a legacy field file"


def test_export_legacy_help_names_overwrite(capsys):
    with pytest.raises(SystemExit):
        main(["export-legacy", "--help"])
    assert "--overwrite" in capsys.readouterr().out


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("run")
    write_tiny_run(tmp, "path.csv")
    return tmp, json.dumps(TINY_RUN)


def simulate_argv(tiny_run, out: Path, *extra: str) -> list[str]:
    tmp, config = tiny_run
    return [
        "simulate",
        "--bed",
        str(tmp / "bed.npz"),
        "--trajectory",
        str(tmp / "path.csv"),
        "--config",
        config,
        "--out",
        str(out),
        *extra,
    ]


def test_simulate_writes_its_vtk_folder_whole_and_never_into_a_users(tiny_run, tmp_path, capsys):
    vtk = users_folder(tmp_path / "vtk")
    (vtk / "particles_000010.vtu").write_text('<VTKFile type="UnstructuredGrid">mine</VTKFile>')
    before = snapshot(tmp_path)
    refused(
        simulate_argv(tiny_run, tmp_path / "f.zarr", "--vtk-dir", str(vtk)),
        capsys,
        f"refusing to replace {vtk}",
        "folder of particle snapshots",
    )
    assert snapshot(tmp_path) == before  # no store either
    ours = tmp_path / "snapshots"
    argv = simulate_argv(
        tiny_run, tmp_path / "f.zarr", "--vtk-dir", str(ours), "--state", str(tmp_path / "s.npz")
    )
    assert main(argv) == 0
    names = sorted(p.name for p in ours.iterdir())
    assert ".dozerlab-output.json" in names and "particles_000010.vtu" in names
    assert main(argv) == 0  # its own folder, store and state are replaced
    assert sorted(p.name for p in ours.iterdir()) == names
    (ours / "my_note.txt").write_text("added by the user")
    refused(argv, capsys, f"refusing to replace {ours}")
    assert (ours / "my_note.txt").read_text() == "added by the user"


def test_train_and_train_dynamics_never_replace_each_others_models(store, tmp_path, capsys):
    evolution = model_dir(tmp_path / "dynamics" / "ridge", evolution=True)
    force = model_dir(tmp_path / "models" / "linear", evolution=False)
    before = snapshot(tmp_path / "dynamics"), snapshot(tmp_path / "models")
    train = ["--train", str(store), "--config", '{"learn": {"epochs": 1}}']
    refused(
        ["train", "--model", "linear", *train, "--out", str(evolution)],
        capsys,
        f"refusing to replace {evolution}",
        "force model directory",
    )
    refused(
        ["train-dynamics", "--model", "ridge", *train, "--out", str(force)],
        capsys,
        f"refusing to replace {force}",
        "evolution model directory",
    )
    assert (snapshot(tmp_path / "dynamics"), snapshot(tmp_path / "models")) == before


def test_field_stores_are_replaced_only_by_the_command_that_wrote_them(
    store, tiny_run, tmp_path, capsys
):
    ndem = snapshot(store)
    legacy = export_legacy(store, tmp_path / "run.bin")
    refused(
        ["import-legacy", str(legacy), str(store)],
        capsys,
        f"refusing to replace {store}",
        "written by import-legacy",
    )
    imported = tmp_path / "imported.zarr"
    assert main(["import-legacy", str(legacy), str(imported)]) == 0
    assert main(["import-legacy", str(legacy), str(imported)]) == 0  # its own: replaced
    refused(simulate_argv(tiny_run, imported), capsys, "written by simulate")
    tmp, config = tiny_run
    reduce = [
        "reduce",
        "--bed",
        str(tmp / "bed.npz"),
        "--trajectory",
        str(tmp / "path.csv"),
        "--dynamics",
        "replay",
        "--force-model",
        str(tmp_path / "no-model"),
        "--config",
        config,
        "--out",
        str(store),
        "--state",
        str(tmp_path / "r.npz"),
    ]
    refused(reduce, capsys, f"refusing to replace {store}", "written by reduce")
    assert snapshot(store) == ndem


def test_beds_and_final_states_are_not_replaced_by_each_other(tiny_run, tmp_path, capsys):
    tmp, _ = tiny_run
    bed = tmp_path / "bed.npz"
    shutil.copy(tmp / "bed.npz", bed)
    refused(
        simulate_argv(tiny_run, tmp_path / "f.zarr", "--state", str(bed)),
        capsys,
        f"refusing to replace {bed}",
        "final state",
    )
    assert bed.read_bytes() == (tmp / "bed.npz").read_bytes()
    assert not (tmp_path / "f.zarr").exists()


def test_a_figure_of_one_command_is_not_replaced_by_another(tiny_run, tmp_path, capsys):
    tmp, config = tiny_run
    png = tmp_path / "path.png"
    argv = ["trajectory", "--bed", str(tmp / "bed.npz"), "--speed", "0.5", "--depth", "0.06"]
    argv += ["--config", config, "--out", str(tmp_path / "t.csv"), "--plot", str(png)]
    assert main(argv) == 0
    assert main(argv) == 0  # its own figure is replaced
    before = snapshot(tmp_path)
    refused(
        ["bed", "--scenario", "hill", "--out", str(tmp_path / "b.npz"), "--plot", str(png)],
        capsys,
        f"refusing to replace {png}",
        "bed figure",
    )
    assert snapshot(tmp_path) == before


@pytest.mark.parametrize("folder", ["users", "empty", "another command's"])
def test_plot_fields_writes_only_a_new_folder_or_its_own(store, tmp_path, capsys, folder):
    out = tmp_path / "figures"
    if folder == "users":
        users_folder(out)
    elif folder == "empty":
        out.mkdir()
    else:
        assert main(["plot-fields", str(store), "--out", str(out), "--no-animation"]) == 0
        mark = out / ".dozerlab-output.json"
        mark.write_text(mark.read_text().replace("field-plots", "validation-plots"))
    before = snapshot(tmp_path)
    refused(
        ["plot-fields", str(store), "--out", str(out), "--no-animation"],
        capsys,
        f"refusing to replace {out}",
    )
    assert snapshot(tmp_path) == before


def test_plot_fields_refused_leaves_no_figure_behind(store, tmp_path, capsys):
    """It refused force.png but had written four slices beside it."""
    out = tmp_path / "figures"
    out.mkdir()
    (out / "force.png").write_bytes(b"\x89PNG\r\n\x1a\n a user's figure")
    refused(["plot-fields", str(store), "--out", str(out)], capsys, f"refusing to replace {out}")
    assert [p.name for p in out.iterdir()] == ["force.png"]
    assert not list(tmp_path.rglob("slice_*")) and not list(tmp_path.rglob(".*tmp-*"))


@pytest.mark.parametrize("command", ["validate", "validate-dynamics"])
def test_validation_plots_never_go_into_a_users_folder(command, store, tmp_path, capsys):
    plots = users_folder(tmp_path / "plots")
    before = snapshot(tmp_path)
    argv = [command, "--model", str(tmp_path / "m"), "--interpolation", str(store)]
    refused(
        [*argv, "--out", str(tmp_path / "v.json"), "--plots", str(plots)],
        capsys,
        f"refusing to replace {plots}",
    )
    assert snapshot(tmp_path) == before


def test_validate_dynamics_refused_creates_no_plots(store, tmp_path, capsys):
    """--out FILE-OF-USERS was refused, yet plots/file/*.png had been written."""
    users = tmp_path / "file"
    users.write_text("a user's file")
    before = snapshot(tmp_path)
    refused(
        ["validate-dynamics", "--model", str(tmp_path / "m"), "--interpolation", str(store)]
        + ["--out", str(users)],
        capsys,
        f"refusing to replace {users}",
    )
    assert snapshot(tmp_path) == before


def test_validation_jsons_of_the_two_families_are_told_apart(store, tmp_path, capsys):
    dynamics = tmp_path / "ridge.json"
    dynamics.write_text(
        json.dumps({"model": "ridge", "horizon": 4, "overall": {}, "groups": {}, "summary": ""})
    )
    refused(
        ["validate", "--model", str(tmp_path / "m"), "--interpolation", str(store)]
        + ["--out", str(dynamics)],
        capsys,
        "not a dozerlab validation JSON",
    )


@pytest.mark.parametrize(
    "argv",
    [
        ["reduce-points", "--dynamics-model", "../../../victim/esc"],
        ["reduce-points", "--dynamics-model", ".."],
        ["reduce-points", "--dynamics-model", ""],
        ["reduce-points", "--dynamics-model", "ridge", "--points", "../speed~1.0_depth~0.1"],
        ["reduce-points", "--dynamics-model", "ridge", "--points", "a/b/speed~1.0_depth~0.1"],
        ["compare-reduced", "--dynamics-model", "/abs/olute", "--out", "x.json", "--plots", "p"],
    ],
)
def test_a_name_that_becomes_a_path_is_a_name(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    results = tmp_path / "deep" / "er" / "results"
    results.mkdir(parents=True)
    if argv[0] == "reduce-points":
        argv = [*argv, "--dynamics", "replay", "--force-model", "m"]
        if "--points" not in argv:
            argv += ["--points", "hill/speed~1.0_depth~0.1"]
    refused([*argv, "--results", str(results)], capsys, "--")
    assert snapshot(tmp_path) == {"deep": None, "deep/er": None, "deep/er/results": None}


# 2. Every output path checked before the work: one line, exit 2, nothing written.


def _commands(tmp: Path, store: Path, tiny: tuple[Path, str]) -> dict[str, tuple[list[str], str]]:
    """Each command with ``{}`` where the output under test goes, and that output's argument.
    Inputs that do not exist (``missing``) show that the output was checked before them."""
    run, config = tiny
    missing = str(tmp / "missing")
    run_in = ["--bed", str(run / "bed.npz"), "--trajectory", str(run / "path.csv")]
    cfg = ["--config", config]
    reduce = ["reduce", "--bed", missing, "--trajectory", missing, "--dynamics", "replay"]
    reduce += ["--force-model", missing, *cfg]
    return {
        "bed": (["bed", "--scenario", "hill", "--out", "{}"], "--out"),
        "bed --plot": (
            ["bed", "--scenario", "hill", "--out", str(tmp / "b.npz"), "--plot", "{}"],
            "--plot",
        ),
        "trajectory": (
            ["trajectory", "--bed", missing, "--speed", "1", "--depth", "0.1", "--out", "{}"],
            "--out",
        ),
        "simulate": (["simulate", *run_in, *cfg, "--out", "{}"], "--out"),
        "simulate --state": (
            ["simulate", *run_in, *cfg, "--out", str(tmp / "f.zarr"), "--state", "{}"],
            "--state",
        ),
        "simulate --vtk-dir": (
            ["simulate", *run_in, *cfg, "--out", str(tmp / "f.zarr"), "--vtk-dir", "{}"],
            "--vtk-dir",
        ),
        "simulate --plots": (
            ["simulate", *run_in, *cfg, "--out", str(tmp / "f.zarr"), "--plots", "{}"],
            "--plots",
        ),
        "train": (["train", "--model", "linear", "--train", missing, "--out", "{}"], "--out"),
        "train-dynamics": (
            ["train-dynamics", "--model", "ridge", "--train", missing, "--out", "{}"],
            "--out",
        ),
        "validate": (["validate", "--model", missing, "--out", "{}"], "--out"),
        "validate --plots": (
            ["validate", "--model", missing, "--out", str(tmp / "v.json"), "--plots", "{}"],
            "--plots",
        ),
        "validate-dynamics": (["validate-dynamics", "--model", missing, "--out", "{}"], "--out"),
        "report": (["report", "--results", missing, "--out", "{}"], "--out"),
        "plot-fields": (["plot-fields", missing, "--out", "{}"], "--out"),
        "export-legacy": (["export-legacy", missing, "{}"], "OUT"),
        "import-legacy": (["import-legacy", missing, "{}"], "OUT"),
        "reduce": ([*reduce, "--out", "{}", "--state", str(tmp / "r.npz")], "--out"),
        "reduce --state": ([*reduce, "--out", str(tmp / "r.zarr"), "--state", "{}"], "--state"),
        "compare-reduced": (
            ["compare-reduced", "--dynamics-model", "m", "--results", missing]
            + ["--out", "{}", "--plots", str(tmp / "cp")],
            "--out",
        ),
        "compare-reduced --plots": (
            ["compare-reduced", "--dynamics-model", "m", "--results", missing]
            + ["--out", str(tmp / "c.json"), "--plots", "{}"],
            "--plots",
        ),
    }


COMMANDS = [
    "bed",
    "bed --plot",
    "trajectory",
    "simulate",
    "simulate --state",
    "simulate --vtk-dir",
    "simulate --plots",
    "train",
    "train-dynamics",
    "validate",
    "validate --plots",
    "validate-dynamics",
    "report",
    "plot-fields",
    "export-legacy",
    "import-legacy",
    "reduce",
    "reduce --state",
    "compare-reduced",
    "compare-reduced --plots",
]


def _run(command, tmp_path, store, tiny_run, output: str) -> tuple[list[str], str]:
    """The command's argv with ``output`` where the output under test goes, and its argument
    (the tiny run's config snapshots every 10 steps, so ``--vtk-dir`` is written)."""
    argv, argument = _commands(tmp_path, store, tiny_run)[command]
    return [output if a == "{}" else a for a in argv], argument


@pytest.mark.parametrize("command", COMMANDS)
def test_a_file_in_the_way_of_an_outputs_folder(command, store, tiny_run, tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    (work / "results").write_text("a file where a folder should be")
    output = str(work / "results" / "sub" / "out.x")
    argv, argument = _run(command, work, store, tiny_run, output)
    before = snapshot(work)
    refused(
        argv,
        capsys,
        f"cannot write {output} ({argument})",
        f"{work / 'results'} is a file, not a folder",
        "nothing was written",
    )
    assert snapshot(work) == before


@pytest.mark.parametrize("command", COMMANDS)
def test_a_name_too_long(command, store, tiny_run, tmp_path, capsys):
    work = tmp_path / "work"
    work.mkdir()
    output = str(work / "new" / ("n" * 300))
    argv, argument = _run(command, work, store, tiny_run, output)
    refused(argv, capsys, f"({argument})", "300 bytes, longer than the 255 bytes")
    assert list(work.iterdir()) == []


def test_a_name_whose_temporary_would_be_too_long(store, tmp_path, capsys):
    out = tmp_path / ("n" * 250)  # fits, but .NAME.tmp-HOST-PID does not
    refused(["export-legacy", str(store), str(out)], capsys, "longer than the 255 bytes")
    assert [p.name for p in tmp_path.iterdir()] == ["in"]


def test_a_path_too_long(store, tmp_path, capsys):
    out = tmp_path.joinpath(*["d" * 200] * 21, "out.bin")  # > 4096 bytes, each name fits
    refused(["export-legacy", str(out.parent), str(out)], capsys, "(OUT)", "bytes a path may have")
    assert [p.name for p in tmp_path.iterdir()] == ["in"]


def test_outputs_that_would_overwrite_each_other(tiny_run, tmp_path, capsys):
    out = tmp_path / "same"
    refused(
        simulate_argv(tiny_run, out, "--state", str(out)),
        capsys,
        "--out",
        "--state",
        "would overwrite each other",
    )
    assert list(tmp_path.iterdir()) == []


UNPRIVILEGED = ["setpriv", "--bounding-set=-all", "--inh-caps=-all"] if os.geteuid() == 0 else []


@pytest.mark.skipif(
    os.geteuid() == 0 and shutil.which("setpriv") is None,
    reason="as root every folder is writable; setpriv (to drop root's capabilities) is missing",
)
@pytest.mark.parametrize("command", ["bed", "export-legacy", "simulate --state", "report"])
def test_an_unwritable_folder(command, store, tiny_run, tmp_path):
    """Run as a process that cannot write there (as root: without its capabilities)."""
    work = tmp_path / "work"
    (work / "ro").mkdir(parents=True)
    output = str(work / "ro" / "new" / "out.x")
    argv, argument = _run(command, work, store, tiny_run, output)
    (work / "ro").chmod(0o555)
    try:
        done = subprocess.run(
            [*UNPRIVILEGED, sys.executable, "-m", "dozerlab", *argv],
            capture_output=True,
            text=True,
            env=os.environ | {"DOZERLAB_MLFLOW": "0"},
        )
    finally:
        (work / "ro").chmod(0o755)
    assert done.returncode == 2, done.stderr
    (line,) = done.stderr.strip().splitlines()
    assert f"cannot write {output} ({argument})" in line
    assert f"the folder {work / 'ro'} is not writable" in line
    assert list((work / "ro").iterdir()) == []


def test_simulate_leaves_no_store_when_its_state_cannot_be_written(tiny_run, tmp_path, capsys):
    (tmp_path / "states").write_text("a file in the way of --state's folder")
    refused(
        simulate_argv(tiny_run, tmp_path / "f.zarr", "--state", str(tmp_path / "states" / "s.npz")),
        capsys,
        "(--state)",
    )
    assert [p.name for p in tmp_path.iterdir()] == ["states"]


def test_simulate_that_fails_after_its_store_leaves_none_of_its_outputs(
    tiny_run, tmp_path, capsys, monkeypatch
):
    """The store, state and snapshots were in place when the plots failed: all are taken back,
    and the earlier run's store and state put back."""
    from dozerlab.fields import plots

    out, state, vtk = tmp_path / "f.zarr", tmp_path / "s.npz", tmp_path / "vtk"
    argv = simulate_argv(tiny_run, out, "--state", str(state), "--vtk-dir", str(vtk))
    assert main(argv) == 0
    earlier = snapshot(tmp_path)

    def fail(*args, **kwargs):
        raise DozerlabError("drawing failed")

    monkeypatch.setattr(plots, "plot_run", fail)
    refused([*argv, "--plots", str(tmp_path / "plots")], capsys, "drawing failed")
    assert snapshot(tmp_path) == earlier
    shutil.rmtree(out)
    shutil.rmtree(vtk)
    state.unlink()
    refused([*argv, "--plots", str(tmp_path / "plots")], capsys, "drawing failed")
    assert list(tmp_path.iterdir()) == []
