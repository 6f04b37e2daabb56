# Models trained on the sweep grid and validated on the held-out points.


rule train:
    input:
        fields_of("train"),
    output:
        directory(P.pattern("model")),
    log:
        "logs/train/{model}.log",
    threads: config["threads"]["train"]
    resources:
        **cluster.job_resources(config, "train"),
    priority: train_priority
    params:
        cfg=lambda wc: config_json("seed", "learn", "mlflow"),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab train --model {wildcards.model} --train {input:q} --config {params.cfg:q}"
        " --out {output:q} --threads {threads} > {log:q} 2>&1"


rule validate:
    input:
        model=P.pattern("model"),
        interpolation=fields_of("interpolation"),
        extrapolation=fields_of("extrapolation"),
        transfer=fields_of("transfer"),
    output:
        json=P.pattern("validation"),
        plots=directory(P.pattern("validation_plots")),
    log:
        "logs/validate/{model}.log",
    threads: 1
    resources:
        **cluster.job_resources(config, "validate"),
    params:
        cfg=lambda wc: config_json("mlflow"),
        held_out=lambda wc, input: held_out_flags(input),
    shell:
        "NUMBA_NUM_THREADS={threads} python -m dozerlab validate --model {input.model:q} {params.held_out} --out {output.json:q}"
        " --plots {output.plots:q} --config {params.cfg:q} --threads {threads} > {log:q} 2>&1"
