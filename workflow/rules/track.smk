# Stage 3: the measurement tool on the rendered video, once per method, like a user would.


rule track:
    input:
        video=f"{RESULTS}/{{scenario}}/render/video.mp4",
        mask=f"{RESULTS}/{{scenario}}/render/mask.png",
        scale=f"{RESULTS}/{{scenario}}/render/render.json",
    output:
        csv=f"{RESULTS}/{{scenario}}/track/{{method}}.csv",
        sidecar=f"{RESULTS}/{{scenario}}/track/{{method}}.json",
    params:
        options=track_args,
    threads: 2
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/track_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/track_{{method}}.tsv"
    shell:
        "refflow track {input.video} --mask {input.mask} --method {wildcards.method}"
        " --scale-file {input.scale} {params.options} --jobs {threads}"
        " --out {output.csv} --no-progress > {log} 2>&1"
