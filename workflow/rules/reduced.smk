# The live reduced simulation (SPEC §9) on the held-out points, measured against their NDEM runs.


rule reduce:
    input:
        canonical,
        bed=P.pattern("bed"),
        trajectory=P.pattern("trajectory"),
        # the NDEM run of the point: replay's fields, and the run the reduced one is aligned with
        ndem=P.pattern("field"),
        force_model=lambda wc: str(P.model_path(RESULTS, config["reduced"]["force_model"])),
        dynamics=dynamics_input,
    output:
        store=directory(P.pattern("reduced")),
        state=P.pattern("reduced_state"),
    benchmark:
        P.pattern("reduce_benchmark")
    log:
        "logs/reduce/{dynamics_model}/{scenario}/speed~{speed}_depth~{depth}.log",
    # the NDEM run's threads: the speed-up compares the two at the same thread count
    resources:
        **cluster.job_resources(config, "reduce"),
    threads: config["threads"]["simulate"]
    params:
        cfg=lambda wc: config_json("seed", "solver", "material", "blade", "sampling", "reduced", "mlflow"),
        dynamics=lambda wc, input: input.dynamics or "replay",
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab reduce --bed {input.bed:q} --trajectory {input.trajectory:q}"
        " --dynamics {params.dynamics:q} --ndem {input.ndem:q} --force-model {input.force_model:q}"
        " --config {params.cfg:q} --out {output.store:q} --state {output.state:q} --threads {threads}"
        " --scenario {wildcards.scenario} --speed {wildcards.speed} --depth {wildcards.depth} > {log:q} 2>&1"


rule compare_reduced:
    input:
        reduced=lambda wc: reduced_of(wc.dynamics_model),
        ndem=[str(P.field_path(RESULTS, p)) for p in HELD_OUT],
        states=[str(P.state_path(RESULTS, p)) for p in HELD_OUT],
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
