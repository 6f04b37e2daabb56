"""``dozerlab reduce``: an aligned store and a bed file written, a missing model refused."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from dozerlab.cli import main
from dozerlab.fields.store import open_store
from dozerlab.scenarios.bed import Bed
from tests.helpers import REDUCED_RUN as CONFIG


def _reduce_argv(tmp, dynamics: str, out: str) -> list[str]:
    return [
        *("reduce", "--bed", str(tmp / "bed.npz")),
        *("--trajectory", str(tmp / "speed~0.5_depth~0.06.csv"), "--dynamics", dynamics),
        *("--ndem", str(tmp / "ndem.zarr"), "--force-model", str(tmp / "linear")),
        *("--config", json.dumps(CONFIG), "--out", str(tmp / f"{out}.zarr")),
        *("--state", str(tmp / f"{out}.npz")),
    ]


@pytest.mark.slow  # a reduced run and its NDEM run; reduce-points covers the command fast
def test_reduce_command_writes_an_aligned_store_and_a_bed_file(ndem_run):
    tmp, _ = ndem_run
    assert main([*_reduce_argv(tmp, "replay", "cli"), "--depth", "0.06"]) == 0
    ds, nd = open_store(tmp / "cli.zarr"), open_store(tmp / "ndem.zarr")
    assert dict(ds.sizes) == dict(nd.sizes)
    np.testing.assert_allclose(ds["time"].values, nd["time"].values)
    np.testing.assert_allclose(ds["blade_position"].values, nd["blade_position"].values)
    assert ds.attrs["dynamics_model"] == "replay" and ds.attrs["force_model"] == "linear"
    assert ds.attrs["depth"] == 0.06
    assert ds.attrs["wall_time_s"] > 0 and nd.attrs["wall_time_s"] > 0
    assert np.isfinite(ds["force"].values).all()
    state = Bed.load(tmp / "cli.npz")
    assert state.count == Bed.load(tmp / "bed.npz").count == Bed.load(tmp / "ndem.npz").count


def test_a_missing_dynamics_model_is_refused(ndem_run, capsys):
    tmp, _ = ndem_run
    assert main(_reduce_argv(tmp, str(tmp / "nowhere"), "x")) == 2
    assert "not an MLflow model directory" in capsys.readouterr().err
    assert not (tmp / "x.zarr").exists()


def test_reduce_points_reads_and_writes_the_workflows_paths(ndem_run, tmp_path, capsys):
    from dozerlab import sweep as P

    tmp, _ = ndem_run
    results = tmp_path / "results"
    point = P.SweepPoint("hill", 0.5, 0.06)
    for src, dest in (
        (tmp / "bed.npz", P.bed_path(results, "hill")),
        (tmp / "speed~0.5_depth~0.06.csv", P.trajectory_path(results, point)),
    ):
        dest.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(src, dest)
    shutil.copytree(tmp / "ndem.zarr", P.field_path(results, point))
    argv = [
        *("reduce-points", "--results", str(results), "--dynamics-model", "replay"),
        *("--dynamics", "replay", "--force-model", str(tmp / "linear")),
        *("--config", json.dumps(CONFIG), "--points"),
    ]
    assert main([*argv, "hill/speed~0.5_depth~fast"]) == 2
    assert "is not named speed~{speed}_depth~{depth}" in capsys.readouterr().err
    assert main([*argv, "hill/speed~0.5_depth~0.06", "hill/speed~0.5_depth~0.06"]) == 2
    assert "are one point; give it once" in capsys.readouterr().err
    assert not (results / "reduced").exists()
    assert main([*argv, "hill/speed~0.5_depth~0.06"]) == 0
    assert "reduced run hill/speed~0.5_depth~0.06:" in capsys.readouterr().out
    ds = open_store(P.reduced_path(results, "replay", point))
    assert ds.attrs["scenario"] == "hill" and ds.attrs["depth"] == 0.06
    assert ds.attrs["dynamics_model"] == "replay" and ds.attrs["force_model"] == "linear"
    np.testing.assert_allclose(ds["time"].values, open_store(tmp / "ndem.zarr")["time"].values)
    assert Bed.load(P.reduced_path(results, "replay", point, "npz")).count > 0


def test_replaying_another_points_store_is_refused_naming_both(ndem_run, capsys):
    """``reduce --ndem`` with another point's store or a store of other bins ran to exit 0 and
    wrote a wrongly shaped reduced store."""
    tmp, _ = ndem_run
    other = tmp / "speed~0.7_depth~0.06.csv"
    argv = ["trajectory", "--bed", str(tmp / "bed.npz"), "--speed", "0.7", "--depth", "0.06"]
    assert main([*argv, "--config", json.dumps(CONFIG), "--out", str(other)]) == 0
    ndem = tmp / "ndem.zarr"
    rows = open_store(ndem).sizes["time"]

    def refused(argv: list[str], *parts: str) -> None:
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert "Traceback" not in err and err.count("\n") == 1, err
        for part in (f"NDEM store {ndem}", *parts):
            assert part in err, err
        assert not (tmp / "bad.zarr").exists() and not (tmp / "bad.npz").exists()

    argv = _reduce_argv(tmp, "replay", "bad")
    argv[argv.index("--trajectory") + 1] = str(other)
    refused(argv, "is the run of", "'speed': 0.7", str(other))
    # labelled as the store's point, the 0.7 m/s trajectory still has other rows
    refused([*argv, "--speed", "0.5"], f"has {rows} rows but trajectory {other} gives")
    bins = {**CONFIG, "sampling": {**CONFIG["sampling"], "bins": [4, 5, 4]}}
    argv = _reduce_argv(tmp, "replay", "bad")
    argv[argv.index("--config") + 1] = json.dumps(bins)
    refused(argv, "has (6, 5, 4) bins but the run samples (4, 5, 4)")
    wide = {**CONFIG, "sampling": {**CONFIG["sampling"], "length": 0.4}}
    argv[argv.index("--config") + 1] = json.dumps(wide)
    refused(argv, "m but the run's are")


def test_speed_and_depth_flags_take_the_bounds_of_the_sweep(ndem_run, capsys):
    """``trajectory --speed 1e-9`` grew past 870 MB."""
    tmp, _ = ndem_run
    out = tmp / "crawl.csv"
    for flag, value, allowed in (("--speed", "1e-9", ">= 0.01"), ("--depth", "1e-250", ">= 0.001")):
        argv = ["trajectory", "--bed", str(tmp / "bed.npz"), "--speed", "0.5", "--depth", "0.06"]
        argv[argv.index(flag) + 1] = value
        with pytest.raises(SystemExit) as exit_:
            main([*argv, "--out", str(out)])
        assert exit_.value.code == 2
        err = capsys.readouterr().err
        assert f"argument {flag}:" in err and f"(allowed: {allowed}" in err
        assert not out.exists()
    with pytest.raises(SystemExit):
        main([*_reduce_argv(tmp, "replay", "bad"), "--speed", "nan"])
    assert "nan is not a finite number" in capsys.readouterr().err
