# An adaptive sweep (sweep.adaptive, docs/adaptive.md). One checkpoint per round writes the
# round's points (round 0: the initial design); the input functions below read them back once
# written, and Snakemake re-evaluates the DAG: the round's NDEM runs (rule simulate), the models
# trained on the runs so far and their validations (adaptive_train, adaptive_validate) are
# ordinary jobs, and round r + 1's checkpoint waits for round r's runs.
ADAPTIVE = config["sweep"]["adaptive"]
ADAPTIVE_ROUNDS = list(range(ADAPTIVE["rounds"] + 1))
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


wildcard_constraints:
    round="[0-9]+",


checkpoint adaptive_points:
    input:
        unpack(adaptive_points_input),
    output:
        P.pattern("adaptive_points"),
    log:
        "logs/adaptive_points/round~{round}.log",
    threads: 1
    resources:
        **cluster.job_resources(config, "validate"),
    params:
        cfg=lambda wc: config_json("seed", "sweep", "mlflow"),
        inputs=lambda wc, input: " ".join([flag("previous", input.previous), flag("stores", input.stores)]),
    shell:
        "python -m dozerlab adaptive-points --round {wildcards.round} --config {params.cfg:q} {params.inputs}"
        " --out {output:q} > {log:q} 2>&1"


rule adaptive_train:
    input:
        lambda wc: adaptive_runs_through(int(wc.round)),
    output:
        directory(P.pattern("adaptive_model")),
    log:
        "logs/adaptive_train/round~{round}/{model}.log",
    threads: config["threads"]["train"]
    resources:
        **cluster.job_resources(config, "train"),
    priority: train_priority
    params:
        cfg=lambda wc: config_json("seed", "learn", "mlflow"),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab train --model {wildcards.model} --train {input:q} --config {params.cfg:q}"
        " --out {output:q} --threads {threads} > {log:q} 2>&1"


rule adaptive_validate:
    input:
        model=P.pattern("adaptive_model"),
        interpolation=fields_of("interpolation"),
        extrapolation=fields_of("extrapolation"),
    output:
        json=P.pattern("adaptive_validation"),
        plots=directory(P.pattern("adaptive_validation_plots")),
    log:
        "logs/adaptive_validate/round~{round}/{model}.log",
    threads: 1
    resources:
        **cluster.job_resources(config, "validate"),
    params:
        cfg=lambda wc: config_json("mlflow"),
        held_out=lambda wc, input: " ".join(
            [flag("interpolation", input.interpolation), flag("extrapolation", input.extrapolation)]
        ),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab validate --model {input.model:q} {params.held_out} --out {output.json:q}"
        " --plots {output.plots:q} --config {params.cfg:q} --threads {threads} > {log:q} 2>&1"


# One MLflow run per round: its points and scores, the models' held-out errors after it.
rule adaptive_record:
    input:
        rounds=lambda wc: [adaptive_points_file(k) for k in range(int(wc.round) + 1)],
        validations=lambda wc: [
            str(P.adaptive_path("adaptive_validation", RESULTS, int(wc.round), m)) for m in validated_models()
        ],
    output:
        P.pattern("adaptive_record"),
    log:
        "logs/adaptive_record/round~{round}.log",
    threads: 1
    resources:
        **cluster.job_resources(config, "validate"),
    params:
        cfg=lambda wc: config_json("mlflow"),
        validations=lambda wc, input: flag("validations", input.validations),
    shell:
        "python -m dozerlab adaptive-record --config {params.cfg:q} --rounds {input.rounds:q} {params.validations}"
        " --out {output:q} > {log:q} 2>&1"


rule adaptive_curve:
    input:
        rounds=lambda wc: [adaptive_points_file(r) for r in ADAPTIVE_ROUNDS],
        records=[str(P.adaptive_path("adaptive_record", RESULTS, r)) for r in ADAPTIVE_ROUNDS],
        stores=adaptive_curve_stores,
        held_out=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
    output:
        csv=P.pattern("learning_curve"),
        plots=directory(P.pattern("learning_curve_plots")),
    log:
        "logs/adaptive_curve.log",
    threads: config["threads"]["train"]
    resources:
        **cluster.job_resources(config, "train"),
    params:
        cfg=lambda wc: config_json("seed", "sweep", "learn", "mlflow"),
        results=lambda wc: RESULTS,
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab adaptive-curve --config {params.cfg:q} --rounds {input.rounds:q}"
        " --results {params.results:q} --out {output.csv:q} --plots {output.plots:q} --threads {threads} > {log:q} 2>&1"


def adaptive_report_inputs():
    """What the report shows of an adaptive sweep: its learning curve (nothing without one)."""
    return [P.pattern("learning_curve"), P.pattern("learning_curve_plots")] if ADAPTIVE["enabled"] else []


def adaptive_targets():
    """What rule all builds for an adaptive sweep: every round's record and the learning curve,
    and with compare (the grid's runs are made anyway) the report, whose sections show the grid's
    models beside the adaptive section."""
    records = [str(P.adaptive_path("adaptive_record", RESULTS, r)) for r in ADAPTIVE_ROUNDS]
    page = [P.pattern("report"), P.pattern("report_animations")] if ADAPTIVE["compare"] else []
    return records + adaptive_report_inputs() + page
