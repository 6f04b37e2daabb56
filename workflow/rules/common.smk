# Shared helpers of the rules: the validated config, the sweep's points and target paths, the
# per-rule config sections and the parent MLflow run of this invocation. Computing commands run
# with NUMBA_NUM_THREADS={threads}: numba fixes its pool size when first imported, so the pool
# matches the rule's threads even if a command imports numba before it calls set_threads.
import json
import os
import shlex
import socket
import subprocess
import sys
import time
from pathlib import Path

from snakemake.exceptions import WorkflowError
from snakemake.logging import ColorizingTextHandler, logger

from dozerlab import cluster, console, headline, runtime, spool, terrain, tracking
from dozerlab.config import load_config, read_yaml, schema
from dozerlab import sweep as P
from dozerlab.reduce import LOOP_FIELDS

STARTED = time.time()
# One line per job start and end on the console (dozerlab.console); Snakemake's log under
# .snakemake/log keeps its full output, shell commands included. Dry runs (-n) and --verbose
# keep Snakemake's.
console.install(logger, ColorizingTextHandler)
# The jobs' time by rule, for the closing summary and the parent MLflow run.
JOB_CLOCK = console.JobClock()
logger.addHandler(JOB_CLOCK)

# Validate before any job runs (before onstart, so no MLflow run is started): a bad value stops
# here with the files, its field name and allowed range. Snakemake's YAML loader keeps the last
# of a key given twice, so each file is read again with ours, which refuses it.
for _path in workflow.configfiles:
    if Path(_path).is_file():  # the Snakefile's default, absent in a bare workdir, is skipped
        read_yaml(_path)
try:
    config.update(load_config(config))
except runtime.ConfigError as _exc:
    _files = " + ".join(map(str, workflow.configfiles)) or "the defaults"
    raise runtime.ConfigError(f"configuration {_files}: {_exc}") from None
POINTS = P.sweep_points(config)
HELD_OUT = [p for role in P.HELD_OUT_ROLES for p in P.by_role(POINTS, role)]
RESULTS = P.RESULTS
if not config["mlflow"]["enabled"]:
    os.environ[tracking.ENABLED_ENV] = "0"  # the jobs' tracked_run reads this
# Jobs record their MLflow runs here and one process logs them (dozerlab.spool): a job that
# imports MLflow and opens its store spends about 3 s on it.
os.environ.setdefault(spool.SPOOL_ENV, str(Path(".dozerlab", "mlflow-spool").resolve()))
# The jobs stop when this process is gone (runtime.die_with_workflow): a SIGKILLed Snakemake
# leaves no orphaned job running. A job run by a remote executor parses this file in its own
# Snakemake and watches that one.
os.environ[runtime.WORKFLOW_PID_ENV] = str(os.getpid())
os.environ[runtime.WORKFLOW_HOST_ENV] = socket.gethostname()

# Any point can be built by asking for its path, in the sweep or not; numbers are plain
# decimals with a point (P.fmt_number), so a path names one run only. The constraint on speed
# and depth is loose on purpose: any spelling reaches the rules, whose input function
# `canonical` refuses it with the canonical spelling or the reason (a tight pattern would give
# Snakemake's MissingRuleException, which says neither).
wildcard_constraints:
    scenario="|".join(sorted(config["scenarios"])),  # the presets and the config's own
    speed=P.WILDCARD_PATTERN,
    depth=P.WILDCARD_PATTERN,
    model="[a-z]+",
    draw="[1-9][0-9]*",
    dynamics_model="|".join(schema()["properties"]["reduced"]["properties"]["dynamics_models"]["items"]["enum"]),


def config_json(*sections, scenario=None, fields=None):
    """The named config sections as inline JSON for a command's --config (a rule's params).

    A rule reruns when its params change, so each rule passes only what its command reads;
    with ``scenario``, the ``scenarios`` section holds only that scenario's shape; ``fields``
    maps a section to the only fields of it the command reads ("twin.enabled": one field of a
    subsection).
    """
    doc = {name: config[name] for name in sections}
    if scenario is not None and "scenarios" in doc:
        doc["scenarios"] = {scenario: config["scenarios"][scenario]}
    if "sweep" in doc and "scenarios" not in doc:
        # the sweep's own scenarios, which its check refuses unless defined (presets always are),
        # and the bed they are checked in
        own = {p.scenario for p in POINTS} - set(terrain.PRESETS)
        if own:
            doc["scenarios"] = {s: config["scenarios"][s] for s in sorted(own)}
            doc.setdefault("bed", config["bed"])
    for name, keep in (fields or {}).items():
        kept = {}
        for key, value in doc[name].items():
            if key in keep:
                kept[key] = value
            elif isinstance(value, dict):
                sub = {k: v for k, v in value.items() if f"{key}.{k}" in keep}
                if sub:
                    kept[key] = sub
        doc[name] = kept
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


