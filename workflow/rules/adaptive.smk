# An adaptive sweep (sweep.adaptive, docs/adaptive.md). One checkpoint per round writes the
# round's points (round 0: the initial design); the input functions (common.smk) read them back once
# written, and Snakemake re-evaluates the DAG: the round's NDEM runs (rule simulate), the models
# trained on the runs so far and their validations (adaptive_train, adaptive_validate) are
# ordinary jobs, and round r + 1's checkpoint waits for round r's runs.
# Its config, checks and input functions are in common.smk.


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
        models=lambda wc: [str(P.adaptive_path("adaptive_model", RESULTS, int(wc.round), m)) for m in validated_models()],
        loops=adaptive_loop_inputs(),
        held_out=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
    output:
        P.pattern("adaptive_record"),
    log:
        "logs/adaptive_record/round~{round}.log",
    threads: 1
    resources:
        **cluster.job_resources(config, "validate"),
    params:
        cfg=lambda wc: config_json("seed", "sweep", "mlflow", "reduced", fields={"reduced": REDUCED_CURVE_FIELDS}),
        validations=lambda wc, input: flag("validations", input.validations),
        models=lambda wc, input: flag("models", input.models),
        results=lambda wc: RESULTS,
    shell:
        "python -m dozerlab adaptive-record --config {params.cfg:q} --rounds {input.rounds:q} {params.validations}"
        " {params.models} --results {params.results:q} --out {output:q} > {log:q} 2>&1"


rule adaptive_curve:
    input:
        rounds=lambda wc: [adaptive_points_file(r) for r in ADAPTIVE_ROUNDS],
        records=[str(P.adaptive_path("adaptive_record", RESULTS, r)) for r in ADAPTIVE_ROUNDS],
        stores=adaptive_curve_stores,
        held_out=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
        loops=adaptive_loop_inputs(),
    output:
        csv=P.pattern("learning_curve"),
        plots=directory(P.pattern("learning_curve_plots")),
    log:
        "logs/adaptive_curve.log",
    threads: config["threads"]["train"]
    resources:
        **cluster.job_resources(config, "train"),
    params:
        cfg=lambda wc: config_json("seed", "sweep", "learn", "mlflow", "reduced", fields={"reduced": REDUCED_CURVE_FIELDS}),
        results=lambda wc: RESULTS,
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab adaptive-curve --config {params.cfg:q} --rounds {input.rounds:q}"
        " --results {params.results:q} --out {output.csv:q} --plots {output.plots:q} --threads {threads} > {log:q} 2>&1"
