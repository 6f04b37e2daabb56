"""The whole workflow, for real: the quick sweep in a temporary directory, shared by the checks.

One run of ``snakemake --cores 2 --configfile config/quick.yaml`` builds beds, trajectories,
field stores, models, validations and the report while MLflow records them; the checks read
what it left, then rerun it (nothing to do, nothing logged), kill a simulation half-way and
build it again, and feed it an invalid config.
"""

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.tracking import PARENT_ENV

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]
QUICK = REPO / "config" / "quick.yaml"
CFG = load_config(QUICK)
POINTS = P.sweep_points(CFG)
MODELS = CFG["learn"]["models"]
DYNAMICS = CFG["dynamics"]["models"]
REDUCED = CFG["reduced"]["dynamics_models"]
HELD_OUT = [p for p in POINTS if p.role != "train"]


def snakemake_cmd(workdir: Path, *args: str, configfile: Path = QUICK) -> list[str]:
    return [
        sys.executable,
        "-m",
        "snakemake",
        *args,
        "--cores",
        "2",
        "-s",
        str(REPO / "Snakefile"),
        "--directory",
        str(workdir),
        "--configfile",
        str(configfile),
    ]


def clean_env() -> dict[str, str]:
    """The environment without tracking settings of the session running the tests."""
    drop = {PARENT_ENV, "MLFLOW_TRACKING_URI", "DOZERLAB_MLFLOW", "MLFLOW_EXPERIMENT_NAME"}
    return {k: v for k, v in os.environ.items() if k not in drop}


def snakemake(workdir: Path, *args: str, configfile: Path = QUICK) -> subprocess.CompletedProcess:
    return subprocess.run(
        snakemake_cmd(workdir, *args, configfile=configfile),
        env=clean_env(),
        capture_output=True,
        text=True,
        timeout=2400,  # a guard, not a timing: on a machine shared by many jobs the quick sweep (with
        # the evolution models and the reduced runs) has taken over 15 min
    )


def runs(workdir: Path):
    """Every run of the workdir's MLflow store, as a list of mlflow Run objects."""
    from mlflow import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{workdir / 'mlflow.db'}")
    exp = client.get_experiment_by_name(CFG["mlflow"]["experiment"])
    return client, client.search_runs([exp.experiment_id], max_results=1000)


@pytest.fixture(scope="module")
def quick(tmp_path_factory) -> Path:
    workdir = tmp_path_factory.mktemp("quick")
    done = snakemake(workdir)
    assert done.returncode == 0, done.stderr[-5000:]
    return workdir


def test_stores_open_and_nothing_half_written_is_left(quick):
    for point in POINTS:
        ds = xr.open_zarr(P.field_path(quick / "results", point))
        assert ds["velocity"].dims == ("time", "x", "y", "z", "component")
        assert ds.sizes["time"] > 0 and np.isfinite(ds["force"].values).all()
        assert (ds.attrs["scenario"], ds.attrs["speed"], ds.attrs["depth"]) == (
            point.scenario,
            point.speed,
            point.depth,
        )
    assert not list((quick / "results").rglob("*.tmp-*"))


def test_models_reload_through_mlflow(quick):
    import mlflow

    ds = xr.open_zarr(P.field_path(quick / "results", POINTS[0])).isel(time=slice(0, 3))
    arrays = {k: ds[k].values for k in ("velocity", "density", "blade_velocity")}
    for model in MODELS:
        loaded = mlflow.pyfunc.load_model(str(P.model_path(quick / "results", model)))
        pred = loaded.predict(arrays)
        assert pred.shape == (3, 6) and np.isfinite(pred.to_numpy()).all()


