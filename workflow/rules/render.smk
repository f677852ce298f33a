# Stage 2: the phone's video of the simulated beam, its mask, truth and calibration set.


rule render:
    input:
        config=stage_config("render"),
        shapes=f"{RESULTS}/{{scenario}}/sim/shapes.npz",
    output:
        video=f"{RESULTS}/{{scenario}}/render/video.mp4",
        mask=f"{RESULTS}/{{scenario}}/render/mask.png",
        truth=f"{RESULTS}/{{scenario}}/render/truth.csv",
        poi_truth=f"{RESULTS}/{{scenario}}/render/poi_truth.npz",
        sidecar=f"{RESULTS}/{{scenario}}/render/render.json",
    params:
        out_dir=subpath(output.sidecar, parent=True),
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/render.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/render.tsv"
    shell:
        "python -m sim render --config {input.config} --shapes {input.shapes}"
        " --out-dir {params.out_dir} > {log} 2>&1"


rule calibration_set:
    input:
        stage_config("render"),
    output:
        directory(f"{RESULTS}/{{scenario}}/calibration/images"),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/calibration_set.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/calibration_set.log",
    shell:
        "python -m sim render calibration --config {input} --out-dir {output} > {log} 2>&1"


rule calibrate:
    input:
        images=f"{RESULTS}/{{scenario}}/calibration/images",
    output:
        f"{RESULTS}/{{scenario}}/calibration/calibration.json",
    params:
        board=lookup(dpath="calibration/board", within=config, default="9x6"),
        square_mm=lookup(dpath="calibration/square_mm", within=config, default=25),
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/calibrate.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/calibrate.log",
    shell:
        "refflow calibrate {input.images} --board {params.board}"
        " --square-mm {params.square_mm} --out {output} > {log} 2>&1"