# The solver fields a bed or a trajectory reads: of the active zone only when a grain sleeps
# and wakes (a bed's pour, bed.active_zone), so switching the blade's zone reruns no bed; not
# rest_tolerance, which the pour leaves out.
BED_SOLVER_FIELDS = [k for k in config["solver"] if k not in ("active_zone", "rest_tolerance")] + [
    "active_zone.rest_speed",
    "active_zone.rest_time",
    "active_zone.wake_load",
]


def reduce_config_json():
    """What a reduce job reads: the sections of the run and, of the reduced section, the loop's
    settings (dozerlab.reduce.LOOP_FIELDS); not the targets, which only the comparison and the
    report read."""
    sections = ("seed", "solver", "material", "blade", "sampling", "reduced", "mlflow")
    return config_json(*sections, fields={"reduced": LOOP_FIELDS})


def loop_force_config_json():
    """What train_loop_force reads: seed, mlflow and learn, with learn.history the loop's
    force model's own (reduced.force_history)."""
    doc = json.loads(config_json("seed", "learn", "mlflow"))
    doc["learn"]["history"] = config["reduced"]["force_history"]
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def canonical(wildcards):
    """Refuse non-canonical spellings (speed~1, speed~1.00): they would duplicate a run."""
    P.check_canonical("speed", wildcards.speed)
    P.check_canonical("depth", wildcards.depth)
    return []


def fields_of(role):
    """The field stores of the sweep's points of one role."""
    return [str(P.field_path(RESULTS, p)) for p in P.by_role(POINTS, role)]


def flag(name, paths):
    """``--name p1 p2 …`` quoted for the shell, or nothing when there are no paths."""
    return f"--{name} " + " ".join(shlex.quote(str(p)) for p in paths) if paths else ""


def validated_models():
    """Models validated on the held-out points (none without held-out points)."""
    return config["learn"]["models"] if HELD_OUT else []


DYNAMICS_MODELS = schema()["properties"]["dynamics"]["properties"]["models"]["items"]["enum"]


def dynamics_config_json():
    """What the evolution-model jobs read: their section, the seed, tracking, and the force
    models' early-stopping blocks (shared, so the held-out split is one)."""
    split = {k: config["learn"][k] for k in ("validation_fraction", "validation_block")}
    doc = {"seed": config["seed"], "dynamics": config["dynamics"], "mlflow": config["mlflow"], "learn": split}
    return json.dumps(doc, sort_keys=True, separators=(",", ":"))


def validated_dynamics():
    """Evolution models validated on the held-out points (none without held-out points)."""
    return config["dynamics"]["models"] if HELD_OUT else []


def held_out_flags(input):
    """A validation's ``--interpolation … --extrapolation … [--transfer …]`` of its rule's inputs
    (no ``--transfer`` without transfer points: a sweep without them reruns no validation)."""
    flags = [flag("interpolation", input.interpolation), flag("extrapolation", input.extrapolation)]
    return " ".join(flags + ([flag("transfer", input.transfer)] if input.transfer else []))


def heightmap_input(wildcards):
    """The heightmap file of a scenario of kind heightmap (the bed reruns when it changes)."""
    return [f] if (f := terrain.heightmap_file(wildcards.scenario, config)) else []


def dynamics_input(wildcards):
    """The dynamics model directory a reduce job loads (none for replay: it reads the NDEM store)."""
    if wildcards.dynamics_model == "replay":
        return []
    return str(P.dynamics_model_path(RESULTS, wildcards.dynamics_model))


