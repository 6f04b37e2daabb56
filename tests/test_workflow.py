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
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
import yaml

from dozerlab import sweep as P
from dozerlab.config import load_config
from dozerlab.runtime import process_token
from dozerlab.tracking import PARENT_ENV
from tests.helpers import expected_job_runs

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
    (workdir / "console.txt").write_text(done.stderr)
    return workdir


def test_the_console_is_one_line_per_job_start_and_end_and_a_summary(quick):
    console = (quick / "console.txt").read_text()
    jobs = sum(expected_job_runs(CFG).values())
    assert "Shell command" not in console and "reason:" not in console
    assert max(len(line) for line in console.splitlines()) < 400
    assert len(re.findall(r"^\S+  start  ", console, re.M)) > jobs  # and the trajectories, report
    assert re.search(r"done   all  \(\d+ s\)  \[(\d+)/\1, 100%\]$", console, re.M), console[-3000:]
    assert "report    results/report/index.html" in console
    assert f"MLflow: {jobs} job runs under workflow run" in console
    # where the time went: the jobs' time by rule, the largest first, and how busy the cores were
    clock = re.search(
        r"^  jobs      (\d+) s of job time on 2 cores \((\d+) % busy\), by rule \(jobs\): (.*)$",
        console,
        re.M,
    )
    assert clock, console[-3000:]
    shares = dict(re.findall(r"(\w+) \d+ s \((\d+)\)", clock[3]))
    assert shares["simulate"] == str(len(POINTS)) and shares["train"] == str(len(MODELS))
    assert 0 < int(clock[2]) <= 100
    # Snakemake's own log keeps what the console leaves out
    (log,) = (quick / ".snakemake" / "log").glob("*.snakemake.log")
    assert "python -m dozerlab simulate" in log.read_text()


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


def test_every_long_job_logs_its_progress(quick):
    # the bed build runs with the bar off (--no-progress): its log must still show it settling
    bed_log = (quick / "logs" / "bed" / "hill.log").read_text()
    assert "bed hill step 100 " in bed_log and "per particle" in bed_log, bed_log[-2000:]
    for log_file in (quick / "logs" / "simulate").rglob("*.log"):
        assert "ms/step" in log_file.read_text(), log_file


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
    h = CFG["dynamics"]["history"]
    for model in DYNAMICS:
        loaded = mlflow.pyfunc.load_model(str(P.dynamics_model_path(quick / "results", model)))
        assert loaded.metadata.metadata["history"] == h
        # the ridge predicts its own rows a call (dynamics.ridge_horizon), the others horizon
        m = CFG["dynamics"]["ridge_horizon" if model == "ridge" else "horizon"]
        assert loaded.metadata.metadata["horizon"] == m
        inputs = {
            "velocity": ds["velocity"].values[None, :h],
            "density": ds["density"].values[None, :h],
            "blade_velocity": ds["blade_velocity"].values[None, : h + m],
        }
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
    for point in HELD_OUT:  # its twin: from the bed moved by reduced.twin.jitter_m
        twin = open_store(P.twin_path(results, point))
        assert twin.attrs["jitter_m"] == CFG["reduced"]["twin"]["jitter_m"]
        assert Bed.load(P.twin_path(results, point, "npz")).count == twin.attrs["particle_count"]
    for model in REDUCED:
        for point in HELD_OUT:
            ds = open_store(P.reduced_path(results, model, point))
            ndem = open_store(P.field_path(results, point))
            assert dict(ds.sizes) == dict(ndem.sizes)
            # replay's fields are NDEM's; the others' force model learnt their loop's fields
            force = CFG["reduced"]["force_model"] + ("" if model == "replay" else "-loop")
            assert ds.attrs["dynamics_model"] == model and ds.attrs["force_model"] == force
            assert ds.attrs["wall_time_s"] > 0 and np.isfinite(ds["force"].values).all()
            state = Bed.load(P.reduced_path(results, model, point, "npz"))
            assert state.count == ndem.attrs["particle_count"]
        assert P.reduce_benchmark_path(results, model).is_file()  # one job, every point
        if model != "replay":
            meta = P.loop_force_model_path(results, model) / "artifacts" / "meta.json"
            trained_on = json.loads(meta.read_text())["loop_fields"]
            assert trained_on == [
                str(P.reduced_path(results, model, p).resolve()) for p in P.by_role(POINTS, "train")
            ]
            # those runs, one job's, were driven by the force model fitted to NDEM's fields
            for p in P.by_role(POINTS, "train"):
                ds = open_store(P.reduced_path(results, model, p))
                assert ds.attrs["force_model"] == CFG["reduced"]["force_model"]
            assert P.reduce_training_benchmark_path(results, model).is_file()
        summary = json.loads(P.reduced_comparison_path(results, model).read_text())
        assert {(p["scenario"], p["speed"], p["depth"]) for p in summary["points"]} == {
            (p.scenario, p.speed, p.depth) for p in HELD_OUT
        }
        for entry in summary["points"]:
            assert entry["left_bed"] == 0 and entry["targets_met"]["nothing_through"]
            assert np.isfinite(entry["height_accuracy"]) and entry["loop_speedup"] > 0
            # beside NDEM's twin (reduced.twin, on in the quick sweep)
            assert 0 < entry["twin_surface_accuracy"] <= 1 and entry["surface_accuracy_skill"] > 0
            for plot in entry["plots"]:
                assert (results / "reduced" / model / "compare" / plot).is_file()


