# The live reduced simulation (docs/models.md) on the held-out points, measured against their NDEM runs.


# One job a dynamics model runs every held-out point: the start-up (imports, models, compiled
# kernels, about 3 s) is paid once, and each point's job speed-up counts its share of it
# (reduce.compare.job_shares).
rule reduce:
    input:
        beds=[str(P.bed_path(RESULTS, s)) for s in sorted({p.scenario for p in HELD_OUT})],
        trajectories=[str(P.trajectory_path(RESULTS, p)) for p in HELD_OUT],
        # the points' NDEM runs: replay's fields, and the runs the reduced ones are aligned with
        ndem=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
        force_model=reduce_force_model,
        dynamics=dynamics_input,
    output:
        stores=[directory(s) for s in model_runs(HELD_OUT, "zarr")],
        states=model_runs(HELD_OUT, "npz"),
    benchmark:
        P.pattern("reduce_benchmark")
    log:
        "logs/reduce/{dynamics_model}.log",
    # the NDEM runs' threads: the speed-up compares the two at the same thread count
    resources:
        **cluster.job_resources(config, "reduce"),
    threads: config["threads"]["simulate"]
    params:
        cfg=lambda wc: reduce_config_json(),
        results=lambda wc: RESULTS,
        dynamics=lambda wc, input: input.dynamics or "replay",
        points=" ".join(f"{p.scenario}/{p.name}" for p in HELD_OUT),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab reduce-points --results {params.results:q}"
        " --dynamics-model {wildcards.dynamics_model} --dynamics {params.dynamics:q}"
        " --force-model {input.force_model:q} --points {params.points} --config {params.cfg:q}"
        " --rule reduce --threads {threads} > {log:q} 2>&1"


# The runs the loop's force model learns from (reduced.force_fields: loop): one learned dynamics
# model's loop on every training point, in one process, as rule reduce's.
rule reduce_training_points:
    input:
        beds=[str(P.bed_path(RESULTS, s)) for s in sorted({p.scenario for p in TRAINING_POINTS})],
        trajectories=[str(P.trajectory_path(RESULTS, p)) for p in TRAINING_POINTS],
        ndem=fields_of("train"),
        force_model=str(P.model_path(RESULTS, config["reduced"]["force_model"])),
        dynamics=dynamics_input,
    output:
        stores=[directory(s) for s in model_runs(TRAINING_POINTS, "zarr")],
        states=model_runs(TRAINING_POINTS, "npz"),
    benchmark:
        P.pattern("reduce_training_benchmark")
    log:
        "logs/reduce_training_points/{dynamics_model}.log",
    wildcard_constraints:
        dynamics_model="persistence|ridge|unet",  # replay's fields are NDEM's: no loop force model
    resources:
        **cluster.job_resources(config, "reduce_training_points"),
    threads: config["threads"]["simulate"]
    priority: 1  # the loop's force model, which the held-out runs wait for, learns from these
    params:
        cfg=lambda wc: reduce_config_json(),
        results=lambda wc: RESULTS,
        points=" ".join(f"{p.scenario}/{p.name}" for p in TRAINING_POINTS),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab reduce-points --results {params.results:q}"
        " --dynamics-model {wildcards.dynamics_model} --dynamics {input.dynamics:q}"
        " --force-model {input.force_model:q} --points {params.points} --config {params.cfg:q}"
        " --rule reduce_training_points --threads {threads} > {log:q} 2>&1"


# The loop's force model (reduced.force_fields: loop): the force model fitted to the fields this
# dynamics model's loop makes at the training points, paired row by row with NDEM's force.
rule train_loop_force:
    input:
        ndem=fields_of("train"),
        loop=lambda wc: loop_fields_of(wc.dynamics_model),
    output:
        directory(P.pattern("loop_force_model")),
    log:
        "logs/train_loop_force/{dynamics_model}.log",
    wildcard_constraints:
        dynamics_model="persistence|ridge|unet",  # replay's fields are NDEM's: results/models
    threads: config["threads"]["train"]
    resources:
        **cluster.job_resources(config, "train_loop_force"),
    params:
        cfg=lambda wc: loop_force_config_json(),
        model=config["reduced"]["force_model"],
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab train --model {params.model} --train {input.ndem:q}"
        " --loop-fields {input.loop:q} --config {params.cfg:q} --out {output:q} --threads {threads} > {log:q} 2>&1"


rule compare_reduced:
    input:
        reduced=lambda wc: reduced_of(wc.dynamics_model),
        ndem=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
        states=[str(P.state_path(RESULTS, p)) for p in HELD_OUT],
        twins=twins_of_held_out(),
    output:
        json=P.pattern("reduced_comparison"),
        plots=directory(P.pattern("reduced_comparison_plots")),
    log:
        "logs/compare_reduced/{dynamics_model}.log",
    resources:
        **cluster.job_resources(config, "compare_reduced"),
    threads: 1
    params:
        cfg=lambda wc: config_json("solver", "material", "blade", "trajectory", "sweep", "reduced", "mlflow"),
        results=lambda wc: RESULTS,
    shell:
        "python -m dozerlab compare-reduced --dynamics-model {wildcards.dynamics_model} --config {params.cfg:q}"
        " --results {params.results:q} --out {output.json:q} --plots {output.plots:q} > {log:q} 2>&1"
