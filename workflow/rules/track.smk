# Stage 3: the measurement tool on the rendered video, once per method, like a user would.
# Reference-frame (dense) methods measure every frame against the reference (`deepflow` in
# chains fixed by the frame index, so a range gives the numbers of a whole run): their runs
# are split into frame ranges (`track.chunk_frames`) that run as separate jobs, then merged.
# KLT follows its features from frame to frame and runs as one job.


rule track_part:
    input:
        unpack(track_inputs),
    output:
        temp(f"{RESULTS}/{{scenario}}/track/parts/{{method}}.{{part}}.npz"),
    wildcard_constraints:
        method=methods_of_kind("dense"),
        part=r"\d+",
    params:
        code=CODE["flow"],
        frames=part_frames,
        measure=measure_args,
        setup=setup_args,
    threads: 2
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/track_{{method}}.{{part}}.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/track_part_{{method}}.{{part}}.tsv"
    shell:
        "refflow track {input.video} --mask {input.mask} --method {wildcards.method}"
        " {params.measure} {params.setup} --frames {params.frames} --jobs {threads}"
        " --raw-tracks {output} --no-progress > {log} 2>&1"


rule merge_track:
    input:
        parts=track_parts,
        scale=f"{RESULTS}/{{scenario}}/render/scale.json",
    output:
        csv=f"{RESULTS}/{{scenario}}/track/{{method}}.csv",
        sidecar=f"{RESULTS}/{{scenario}}/track/{{method}}.json",
    wildcard_constraints:
        method=methods_of_kind("dense"),
    params:
        code=CODE["flow"],
        filters=filter_args,
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/track_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/merge_track_{{method}}.tsv"
    shell:
        "refflow merge {input.parts} --scale-file {input.scale} {params.filters}"
        " --out {output.csv} > {log} 2>&1"


rule track:
    input:
        unpack(track_inputs),
    output:
        csv=f"{RESULTS}/{{scenario}}/track/{{method}}.csv",
        sidecar=f"{RESULTS}/{{scenario}}/track/{{method}}.json",
        # every feature's track: Fig. 11 shows what each one reads
        raw=f"{RESULTS}/{{scenario}}/track/{{method}}.npz",
    wildcard_constraints:
        method=methods_of_kind("sparse"),
    params:
        code=CODE["flow"],
        measure=measure_args,
        setup=setup_args,
        filters=filter_args,
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/track_{{method}}.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/track_{{method}}.tsv"
    shell:
        "refflow track {input.video} --mask {input.mask} --method {wildcards.method}"
        " {params.measure} {params.setup} --scale-file {input.scale} {params.filters}"
        " --out {output.csv} --raw-tracks {output.raw} --no-progress > {log} 2>&1"


# The sensor's heights as the regions of one run (a scenario with a `regions` section): one
# flow per frame, each region filtered and averaged on its own, one CSV with a region column.
rule track_regions:
    input:
        unpack(track_inputs),
        regions=f"{RESULTS}/{{scenario}}/render/regions.png",
    output:
        csv=f"{RESULTS}/{{scenario}}/track/regions.csv",
        sidecar=f"{RESULTS}/{{scenario}}/track/regions.json",
    # One run of the default over the whole clip (the modal scenario's: 18 CPU minutes), its
    # chains spread over the cores; the numbers do not depend on --jobs.
    threads: 2
    params:
        code=CODE["flow"],
        method=regions_method,
        options=regions_track_args,
    conda:
        "../envs/refflow.yaml"
    log:
        f"{RESULTS}/{{scenario}}/logs/track_regions.log",
    benchmark:
        f"{RESULTS}/{{scenario}}/benchmarks/track_regions.tsv"
    shell:
        "refflow track {input.video} --mask {input.regions} --method {params.method}"
        " {params.options} --scale-file {input.scale} --jobs {threads}"
        " --out {output.csv} --no-progress > {log} 2>&1"
