# The platform's report: the summary, the sweep table, per-point figures and the model comparison;
# results/report/index.html and its animations in results/report/animations/.


rule report:
    input:
        fields=[str(P.field_path(RESULTS, p)) for p in POINTS],
        trajectories=[str(P.trajectory_path(RESULTS, p, "png")) for p in POINTS],
        validation=[str(P.validation_path(RESULTS, m)) for m in validated_models()],
        reduced=reduced_comparisons(),
        dynamics=[str(P.dynamics_validation_path(RESULTS, m)) for m in validated_dynamics()],
        adaptive=adaptive_report_inputs(),
    output:
        # the page and its animations folder beside it; Snakemake's own report (--report) takes
        # the page alone: a folder would make it a zip
        page=report(P.pattern("report"), caption="../report/index.rst", category="Report"),
        animations=directory(P.pattern("report_animations")),
    log:
        "logs/report.log",
    threads: config["threads"]["report"]
    resources:
        **cluster.job_resources(config, "report"),
    params:
        cfg=lambda wc: config_json("sweep", "learn", "dynamics", "report", "reduced"),
    shell:
        "python -m dozerlab report --config {params.cfg:q} --results %s --out %s "
        "--processes {threads} > {log:q} 2>&1" % (P.RESULTS, P.pattern("report"))