def test_mlflow_holds_one_parent_and_a_child_per_job(quick):
    client, all_runs = runs(quick)
    parents = [r for r in all_runs if r.data.tags.get("rule") == "workflow"]
    assert len(parents) == 1
    parent = parents[0]
    assert parent.info.status == "FINISHED"
    artifacts = {a.path for a in client.list_artifacts(parent.info.run_id)}
    assert "report" in artifacts  # the report's folder: the page and its animations
    page = {a.path for a in client.list_artifacts(parent.info.run_id, "report")}
    assert {"report/index.html", "report/animations"} <= page
    assert any(a.endswith(".snakemake.log") for a in artifacts), artifacts  # Snakemake's own log
    assert parent.data.tags["dozerlab.host"] and parent.data.tags["dozerlab.pid"].isdigit()
    assert parent.data.params["sweep.speeds"] == str(CFG["sweep"]["speeds"])
    children = [r for r in all_runs if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    rules = sorted(r.data.tags["rule"] for r in children)
    expected = expected_job_runs(CFG)
    assert {rule: rules.count(rule) for rule in expected} == expected
    assert len(all_runs) == 1 + len(children)
    for child in children:
        assert child.info.status == "FINISHED" and child.data.metrics, child.data.tags["rule"]
    # each reduce run says what its loop ran with: the crest is replay's; the quick sweep
    # steers no loop (density_gain 0)
    reduce_runs = [r for r in children if r.data.tags["rule"].startswith("reduce")]
    assert {r.data.tags["model"] for r in reduce_runs} == set(REDUCED)
    assert CFG["reduced"]["density_gain"] == 0
    for r in reduce_runs:
        replay = r.data.tags["model"] == "replay"
        assert float(r.data.tags["crest_bins"]) == (CFG["reduced"]["crest_bins"] if replay else 0)
        assert r.data.tags["density_steered"] == "False"
    sims = {
        (r.data.tags["scenario"], float(r.data.tags["speed"]), float(r.data.tags["depth"]))
        for r in children
        if r.data.tags["rule"] == "simulate"
    }
    assert sims == {(p.scenario, p.speed, p.depth) for p in POINTS}
    groups = {
        "train": "training",
        "interpolation": "interpolation",
        "extrapolation": "extrapolation",
    }
    for r in children:
        tags = r.data.tags
        assert r.info.run_name.startswith(tags["role"] + "/"), r.info.run_name
        if tags["rule"] == "simulate":
            point = next(
                p
                for p in POINTS
                if (p.speed, p.depth) == (float(tags["speed"]), float(tags["depth"]))
            )
            assert tags["group"] == groups[point.role]
            assert r.info.run_name == f"simulate/{point.scenario}/{point.name}"
    assert parent.data.tags["role"] == "parent" and parent.info.run_name == "sweep/quick"
    # the sweep's headline figures compare sweeps in MLflow's chart view
    assert {f"force_x_rel_rmse/{m}" for m in MODELS} < set(parent.data.metrics)
    assert {f"reduced_{m}/height_accuracy" for m in REDUCED} < set(parent.data.metrics)
    assert parent.data.metrics["wall_seconds"] > 0
    # and the jobs' time by rule: where it went
    assert parent.data.metrics["job_seconds/simulate"] > 0
    assert parent.data.metrics["job_seconds_total"] > parent.data.metrics["job_seconds/simulate"]
    # every trained model is registered by kind: models:/NAME/VERSION
    query = f"tags.`dozerlab.parent_run_id` = '{parent.info.run_id}'"
    names = {v.name for v in client.search_model_versions(query)}
    assert {f"dozerlab-force-{m}" for m in MODELS} | {
        f"dozerlab-evolution-{m}" for m in DYNAMICS
    } < names


def test_report_has_table_figures_and_models(quick):
    text = (quick / "results" / "report" / "index.html").read_text()
    sections = re.findall(r'<section id="([a-z]+)">', text)
    assert {"sweep", "beds", "runs", "models", "reduced"} <= set(sections)
    assert '<div class="note">Smoke test' in text  # quick.yaml: report.smoke_test
    for point in POINTS:
        assert f"{point.scenario} {point.name}: blade trajectory" in text
        assert f"{point.scenario} {point.name}: blade force (kN) and torque" in text
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


def _terminal_signals() -> None:
    """Ctrl-C's default action, as in a terminal: a shell's background job (`cmd &`) starts with
    SIGINT ignored, and Snakemake would inherit that."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def background(workdir: Path, *args: str) -> subprocess.Popen:
    """Snakemake started in its own process group (to signal it as a terminal would)."""
    return subprocess.Popen(
        snakemake_cmd(workdir, *args),
        env=clean_env(),
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        preexec_fn=_terminal_signals,
    )


@contextmanager
def simulating(workdir: Path, point: P.SweepPoint):
    """Snakemake building one point's store, from the moment its simulate job writes:
    yields (the Snakemake process, the store, the target, the simulate job's pid)."""
    store = P.field_path(workdir / "results", point)
    target = str(store.relative_to(workdir))  # targets are paths relative to the working directory
    proc = background(workdir, target)
    try:
        deadline = time.monotonic() + 300
        while not (partial := list(store.parent.glob(f".{store.name}.tmp-*"))):
            assert proc.poll() is None and time.monotonic() < deadline, "no simulation started"
            time.sleep(0.05)
        yield proc, store, target, int(partial[0].name.rsplit("-", 1)[1])
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


def _ended(proc: subprocess.Popen, workdir: Path, timeout: float) -> str:
    """Wait for the background Snakemake ``proc`` to end; return its stderr. One still running
    after ``timeout`` seconds fails the test with the workflow's processes (the MLflow follower
    runs in a session of its own) and the follower's log."""
    try:
        return proc.communicate(timeout=timeout)[1]
    except subprocess.TimeoutExpired:
        running = "\n".join(
            f"{pid}: {cmd[:300]}"
            for pid, cmd in _processes().items()
            if "snakemake" in cmd or "dozerlab" in cmd
        )
        ingest = workdir / "logs" / "mlflow-ingest.log"
        pytest.fail(
            f"snakemake still running {timeout:g} s on; its session:\n{running}\n"
            f"{ingest}:\n{ingest.read_text()[-3000:] if ingest.exists() else '(none)'}"
        )


def test_killed_simulation_is_redone_cleanly(quick):
    # A point outside the configured sweep: built by asking for its path.
    with simulating(quick, P.SweepPoint("hill", 1.1, 0.06)) as (proc, store, target, job):
        os.kill(job, signal.SIGKILL)  # the simulate process, mid-run
        err = _ended(proc, quick, timeout=120)
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
    assert not list(store.parent.glob(f".{store.name}.tmp-*"))


def _processes(session: int | None = None) -> dict[int, str]:
    """pid -> command line of this machine's processes (from /proc), or of those in the
    ``session`` led by that pid."""
    found = {}
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                if session is not None and os.getsid(int(entry.name)) != session:
                    continue
                found[int(entry.name)] = (
                    (entry / "cmdline").read_bytes().replace(b"\0", b" ").decode()
                )
            except OSError:
                continue
    return found


def _gone(pid: int, within_s: float) -> bool:
    deadline = time.monotonic() + within_s
    while process_token(pid) is not None:
        if time.monotonic() > deadline:
            return False
        time.sleep(0.05)
    return True


def test_killed_snakemake_leaves_no_orphan_and_its_run_is_closed(quick):
    """SIGKILL to Snakemake itself: its simulate job stops, nothing half-written stays; the lock
    stays (Snakemake's), --unlock lifts it, and the next run closes the dead parent run."""
    with simulating(quick, P.SweepPoint("hill", 1.2, 0.05)) as (proc, store, target, job):
        proc.kill()  # Snakemake alone, as the OOM killer or `kill -9` would
        proc.communicate(timeout=60)
        assert _gone(job, within_s=20), "the simulate job runs on, orphaned"
    assert not store.exists() and not list(store.parent.glob(f".{store.name}.tmp-*"))
    client, all_runs = runs(quick)
    dead = max(
        (r for r in all_runs if r.data.tags.get("rule") == "workflow"),
        key=lambda r: r.info.start_time,
    )
    assert dead.info.status == "RUNNING"

    locked = snakemake(quick, target)
    assert locked.returncode != 0 and "cannot be locked" in locked.stderr  # docs/safety.md
    assert snakemake(quick, "--unlock").returncode == 0
    done = snakemake(quick, target)
    assert done.returncode == 0, done.stderr[-3000:]
    assert client.get_run(dead.info.run_id).info.status == "KILLED"
    assert xr.open_zarr(store).attrs["speed"] == 1.2


def test_ctrl_c_during_onstart_is_a_clean_message(tmp_path):
    proc = background(tmp_path)
    try:
        deadline = time.monotonic() + 120
        while not any("mlflow-start" in c for c in _processes().values()):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
            time.sleep(0.02)
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in the terminal does
        err = _ended(proc, tmp_path, timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err[-3000:]
    assert "interrupted while starting the MLflow parent run; no job ran" in err
    assert "Traceback" not in err and not (tmp_path / "results").exists()
    assert not list((tmp_path / ".snakemake" / "locks").glob("*"))  # no --unlock needed


def test_sigterm_stops_the_jobs_as_ctrl_c_does(tmp_path):
    """Snakemake's own SIGTERM handler let the running jobs finish; the README says SIGTERM
    stops them like Ctrl-C: the job stops, leaves nothing, the parent run ends FAILED, the lock
    is released."""
    bed = tmp_path / P.bed_path("results", "hill")
    proc = background(tmp_path, str(P.bed_path("results", "hill")))
    try:
        deadline = time.monotonic() + 300
        while not (jobs := [p for p, c in _processes(proc.pid).items() if "dozerlab bed " in c]):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read()[-3000:]
            time.sleep(0.05)
        time.sleep(1.0)  # into its work
        proc.send_signal(signal.SIGTERM)  # Snakemake alone, as `kill PID` or a scheduler would
        err = _ended(proc, tmp_path, timeout=120)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode != 0, err[-3000:]
    assert all(_gone(job, within_s=20) for job in jobs), "the bed job ran on"
    assert not bed.exists() and not list(bed.parent.glob("*.tmp-*"))
    assert not list((tmp_path / ".snakemake" / "locks").glob("*"))
    _client, all_runs = runs(tmp_path)
    assert [r.info.status for r in all_runs if r.data.tags.get("rule") == "workflow"] == ["FAILED"]


@pytest.mark.parametrize(
    ("target", "message"),
    [
        ("results/fields/hill/speed~1_depth~0.04.zarr", "ask for speed~1.0"),
        ("results/fields/hill/speed~1.0_depth~0.040.zarr", "ask for depth~0.04"),
        ("results/trajectories/hill/speed~1e0_depth~0.04.csv", "ask for speed~1.0"),
        ("results/fields/hill/speed~-1.0_depth~0.04.zarr", r"allowed: a finite number > 0 m/s"),
        ("results/plots/hill/speed~1.0_depth~fast", r"depth 'fast' is not a number"),
    ],
)
def test_a_path_spelled_otherwise_gets_the_canonical_spelling_or_the_reason(
    tmp_path, target, message
):
    done = snakemake(tmp_path, "-n", target)
    said = done.stdout + done.stderr  # a dry run reports on stdout
    assert done.returncode != 0
    assert re.search(message, said), said[-3000:]
    assert "MissingRuleException" not in said


def test_force_fields_pick_the_reduce_jobs_force_model(tmp_path):
    """force_fields loop: a learned dynamics model's held-out runs take the force model of its
    loop's fields, trained on its runs of the training points with reduced.force_history rows
    of history; ndem: results/models for all."""
    quick = yaml.safe_load(QUICK.read_text())
    quick["reduced"]["force_history"] = 2
    for fields, loop_jobs in (("loop", 1), ("ndem", 0)):
        quick["reduced"]["force_fields"] = fields
        cfg = tmp_path / f"{fields}.yaml"
        cfg.write_text(yaml.safe_dump(quick))
        done = snakemake(tmp_path, "-n", "-p", configfile=cfg)
        assert done.returncode == 0, done.stderr[-3000:]
        jobs = re.findall(r"^rule (\w+):", done.stdout, re.M)
        assert jobs.count("train_loop_force") == loop_jobs
        histories = [
            json.loads(c)["learn"]["history"]
            for c in re.findall(
                r"dozerlab train .*?--loop-fields .*?--config '(\{.*?\})'", done.stdout
            )
        ]
        assert histories == [2] * loop_jobs and quick["learn"]["history"] == 3
        assert jobs.count("reduce") == 2  # one a model, every held-out point
        # ridge's runs of the 4 training points, in one job, with the NDEM-fitted force model
        assert jobs.count("reduce_training_points") == loop_jobs
        forces = re.findall(r"--force-model (\S+) .*?--rule (\S+)", done.stdout)
        models = {("results/models/linear", "reduce")}  # replay's, and ridge's under ndem
        if loop_jobs:
            models |= {
                ("results/reduced/ridge/force_model", "reduce"),
                ("results/models/linear", "reduce_training_points"),
            }
        assert set(forces) == models


def test_twin_runs_join_the_workflow_only_when_enabled(tmp_path):
    """reduced.twin.enabled: per held-out point one twin NDEM job from its bed and trajectory
    with the configured jitter and seed, and with reduced.twin.draws 3 two more draws (seed + 1,
    seed + 2) beside it; compare-reduced reads them all; disabled: none."""
    quick = yaml.safe_load(QUICK.read_text())
    held_out = quick["sweep"]["interpolation"] + quick["sweep"]["extrapolation"]
    for enabled in (True, False):
        quick["reduced"]["twin"] = {"enabled": enabled, "jitter_m": 2e-6, "seed": 7, "draws": 3}
        cfg = tmp_path / f"{enabled}.yaml"
        cfg.write_text(yaml.safe_dump(quick))
        done = snakemake(tmp_path, "-n", "-p", configfile=cfg)
        assert done.returncode == 0, done.stderr[-3000:]
        jobs = re.findall(r"^rule (\w+):", done.stdout, re.M)
        n = len(held_out) if enabled else 0
        assert (jobs.count("twin"), jobs.count("twin_draw")) == (n, 2 * n)
        twins = re.findall(
            r"dozerlab simulate .*--jitter (\S+) --jitter-seed (\S+) .*--out '?([^'\s]+)",
            done.stdout,
        )
        want = []
        for p in held_out if enabled else []:
            stem = f"results/twins/{p['scenario']}/speed~{p['speed']}_depth~{p['depth']}"
            want += [(str(7 + k), f"{stem}{f'_draw~{k + 1}' if k else ''}.zarr") for k in range(3)]
        assert sorted(twins) == sorted(("2e-06", seed, s) for seed, s in want)
        compare = re.findall(
            r"^rule compare_reduced:\n(?:    .*\n)*?    input: (.*)$", done.stdout, re.M
        )
        assert compare and all(("results/twins/" in line) == enabled for line in compare)
        assert all(line.count("_draw~") == 4 * n for line in compare)
        assert jobs.count("simulate") == 6  # NDEM's own runs, with or without twins


#: An adaptive sweep of one round over the quick sweep's ranges (its rules in the dry run).
ADAPTIVE = {
    "enabled": True,
    "rounds": 1,
    "per_round": 1,
    "candidates": {"kind": "lattice", "count": 3},
    "min_spacing": 0.5,
}
TARGETS = {"reduced": {"targets": {"force_skill": 0.5, "loop_speedup": 7}}}
DRAWS = {"reduced": {"twin": {"enabled": True, "draws": 3}}}


@pytest.mark.parametrize(
    ("change", "adaptive", "changed"),
    [
        # only compare-reduced and the report read the targets
        (TARGETS, False, {"compare-reduced", "report"}),
        # the twins' draws: new NDEM runs (twin_draw), read by compare-reduced and the report ...
        (DRAWS, False, {"simulate", "compare-reduced", "report"}),
        # ... but not by the adaptive curve and records, which read draw 1 alone
        (DRAWS, True, set()),
    ],
    ids=["targets", "twin draws", "twin draws, adaptive"],
)
def test_a_setting_reaches_only_the_commands_that_read_it(tmp_path, change, adaptive, changed):
    """Changing only reduced.targets re-ran six jobs: a rule reruns when its params (the
    --config it passes) change, so each passes only what its command reads."""
    commands = {}
    for name, extra in (("before", {}), ("after", change)):
        quick = yaml.safe_load(QUICK.read_text())
        if adaptive:
            quick["sweep"]["adaptive"] = ADAPTIVE
        for section, fields in extra.items():
            quick[section].update(fields)
        cfg = tmp_path / f"{name}.yaml"
        cfg.write_text(yaml.safe_dump(quick))
        done = snakemake(tmp_path, "-n", "-p", configfile=cfg)
        assert done.returncode == 0, done.stderr[-3000:]
        commands[name] = {}
        for line in re.findall(r"python -m dozerlab \S+ .*", done.stdout):
            commands[name].setdefault(line.split()[3], set()).add(line)
    before, after = commands["before"], commands["after"]
    assert before.keys() == after.keys()
    assert {c for c in before if before[c] != after[c]} == changed
    assert {"train", "simulate"} <= before.keys()
    assert ({"adaptive-record", "adaptive-curve"} <= before.keys()) == adaptive
    if "simulate" in changed:  # NDEM's own runs unchanged, the draws added
        assert before["simulate"] < after["simulate"]


def test_lint_finds_nothing_but_the_per_rule_environments(tmp_path):
    """docs/architecture.md says why rules have no conda/container directive; nothing else lints."""
    done = snakemake(tmp_path, "--lint")
    lints = re.findall(r"^\s+\* (.+?):?$", done.stdout + done.stderr, flags=re.M)
    assert lints, (done.stdout + done.stderr)[-3000:]
    assert set(lints) == {"Specify a conda environment or container for each rule."}


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


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("sampling: {bins: [0, 4, 4]}\n", r"config field 'sampling\.bins\[0\]'.*allowed: >= 1"),
        ("sweep: {speeds: [1.0, 1.0, 1]}\n", r"'sweep\.speeds'.*allowed: each value once"),
        ("sweep: {speeds: [1e9]}\n", r"'sweep\.speeds\[0\]'.*allowed: <= 20"),
        ("sweep: {depths: [0.34]}\n", r"'sweep\.depths\[0\]'.*deeper than the hill bed"),
        (
            "sweep: {depths: [1.0e-250]}\n",
            r"(?s)bad\.yaml.*'sweep\.depths\[0\]'.*allowed: >= 0\.001",
        ),
        ("solver: {dt: .nan}\n", r"(?s)bad\.yaml.*'solver\.dt': nan is not a finite number"),
        ("learn: {epochs: 3.0}\n", r"'learn\.epochs': 3\.0 is not of type 'integer'"),
        (
            "seed: 1\nseed: 2\n",
            r"bad\.yaml gives the key 'seed' twice in one mapping \(lines 1 and 2",
        ),
        ("sampling: {bins: [1024, 1024, 1024]}\n", r"sampling\.bins.*GiB of memory"),
    ],
)
def test_invalid_config_is_refused_before_any_job(tmp_path, text, message):
    bad = tmp_path / "bad.yaml"
    bad.write_text(text)
    done = snakemake(tmp_path, configfile=bad)
    assert done.returncode != 0
    assert re.search(message, done.stderr), done.stderr[-3000:]
    assert not (tmp_path / "results").exists() and not (tmp_path / "mlflow.db").exists()


def test_transfer_points_on_the_users_terrain_are_simulated_validated_and_reduced(tmp_path):
    """A profile and a heightmap written into the config: a transfer point on each is built
    (the heightmap file an input of its bed), validated by every model as unseen terrain and
    run by every reduced model, in a dry run."""
    quick = yaml.safe_load(QUICK.read_text())
    np.save(tmp_path / "site.npy", np.array([[0.4, 0.5], [0.5, 0.6], [0.4, 0.5]]))
    quick["scenarios"]["ramp"] = {"kind": "profile", "points": [[0.0, 0.4], [2.0, 0.6]]}
    quick["scenarios"]["site"] = {"kind": "heightmap", "file": "site.npy"}
    quick["sweep"]["transfer"] = [
        {"scenario": "ramp", "speed": 1.0, "depth": 0.06},
        {"scenario": "site", "speed": 1.0, "depth": 0.06},
    ]
    cfg = tmp_path / "terrain.yaml"
    cfg.write_text(yaml.safe_dump(quick))
    done = snakemake(tmp_path, "-n", "-p", configfile=cfg)
    assert done.returncode == 0, done.stderr[-3000:]
    out = done.stdout
    beds = re.findall(r"dozerlab bed --scenario (\w+)", out)
    assert sorted(beds) == ["hill", "ramp", "site"]
    assert re.search(r"rule bed:\n\s+input: site\.npy\n", out)
    for name in ("ramp", "site"):
        assert f"--out 'results/fields/{name}/speed~1.0_depth~0.06.zarr'" in out
    validations = re.findall(r"dozerlab validate(?:-dynamics)? .*", out)
    assert len(validations) == len(MODELS) + len(DYNAMICS)
    assert all(
        "--transfer 'results/fields/ramp/speed~1.0_depth~0.06.zarr' "
        "'results/fields/site/speed~1.0_depth~0.06.zarr'" in v
        for v in validations
    )
    # rule reduce: one job a model, every held-out point (the transfer points among them)
    reduced = re.findall(
        r"dozerlab reduce-points .*--dynamics-model (\w+) .*--points ([^-]*)--.*--rule reduce ", out
    )
    assert sorted(m for m, _ in reduced) == sorted(REDUCED)
    assert all(
        {"ramp/speed~1.0_depth~0.06", "site/speed~1.0_depth~0.06"} <= set(p.split())
        for _, p in reduced
    )
