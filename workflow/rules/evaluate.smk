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
        metrics=metrics_files(),
        modal=modal_video_files(),
    output:
        csv=report(
            f"{RESULTS}/summary.csv",
            caption="../report/summary.rst",
            category="Summary",
        ),
        md=f"{RESULTS}/summary.md",
    params:
        code=CODE["analysis"],
        modal=lambda wildcards, input: " ".join(f"--modal {path}" for path in input.modal),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/benchmarks/summary.tsv"
    log:
        f"{RESULTS}/logs/summary.log",
    shell:
        "python -m analysis summary {input.metrics} {params.modal} --out {output.csv}"
        " --markdown {output.md} > {log} 2>&1"


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


# Modes identified from the video, by the tool itself, from the one run of several regions.
rule modal_video:
    input:
        f"{RESULTS}/{{scenario}}/track/regions.csv",
    output:
        json=f"{RESULTS}/{{scenario}}/metrics/modal_video.json",
        stabilisation=report(
            f"{RESULTS}/{{scenario}}/metrics/modal_video_stabilisation.png",
            caption="../report/modal_video.rst",
            category="Modal",
            subcategory="{scenario}",
        ),
        shapes=report(
            f"{RESULTS}/{{scenario}}/metrics/modal_video_shapes.png",
            caption="../report/modal_video.rst",
            category="Modal",
            subcategory="{scenario}",
        ),
    params:
        code=CODE["flow"],
        options=modal_args,
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/modal_video.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/modal_video.log",
    shell:
        "refflow modal {input} {params.options} --out {output.json} > {log} 2>&1"


rule modal_video_vs_model:
    input:
        video=f"{RESULTS}/{{scenario}}/metrics/modal_video.json",
        sensor=f"{RESULTS}/{{scenario}}/metrics/modal.json",
        sim=f"{RESULTS}/{{scenario}}/sim/sim.json",
        config=f"{RESULTS}/{{scenario}}/config.yaml",
    output:
        report(
            f"{RESULTS}/{{scenario}}/metrics/modal_video_vs_model.json",
            caption="../report/modal_video_vs_model.rst",
            category="Modal",
            subcategory="{scenario}",
        ),
    params:
        code=CODE["analysis"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/modal_video_vs_model.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/modal_video_vs_model.log",
    shell:
        "python -m analysis modal-video --video-modal {input.video} --sensor-modal {input.sensor}"
        " --sim-json {input.sim} --config {input.config} --scenario {wildcards.scenario}"
        " --out {output} > {log} 2>&1"
