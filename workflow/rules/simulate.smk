# NDEM runs with field sampling: one zarr field store per sweep point.


rule simulate:
    input:
        canonical,
        bed=P.pattern("bed"),
        trajectory=P.pattern("trajectory"),
    output:
        # A directory: Snakemake removes it if the job fails; the command builds it in a
        # temporary sibling and renames it when complete, so a killed job leaves no store.
        store=directory(P.pattern("field")),
        state=P.pattern("state"),
    benchmark:
        P.pattern("simulate_benchmark")
    log:
        P.log_pattern("simulate"),
    threads: config["threads"]["simulate"]
    resources:
        **cluster.job_resources(config, "simulate"),
    priority: run_priority
    params:
        cfg=ndem_config_json,
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab simulate --bed {input.bed:q} --trajectory {input.trajectory:q}"
        " --scenario {wildcards.scenario} --speed {wildcards.speed} --depth {wildcards.depth}"
        " --config {params.cfg:q} --out {output.store:q} --state {output.state:q} --threads {threads} > {log:q} 2>&1"


# NDEM's floor (reduced.twin): the point's NDEM run again from the bed with every grain moved by
# jitter_m in seeded random directions; compare_reduced measures it against NDEM as it does the
# reduced runs.
rule twin:
    input:
        canonical,
        bed=P.pattern("bed"),
        trajectory=P.pattern("trajectory"),
    output:
        store=directory(P.pattern("twin")),
        state=P.pattern("twin_state"),
    benchmark:
        P.pattern("twin_benchmark")
    log:
        P.log_pattern("twin"),
    threads: config["threads"]["simulate"]
    resources:
        **cluster.job_resources(config, "twin"),
    params:
        cfg=ndem_config_json,
        jitter=config["reduced"]["twin"]["jitter_m"],
        seed=config["reduced"]["twin"]["seed"],
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab simulate --bed {input.bed:q} --trajectory {input.trajectory:q}"
        " --scenario {wildcards.scenario} --speed {wildcards.speed} --depth {wildcards.depth}"
        " --jitter {params.jitter} --jitter-seed {params.seed}"
        " --config {params.cfg:q} --out {output.store:q} --state {output.state:q} --threads {threads} > {log:q} 2>&1"


# NDEM's expected run (reduced.twin.draws > 1): draw k of the twin from the jitter seed seed + k - 1.
use rule twin as twin_draw with:
    output:
        store=directory(P.pattern("twin_draw")),
        state=P.pattern("twin_draw_state"),
    benchmark:
        P.pattern("twin_draw_benchmark")
    log:
        f"logs/twin/{{scenario}}/{P.POINT_STEM}_draw~{{draw}}.log",
    params:
        cfg=ndem_config_json,
        jitter=config["reduced"]["twin"]["jitter_m"],
        seed=lambda wc: config["reduced"]["twin"]["seed"] + int(wc.draw) - 1,


# On request only (not part of `all`): field slices, the force plot and a GIF of one store.
rule plot_fields:
    input:
        canonical,
        store=P.pattern("field"),
    output:
        directory(P.pattern("field_plots")),
    log:
        P.log_pattern("plot_fields"),
    threads: 1
    resources:
        **cluster.job_resources(config, "plot_fields"),
    shell:
        "python -m dozerlab plot-fields {input.store:q} --out {output:q} > {log:q} 2>&1"