# The schedule on few cores (snakemake's priorities, highest first): every model trains on all
# the training runs, so those (and the trajectories they need) run before the held-out runs,
# which only the validations and reduced runs need and which fill the cores beside the
# training. The trainings start longest first (the force U-Net, then the CNN and MLP, then the
# evolution U-Net; the rest take under a minute), so the short ones fill the cores at the end.
TRAINING_RUNS = {(p.scenario, P.fmt_number(p.speed), P.fmt_number(p.depth)) for p in P.by_role(POINTS, "train")}


def is_training_run(wildcards):
    """Whether the job's point is one of the sweep's training points."""
    return (wildcards.scenario, wildcards.speed, wildcards.depth) in TRAINING_RUNS


def run_priority(wildcards):
    """1 for a training run of the sweep (its trajectory and its simulation), 0 for any other."""
    return int(is_training_run(wildcards))


def train_priority(wildcards):
    """Force models: 4 for the U-Net, 3 for the CNN and the MLP, 1 for the linear model."""
    return {"unet": 4, "cnn": 3, "mlp": 3}.get(wildcards.model, 1)


def train_dynamics_priority(wildcards):
    """Evolution models: 2 for the U-Net, 1 for the others."""
    return 2 if wildcards.model == "unet" else 1


def reduce_force_model(wildcards):
    """The force model of a dynamics model's held-out runs (rule reduce), as
    dozerlab.sweep.reduce_force_model_path gives it."""
    return str(P.reduce_force_model_path(RESULTS, config["reduced"], wildcards.dynamics_model))


TRAINING_POINTS = P.by_role(POINTS, "train")


def loop_fields_of(dynamics_model):
    """The reduced runs of one dynamics model on the training points, in fields_of("train")'s order."""
    return [str(P.reduced_path(RESULTS, dynamics_model, p)) for p in TRAINING_POINTS]


def model_runs(points, ext):
    """The reduced stores (zarr) or final states (npz) of ``points``, {dynamics_model} left a
    wildcard (one job's outputs: rules reduce and reduce_training_points)."""
    return [str(P.reduced_path(RESULTS, "{dynamics_model}", p, ext)) for p in points]


def reduced_of(dynamics_model):
    """The reduced stores and final states of one dynamics model on the held-out points."""
    return [str(P.reduced_path(RESULTS, dynamics_model, p, ext)) for p in HELD_OUT for ext in ("zarr", "npz")]


def ndem_config_json(wildcards):
    """The --config of an NDEM run of the scenario (rules simulate, twin and twin_draw)."""
    return config_json(
        "seed", "solver", "material", "bed", "scenarios", "blade", "sampling", scenario=wildcards.scenario
    )


def twins_of_held_out():
    """The twin NDEM runs (stores and final states, every one of reduced.twin.draws) of the
    held-out points when reduced.twin is enabled, else none."""
    if not config["reduced"]["twin"]["enabled"]:
        return []
    draws = config["reduced"]["twin"]["draws"]
    return [str(path) for p in HELD_OUT for run in P.twin_draws(RESULTS, p, draws) for path in run]


def reduced_comparisons():
    """The comparison JSONs of the configured dynamics models (none without held-out points)."""
    return [str(P.reduced_comparison_path(RESULTS, m)) for m in config["reduced"]["dynamics_models"]] if HELD_OUT else []


def all_targets():
    """Every result of the configured sweep, spelled as a user would ask for it (an adaptive
    sweep's: its rounds and learning curve, adaptive.smk)."""
    if config["sweep"]["adaptive"]["enabled"]:
        return adaptive_targets()
    targets = [str(P.bed_path(RESULTS, s)) for s in sorted({p.scenario for p in POINTS})]
    for p in POINTS:
        targets += [str(P.trajectory_path(RESULTS, p, "csv")), str(P.trajectory_path(RESULTS, p, "png"))]
        targets.append(str(P.field_path(RESULTS, p)))
    targets += [str(P.model_path(RESULTS, m)) for m in config["learn"]["models"]]
    targets += [str(P.validation_path(RESULTS, m)) for m in validated_models()]
    targets += [str(P.dynamics_model_path(RESULTS, m)) for m in config["dynamics"]["models"]]
    targets += [str(P.dynamics_validation_path(RESULTS, m)) for m in validated_dynamics()]
    targets += [s for m in config["reduced"]["dynamics_models"] if HELD_OUT for s in reduced_of(m)]
    targets += twins_of_held_out()
    targets += reduced_comparisons()
    targets += [P.pattern("report"), P.pattern("report_animations")]
    return targets


