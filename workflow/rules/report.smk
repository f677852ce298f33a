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
    output:
        report(
            directory(f"{RESULTS}/{{scenario}}/figures"),
            patterns=["{name}.png"],
            caption="../report/figures.rst",
            category="Figures",
            subcategory="{scenario}",
        ),
    params:
        track_args=lambda wc, input: " ".join(f"--track {t}" for t in input.tracks),
    log:
        f"{RESULTS}/{{scenario}}/logs/figures.log",
    shell:
        "python -m analysis figures --sensor {input.sensor} --sim-json {input.sim}"
        " --truth {input.truth} --render-json {input.render} --video {input.video}"
        " --mask {input.mask} --config {input.config} {params.track_args}"
        " --out-dir {output} > {log} 2>&1"
