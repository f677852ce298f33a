# Stage 2: the phone's video of the simulated beam, its mask, truth and calibration set.


rule render:
    input:
        config=stage_config("render"),
        shapes=f"{RESULTS}/{{scenario}}/sim/shapes.npz",
    output:
        video=f"{RESULTS}/{{scenario}}/render/video.mp4",
        mask=f"{RESULTS}/{{scenario}}/render/mask.png",
        background=f"{RESULTS}/{{scenario}}/render/background.png",
        scale=f"{RESULTS}/{{scenario}}/render/scale.json",
        recording=f"{RESULTS}/{{scenario}}/render/recording.json",
        truth=f"{RESULTS}/{{scenario}}/render/truth.csv",
        poi_truth=f"{RESULTS}/{{scenario}}/render/poi_truth.npz",
        sidecar=f"{RESULTS}/{{scenario}}/render/render.json",
    params:
        code=CODE["sim"],
        out_dir=subpath(output.sidecar, parent=True),
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/render.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/render.tsv"
    shell:
        "python -m sim render --config {input.config} --shapes {input.shapes}"
        " --out-dir {params.out_dir} --no-progress > {log} 2>&1"


rule calibration_set:
    input:
        stage_config("render"),
    output:
        directory(f"{RESULTS}/{{scenario}}/calibration/images"),
    params:
        code=CODE["sim"],
        board=calibration_board,
        square_mm=calibration_square_mm,
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/calibration_set.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/calibration_set.log",
    shell:
        "python -m sim render calibration --config {input} --board {params.board}"
        " --square-mm {params.square_mm} --out-dir {output} --no-progress > {log} 2>&1"


rule calibrate:
    input:
        images=f"{RESULTS}/{{scenario}}/calibration/images",
    output:
        f"{RESULTS}/{{scenario}}/calibration/calibration.json",
    params:
        code=CODE["flow"],
        board=calibration_board,
        square_mm=calibration_square_mm,
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/calibrate.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/calibrate.log",
    shell:
        "refflow calibrate {input.images} --board {params.board}"
        " --square-mm {params.square_mm} --out {output} > {log} 2>&1"


rule regions_mask:
    input:
        stage_config("regions"),
    output:
        f"{RESULTS}/{{scenario}}/render/regions.png",
    params:
        code=CODE["sim"],
    conda:
        "../envs/refflow.yaml"
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/regions_mask.tsv"
    log:
        f"{RESULTS}/{{scenario}}/logs/regions_mask.log",
    shell:
        "python -m sim render regions --config {input} --out {output} > {log} 2>&1"
