# NDEM runs with field sampling: one zarr field store per sweep point.


rule simulate:
    input:
        canonical,
        bed="results/beds/{scenario}.npz",
        trajectory="results/trajectories/{scenario}/speed~{speed}_depth~{depth}.csv",
    output:
        # A directory: Snakemake removes it if the job fails; the command builds it in a
        # temporary sibling and renames it when complete, so a killed job leaves no store.
        directory("results/fields/{scenario}/speed~{speed}_depth~{depth}.zarr"),
    benchmark:
        "results/benchmarks/simulate/{scenario}/speed~{speed}_depth~{depth}.tsv"
    log:
        "logs/simulate/{scenario}/speed~{speed}_depth~{depth}.log",
    threads: config["threads"]["simulate"]
    params:
        cfg=lambda wc: config_json(
            "seed", "solver", "material", "bed", "scenarios", "blade", "sampling", scenario=wc.scenario
        ),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab simulate --bed {input.bed:q} --trajectory {input.trajectory:q}"
        " --config {params.cfg:q} --out {output:q} --threads {threads} > {log:q} 2>&1"


# On request only (not part of `all`): field slices, the force plot and a GIF of one store.
rule plot_fields:
    input:
        canonical,
        store="results/fields/{scenario}/speed~{speed}_depth~{depth}.zarr",
    output:
        directory("results/plots/{scenario}/speed~{speed}_depth~{depth}"),
    log:
        "logs/plot_fields/{scenario}/speed~{speed}_depth~{depth}.log",
    threads: 1
    shell:
        "python -m dozerlab plot-fields {input.store:q} --out {output:q} > {log:q} 2>&1"
