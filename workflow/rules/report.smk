# Stage 5: figures people look at (per scenario) and the key figures kept in git.


rule scenario_figures:
    input:
        config=f"{RESULTS}/{{scenario}}/config.yaml",
        sensor=f"{RESULTS}/{{scenario}}/sim/sensor.csv",
        sim=f"{RESULTS}/{{scenario}}/sim/sim.json",
        truth=f"{RESULTS}/{{scenario}}/render/truth.csv",
        render=f"{RESULTS}/{{scenario}}/render/render.json",
        video=f"{RESULTS}/{{scenario}}/render/video.mp4",
        mask=f"{RESULTS}/{{scenario}}/render/mask.png",
        tracks=lambda wc: expand(
            f"{RESULTS}/{wc.scenario}/track/{{method}}.csv",
            method=scenario_methods(wc.scenario),
        ),
        klt_raw=lambda wc: (
            [f"{RESULTS}/{wc.scenario}/track/klt.npz"] if "klt" in scenario_methods(wc.scenario) else []
        ),
    output:
        report(
            directory(f"{RESULTS}/{{scenario}}/figures"),
            patterns=["{name}.png"],
            caption="../report/figures.rst",
            category="Figures",
            subcategory="{scenario}",
        ),
    params:
        code=CODE["analysis"],
        track_args=lambda wc, input: " ".join(f"--track {t}" for t in input.tracks),
        klt_args=lambda wc, input: " ".join(f"--klt-raw {t}" for t in input.klt_raw),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/scenario_figures.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/figures.log",
    shell:
        "python -m analysis figures --sensor {input.sensor} --sim-json {input.sim}"
        " --truth {input.truth} --render-json {input.render} --video {input.video}"
        " --mask {input.mask} --config {input.config} {params.track_args} {params.klt_args}"
        " --out-dir {output} > {log} 2>&1"


rule key_figures:
    input:
        ambient=f"{RESULTS}/{KEY_SCENARIO}/figures",
        occlusion=(
            [f"{RESULTS}/{OCCLUSION_SCENARIO}/figures"] if OCCLUSION_SCENARIO else []
        ),
    output:
        [
            report(path, caption="../report/key_figures.rst", category="Key figures")
            for path in key_figure_paths()
        ],
    params:
        names=key_figure_names(),
        out_dir=lambda wildcards, output: os.path.dirname(output[0]),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/benchmarks/key_figures.tsv"
    log:
        f"{RESULTS}/logs/key_figures.log",
    shell:
        "(for name in {params.names}; do cp {input.ambient}/$name.png {params.out_dir}/; done;"
        " if [ -n '{input.occlusion}' ]; then cp {input.occlusion}/fig10_occlusion.png"
        " {params.out_dir}/; fi) > {log} 2>&1"


rule render_figures:
    input:
        config=f"{RESULTS}/{OCCLUSION_SCENARIO or KEY_SCENARIO}/config/render.yaml",
        shapes=f"{RESULTS}/{OCCLUSION_SCENARIO or KEY_SCENARIO}/sim/shapes.npz",
    output:
        [
            report(path, caption="../report/render_figures.rst", category="Key figures")
            for path in render_figure_paths()
        ],
    params:
        code=CODE["sim"],
        out_dir=lambda wildcards, output: os.path.dirname(output[0]),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/benchmarks/render_figures.tsv"
    log:
        f"{RESULTS}/logs/render_figures.log",
    shell:
        "python -m sim render figures --config {input.config} --shapes {input.shapes}"
        " --out-dir {params.out_dir} > {log} 2>&1"


rule timings:
    input:
        all_outputs(),
    output:
        f"{RESULTS}/timings.md",
    params:
        code=CODE["analysis"],
        results=subpath(output[0], parent=True),
        # Every rule of this workflow: benchmark file names start with one of them.
        rules=lambda wildcards: " ".join(sorted(r.name for r in workflow.rules)),
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/logs/timings.log",
    shell:
        "python -m analysis timings {params.results} --rules {params.rules} --out {output}"
        " > {log} 2>&1"
