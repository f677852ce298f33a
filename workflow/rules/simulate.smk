# Stage 1: the scenario's merged config, the beam's modes and its simulated motion.


rule scenario_config:
    output:
        f"{RESULTS}/{{scenario}}/config.yaml",
    params:
        merged=scenario_config_json,
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/scenario_config.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/config.log",
    shell:
        "python -m refflow.config --json {params.merged:q} --out {output} > {log} 2>&1"


rule stage_config:
    output:
        f"{RESULTS}/{{scenario}}/config/{{stage}}.yaml",
    params:
        sections=stage_config_json,
    wildcard_constraints:
        stage="|".join(STAGE_SECTIONS),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/stage_config_{{stage}}.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/config_{{stage}}.log",
    shell:
        "python -m refflow.config --json {params.sections:q} --out {output} > {log} 2>&1"


rule modes:
    input:
        stage_config("sim"),
    output:
        f"{RESULTS}/{{scenario}}/sim/modes.json",
    params:
        code=CODE["sim"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/modes.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/modes.log",
    shell:
        "python -m sim modes --config {input} --json --out {output} > {log} 2>&1"


rule simulate:
    input:
        stage_config("sim"),
    output:
        sensor=f"{RESULTS}/{{scenario}}/sim/sensor.csv",
        shapes=f"{RESULTS}/{{scenario}}/sim/shapes.npz",
        sidecar=f"{RESULTS}/{{scenario}}/sim/sim.json",
    params:
        code=CODE["sim"],
        out_dir=subpath(output.sidecar, parent=True),
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/simulate.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/simulate.tsv"
    shell:
        "python -m sim simulate --config {input} --out-dir {params.out_dir} > {log} 2>&1"
