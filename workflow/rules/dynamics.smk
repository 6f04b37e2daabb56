# Field-evolution models (config section `dynamics`) trained on the sweep grid and validated on
# the held-out points by one-step and rollout errors.


rule train_dynamics:
    input:
        fields_of("train"),
    output:
        directory(str(P.dynamics_model_path(RESULTS, "{model}"))),
    log:
        "logs/train_dynamics/{model}.log",
    wildcard_constraints:
        model="|".join(DYNAMICS_MODELS),
    resources:
        **cluster.job_resources(config, "train_dynamics"),
    threads: config["threads"]["dynamics"]
    priority: train_dynamics_priority
    params:
        cfg=lambda wc: dynamics_config_json(),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab train-dynamics --model {wildcards.model} --train {input:q}"
        " --config {params.cfg:q} --out {output:q} --threads {threads} > {log:q} 2>&1"


rule validate_dynamics:
    input:
        model=str(P.dynamics_model_path(RESULTS, "{model}")),
        interpolation=fields_of("interpolation"),
        extrapolation=fields_of("extrapolation"),
        transfer=fields_of("transfer"),
    output:
        json=str(P.dynamics_validation_path(RESULTS, "{model}")),
        plots=directory(str(P.dynamics_plots_path(RESULTS, "{model}"))),
    log:
        "logs/validate_dynamics/{model}.log",
    wildcard_constraints:
        model="|".join(DYNAMICS_MODELS),
    resources:
        **cluster.job_resources(config, "validate_dynamics"),
    threads: 1
    params:
        cfg=lambda wc: dynamics_config_json(),
        held_out=lambda wc, input: held_out_flags(input),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab validate-dynamics --model {input.model:q} {params.held_out}"
        " --out {output.json:q} --plots {output.plots:q} --config {params.cfg:q} --threads {threads} > {log:q} 2>&1"
