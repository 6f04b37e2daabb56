# Beds (one settled bed per scenario, reused by all its runs) and blade trajectories.


rule bed:
    input:
        heightmap_input,
    output:
        bed=P.pattern("bed"),
        plot=report(P.pattern("bed_plot"), caption="../report/bed.rst", category="Beds"),
    log:
        "logs/bed/{scenario}.log",
    threads: config["threads"]["bed"]
    resources:
        **cluster.job_resources(config, "bed"),
    params:
        cfg=lambda wc: config_json(
            "seed", "solver", "material", "bed", "scenarios", scenario=wc.scenario,
            fields={"solver": BED_SOLVER_FIELDS},
        ),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab bed --scenario {wildcards.scenario} --config {params.cfg:q}"
        " --out {output.bed:q} --plot {output.plot:q} --threads {threads} --no-progress > {log:q} 2>&1"


rule trajectory:
    input:
        canonical,
        bed=P.pattern("bed"),
    output:
        csv=P.pattern("trajectory"),
        plot=report(
            P.pattern("trajectory_plot"),
            caption="../report/trajectory.rst",
            category="Trajectories",
            subcategory="{scenario}",
            labels={"speed (m/s)": "{speed}", "depth (m)": "{depth}"},
        ),
    log:
        P.log_pattern("trajectory"),
    threads: 1
    resources:
        **cluster.job_resources(config, "trajectory"),
    priority: run_priority
    params:
        cfg=lambda wc: config_json(
            "solver", "scenarios", "blade", "trajectory", scenario=wc.scenario,
            fields={"solver": BED_SOLVER_FIELDS},
        ),
    shell:
        "python -m dozerlab trajectory --bed {input.bed:q} --speed {wildcards.speed} --depth {wildcards.depth}"
        " --config {params.cfg:q} --out {output.csv:q} --plot {output.plot:q} > {log:q} 2>&1"