def check_cluster_fit():
    """On SLURM, refuse before any submission the jobs that no node of their partition can hold.

    sbatch accepts them on clusters without EnforcePartLimits and they pend forever. The jobs'
    own threads and resources are checked, so --set-threads / --set-resources count too.
    """
    plugin = workflow.executor_plugin
    if plugin is None or plugin.name != "slurm":
        return
    requests = [
        cluster.Request(
            f"{job.rule.name} ({', '.join(f'{k}={v}' for k, v in job.wildcards.items()) or 'no wildcards'})",
            job.threads,
            int(job.resources.get("mem_mb", 0)),
            str(job.resources.get("slurm_partition", "") or ""),
        )
        for job in workflow.dag.needrun_jobs()
        if not job.is_local
    ]
    cluster.check_fit(requests, cluster.slurm_nodes())


def sweep_name():
    """The parent run's name: ``sweep/`` and the stems of the config files (the Snakefile's
    config/config.yaml left out when others are laid over it), e.g. ``sweep/quick``."""
    files = list(dict.fromkeys(Path(f).resolve() for f in workflow.configfiles))
    default = Path("config", "config.yaml").resolve()
    stems = [f.stem for f in files if f != default or len(files) == 1]
    return "sweep/" + "+".join(stems or ["config"])


def start_parent_run():
    """Start this invocation's parent MLflow run and export its id to the jobs' environment."""
    if not tracking.enabled():
        return
    cmd = [sys.executable, "-m", "dozerlab", "mlflow-start", "--config", json.dumps(config),
           "--name", sweep_name(), "--tag", "configfiles=" + ",".join(map(str, workflow.configfiles))]
    try:
        # In its own session: Ctrl-C reaches Snakemake alone, which stops the command below.
        done = subprocess.run(cmd, capture_output=True, text=True, start_new_session=True)
    except KeyboardInterrupt:
        # Before any job: say so and stop (SystemExit: no traceback, Snakemake's lock released).
        print("dozerlab: interrupted while starting the MLflow parent run; no job ran", file=sys.stderr)
        sys.exit(130)
    if done.returncode != 0:
        print(done.stderr, end="", file=sys.stderr)
        raise WorkflowError(f"dozerlab mlflow-start failed (exit {done.returncode}); see the message above")
    # dozerlab's own lines (runs closed or logged for a killed workflow), not MLflow's chatter
    for line in done.stderr.splitlines():
        if line.startswith(("closed parent run", "logged", "spooled runs")):
            print(line, file=sys.stderr)
    os.environ[tracking.PARENT_ENV] = done.stdout.strip()
    start_ingest(os.environ[tracking.PARENT_ENV])


# `dozerlab mlflow-ingest --follow` beside the jobs, while this invocation runs.
INGEST = []
INGEST_LOG = Path("logs", "mlflow-ingest.log")


def start_ingest(run_id):
    """Log the jobs' spooled runs as they end, in one process beside the workflow; it writes to
    logs/mlflow-ingest.log and stops with this Snakemake (runtime.die_with_workflow)."""
    INGEST.append(spool.start_follower(run_id, INGEST_LOG))


def stop_ingest():
    """Stop the follower after the run it is logging; mlflow-end logs what is left."""
    for proc in INGEST:
        if not spool.stop_follower(proc):
            print(
                f"dozerlab: the MLflow follower (pid {proc.pid}) did not stop within "
                f"{spool.FOLLOWER_STOP_S:g} s and was killed; its stacks are in {INGEST_LOG}",
                file=sys.stderr,
            )
    INGEST.clear()