def test_evolution_models_predict_through_mlflow_and_are_validated(quick):

    import mlflow

    ds = xr.open_zarr(P.field_path(quick / "results", POINTS[0]))
    h, m = CFG["dynamics"]["history"], CFG["dynamics"]["horizon"]
    inputs = {
        "velocity": ds["velocity"].values[None, :h],
        "density": ds["density"].values[None, :h],
        "blade_velocity": ds["blade_velocity"].values[None, : h + m],
    }
    for model in DYNAMICS:
        loaded = mlflow.pyfunc.load_model(str(P.dynamics_model_path(quick / "results", model)))
        assert loaded.metadata.metadata["history"] == h
        out = loaded.predict(inputs)
        assert out["velocity"].shape == (1, m, *ds["density"].shape[1:], 3)
        assert np.isfinite(out["density"]).all() and (out["density"] >= 0).all()
        result = json.loads(P.dynamics_validation_path(quick / "results", model).read_text())
        assert set(result["groups"]) == {"interpolation", "extrapolation"}
        assert np.isfinite(result["overall"]["one_step"]["velocity"])
        rollout = quick / "results" / "dynamics" / result["plots"]["rollout"]
        assert rollout.is_file() and rollout.parent == P.dynamics_plots_path(
            quick / "results", model
        )


def test_reduced_runs_are_aligned_stores_with_final_states_and_are_compared(quick):
    from dozerlab.fields.store import open_store
    from dozerlab.scenarios.bed import Bed

    results = quick / "results"
    for point in POINTS:
        assert Bed.load(P.state_path(results, point)).count > 0  # NDEM's final state
    for model in REDUCED:
        for point in HELD_OUT:
            ds = open_store(P.reduced_path(results, model, point))
            ndem = open_store(P.field_path(results, point))
            assert dict(ds.sizes) == dict(ndem.sizes)
            assert ds.attrs["dynamics_model"] == model and ds.attrs["force_model"] == "unet"
            assert ds.attrs["wall_time_s"] > 0 and np.isfinite(ds["force"].values).all()
            state = Bed.load(P.reduced_path(results, model, point, "npz"))
            assert state.count == ndem.attrs["particle_count"]
            assert P.reduce_benchmark_path(results, model, point).is_file()
        summary = json.loads(P.reduced_comparison_path(results, model).read_text())
        assert {(p["scenario"], p["speed"], p["depth"]) for p in summary["points"]} == {
            (p.scenario, p.speed, p.depth) for p in HELD_OUT
        }
        for entry in summary["points"]:
            assert entry["left_bed"] == 0 and entry["targets_met"]["nothing_through"]
            assert np.isfinite(entry["height_accuracy"]) and entry["loop_speedup"] > 0
            for plot in entry["plots"]:
                assert (results / "reduced" / model / "compare" / plot).is_file()


