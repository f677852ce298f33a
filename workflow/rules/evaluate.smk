# Stage 4: every measurement against the ground truth; one summary for all scenarios.


rule evaluate:
    input:
        config=f"{RESULTS}/{{scenario}}/config.yaml",
        sensor=f"{RESULTS}/{{scenario}}/sim/sensor.csv",
        sim=f"{RESULTS}/{{scenario}}/sim/sim.json",
        truth=f"{RESULTS}/{{scenario}}/render/truth.csv",
        render=f"{RESULTS}/{{scenario}}/render/render.json",
        track=f"{RESULTS}/{{scenario}}/track/{{method}}.csv",
    output:
        f"{RESULTS}/{{scenario}}/metrics/{{method}}.json",
    params:
        code=CODE["analysis"],
        group=scenario_group,
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/evaluate_{{method}}.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/evaluate_{{method}}.log",
    shell:
        "python -m analysis evaluate --sensor {input.sensor} --sim-json {input.sim}"
        " --truth {input.truth} --render-json {input.render} --track {input.track}"
        " --config {input.config}"
        " --method {wildcards.method} --scenario {wildcards.scenario} --group {params.group}"
        " --out {output}"
        " > {log} 2>&1"


rule summary:
    input:
        metrics_files(),
    output:
        csv=report(
            f"{RESULTS}/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
        ),
        md=f"{RESULTS}/summary.md",
    params:
        code=CODE["analysis"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/benchmarks/summary.tsv"
    log:
        f"{RESULTS}/logs/summary.log",
    shell:
        "python -m analysis summary {input} --out {output.csv} --markdown {output.md}"
        " > {log} 2>&1"


rule table1:
    input:
        metrics_files(),
    output:
        md=f"{RESULTS}/table1.md",
        csv=f"{RESULTS}/table1.csv",
    params:
        code=CODE["analysis"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/benchmarks/table1.tsv"
    log:
        f"{RESULTS}/logs/table1.log",
    shell:
        "python -m analysis table1 {input} --out-md {output.md} --out-csv {output.csv}"
        " > {log} 2>&1"


rule modal:
    input:
        sensor=f"{RESULTS}/{{scenario}}/sim/sensor.csv",
        sim=f"{RESULTS}/{{scenario}}/sim/sim.json",
    output:
        f"{RESULTS}/{{scenario}}/metrics/modal.json",
    params:
        code=CODE["analysis"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/modal.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/modal.log",
    shell:
        "python -m analysis modal --sensor {input.sensor} --sim-json {input.sim}"
        " --out {output} > {log} 2>&1"