def end_parent_run(status, log):
    """End the parent run with ``status``, attaching the report (its folder: the page and its
    animations) and Snakemake's log if new, and the sweep's headline figures (dozerlab.headline)
    as its metrics.

    Snakemake 9 passes ``log`` as the list of its log files (a path in older versions).
    """
    run_id = os.environ.get(tracking.PARENT_ENV)
    if not tracking.enabled() or not run_id:
        return
    stop_ingest()
    logs = [log] if isinstance(log, (str, os.PathLike)) else list(log or [])
    artifacts = [P.pattern("report_dir")] + [str(p) for p in logs]
    cmd = [sys.executable, "-m", "dozerlab", "mlflow-end", run_id, "--status", status]
    for path in artifacts:
        cmd += ["--artifact", path]
    for key, value in (headline.metrics(RESULTS, config) | JOB_CLOCK.metrics()).items():
        cmd += ["--metric", f"{key}={value!r}"]
    subprocess.run(cmd, check=status != "FINISHED")


def print_summary():
    """The closing lines of a run that built the sweep: wall time and the jobs' time by rule,
    report, best models, the reduced simulation's targets met and missed (dozerlab.headline)."""
    wall = time.time() - STARTED
    lines = headline.summary_lines(RESULTS, config, wall)
    jobs = JOB_CLOCK.summary(wall)
    for line in lines[:1] + ([jobs] if jobs else []) + lines[1:]:
        print(line, file=sys.stderr)


# An adaptive sweep's config and input functions (the rules are in adaptive.smk).
ADAPTIVE = config["sweep"]["adaptive"]
ADAPTIVE_ROUNDS = list(range(ADAPTIVE["rounds"] + 1))
# What the curve and the records read of the reduced section: which loops, their force model
# kind, whether twins run (not their draws: they read draw 1, so more draws rerun neither).
REDUCED_CURVE_FIELDS = ["dynamics_models", "force_model", "twin.enabled"]
if ADAPTIVE["enabled"] and not HELD_OUT:
    # the rounds' errors and the learning curve are measured on them
    raise runtime.ConfigError(
        "config field 'sweep.adaptive.enabled': an adaptive sweep needs held-out points "
        "(allowed: sweep.interpolation or sweep.extrapolation not empty)"
    )


def adaptive_points_file(r):
    """Round r's points.csv, once its checkpoint has run (else Snakemake runs it first)."""
    return checkpoints.adaptive_points.get(round=str(r)).output[0]


def adaptive_round_points(r):
    """The sweep points of round r, read from its points.csv."""
    from dozerlab.adaptive.design import read_points

    return [s.point for s in read_points(adaptive_points_file(r))]


def adaptive_runs_through(r):
    """The field stores of the NDEM runs of rounds 0 … r (none for r < 0)."""
    return [str(P.field_path(RESULTS, p)) for k in range(r + 1) for p in adaptive_round_points(k)]


def adaptive_points_input(wildcards):
    """A round's checkpoint reads the points of the rounds before it and their NDEM runs."""
    r = int(wildcards.round)
    return {"previous": [adaptive_points_file(k) for k in range(r)], "stores": adaptive_runs_through(r - 1)}


def adaptive_curve_stores(wildcards):
    """The stores the learning curve trains on: the adaptive design's and, with compare, the
    grid's and the random designs' (dozerlab.adaptive.jobs.design_points)."""
    from dozerlab.adaptive.jobs import design_points

    rounds = [adaptive_round_points(r) for r in ADAPTIVE_ROUNDS]
    return [str(P.field_path(RESULTS, p)) for p in design_points(config, rounds)]


def adaptive_loop_inputs():
    """The replay runs (and twins) of the held-out points whose loops the learning curve and the
    rounds' records measure the reduced simulation on (dozerlab.adaptive.jobs.loop_inputs)."""
    from dozerlab.adaptive.jobs import loop_inputs

    return [str(p) for p in loop_inputs(config, RESULTS)] if ADAPTIVE["enabled"] else []


def adaptive_report_inputs():
    """What the report shows of an adaptive sweep: its learning curve (nothing without one)."""
    return [P.pattern("learning_curve"), P.pattern("learning_curve_plots")] if ADAPTIVE["enabled"] else []


def adaptive_targets():
    """What the target all builds for an adaptive sweep, every round's record and the learning curve,
    and with compare (the grid's runs are made anyway) the report, whose sections show the grid's
    models beside the adaptive section."""
    records = [str(P.adaptive_path("adaptive_record", RESULTS, r)) for r in ADAPTIVE_ROUNDS]
    page = [P.pattern("report"), P.pattern("report_animations")] if ADAPTIVE["compare"] else []
    return records + adaptive_report_inputs() + page