def test_mlflow_holds_one_parent_and_a_child_per_job(quick):
    client, all_runs = runs(quick)
    parents = [r for r in all_runs if r.data.tags.get("rule") == "workflow"]
    assert len(parents) == 1
    parent = parents[0]
    assert parent.info.status == "FINISHED"
    assert "index.html" in {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert parent.data.params["sweep.speeds"] == str(CFG["sweep"]["speeds"])
    children = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    rules = sorted(r.data.tags["rule"] for r in children)
    expected = {
        "bed": 1,
        "simulate": len(POINTS),
        "train": len(MODELS),
        "validate": len(MODELS),
        "train_dynamics": len(DYNAMICS),
        "validate_dynamics": len(DYNAMICS),
        "reduce": len(REDUCED) * len(HELD_OUT),
        "compare_reduced": len(REDUCED),
    }
    assert {rule: rules.count(rule) for rule in expected} == expected
    assert len(all_runs) == 1 + len(children)
    for child in children:
        assert child.info.status == "FINISHED" and child.data.metrics, child.data.tags["rule"]
    sims = {
        (r.data.tags["scenario"], float(r.data.tags["speed"]), float(r.data.tags["depth"]))
        for r in children
        if r.data.tags["rule"] == "simulate"
    }
    assert sims == {(p.scenario, p.speed, p.depth) for p in POINTS}


def test_report_has_table_figures_and_models(quick):
    text = (quick / "results" / "report" / "index.html").read_text()
    sections = re.findall(r'<section id="([a-z]+)">', text)
    assert {"sweep", "beds", "runs", "models", "reduced"} <= set(sections)
    assert '<div class="note">Smoke test' in text  # quick.yaml: report.smoke_test
    for point in POINTS:
        assert f"{point.scenario} {point.name}: blade trajectory" in text
        assert f"{point.scenario} {point.name}: blade force (N) and torque" in text
        # the sweep table's wall time is the simulation's own, recorded in its store
        assert xr.open_zarr(P.field_path(quick / "results", point)).attrs["wall_time_s"] > 0
    # sweep map, bed, per point trajectory, slice and force, error chart, per model parity
    assert text.count("data:image/png;base64,") >= 3 * len(POINTS) + 3 + len(MODELS)
    for model in MODELS:
        assert f'id="validation-{model}"' in text
    for model in DYNAMICS:
        assert f'id="dynamics-{model}"' in text
    assert "Not built yet" not in text and "No results" not in text
    assert not list((quick / "results" / "validation").glob("*.html"))  # report builds HTML


def test_snakemake_report(quick):
    done = snakemake(quick, "--report", "report.html")
    assert done.returncode == 0, done.stderr[-3000:]
    assert (quick / "report.html").stat().st_size > 10_000


def test_rerun_builds_nothing_and_logs_nothing(quick):
    before = len(runs(quick)[1])
    done = snakemake(quick)
    assert done.returncode == 0, done.stderr[-3000:]
    assert "Nothing to be done" in done.stderr
    assert len(runs(quick)[1]) == before


def test_killed_simulation_is_redone_cleanly(quick):
    # A point outside the configured sweep: built by asking for its path.
    point = P.SweepPoint("hill", 1.1, 0.06)
    store = P.field_path(quick / "results", point)
    target = str(store.relative_to(quick))  # targets are paths relative to the working directory
    proc = subprocess.Popen(
        snakemake_cmd(quick, target),
        env=clean_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    try:
        deadline = time.monotonic() + 300
        while not (partial := list(store.parent.glob(f".{store.name}.tmp-*"))):
            assert proc.poll() is None and time.monotonic() < deadline, (
                "the simulation never started"
            )
            time.sleep(0.05)
        os.kill(
            int(partial[0].name.rsplit("-", 1)[1]), signal.SIGKILL
        )  # the simulate process, mid-run
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
    assert proc.returncode != 0, err[-3000:]
    assert not store.exists()
    _client, all_runs = runs(quick)
    failed = [
        r for r in all_runs if r.data.tags.get("rule") == "workflow" and r.info.status == "FAILED"
    ]
    assert len(failed) == 1

    done = snakemake(quick, target)
    assert done.returncode == 0, done.stderr[-3000:]
    ds = xr.open_zarr(store)
    assert ds.attrs["speed"] == 1.1 and ds.sizes["time"] > 0
    assert not list(store.parent.glob("*.tmp-*"))


def test_quick_config_sets_every_field_the_default_config_sets():
    """Snakemake lays --configfile over config/config.yaml in the project, not in a bare workdir:
    the quick sweep is the same either way only if it overrides every field."""
    import yaml

    def fields(doc, prefix=""):
        out = set()
        for key, value in doc.items():
            out.add(prefix + key)
            if isinstance(value, dict):
                out |= fields(value, f"{prefix}{key}.")
        return out

    default = yaml.safe_load((REPO / "config" / "config.yaml").read_text())
    assert fields(default) <= fields(yaml.safe_load(QUICK.read_text()))


def test_invalid_config_is_refused_before_any_job(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("sampling: {bins: [0, 4, 4]}\n")
    done = snakemake(tmp_path, configfile=bad)
    assert done.returncode != 0
    assert re.search(r"config field 'sampling\.bins\.0'.*allowed: >= 1", done.stderr)
    assert not (tmp_path / "results").exists() and not (tmp_path / "mlflow.db").exists()
