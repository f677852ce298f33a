# Helpers shared by the stage files: scenario configs, targets, paths.
import json
import os
import re
from pathlib import Path

from refflow.config import deep_merge
from refflow.io import source_digest
from sim.config import STAGE_SECTIONS

RESULTS = config.get("results_dir", "results")


# The digest of the code each stage runs, passed as a param: Snakemake re-runs a job whose params
# changed but does not look inside the code a command imports, so without it an updated tool
# would leave old results in place (or meet the old tool's parts at `refflow merge`, which
# refuses to mix them).
CODE = {package: source_digest(Path(workflow.main_snakefile).parent, package)
        for package in ("sim", "flow", "analysis")}
METHODS = list(config["methods"])


def _replicates(scenarios):
    """``{scenario: (group, seed)}``: a scenario with ``seeds: [a, b, c]`` runs once per seed
    (fresh noise, texture and excitation draws), as ``NAME`` (seed a), ``NAME-seedb`` and
    ``NAME-seedc``; the summary reports the group's mean and range. Without ``seeds``:
    ``(NAME, None)``, the defaults' seed."""
    out = {}
    for name, cfg in scenarios.items():
        seeds = cfg.get("seeds") or []
        if not seeds:
            out[name] = (name, None)
        for i, seed in enumerate(seeds):
            replicate = name if i == 0 else f"{name}-seed{int(seed)}"
            if replicate in out or (i > 0 and replicate in scenarios):
                raise ValueError(f"scenario {replicate!r} is both configured and a seed replicate of {name!r}")
            out[replicate] = (name, int(seed))
    return out


REPLICATES = _replicates(config["scenarios"])
SCENARIOS = list(REPLICATES)


def scenario_config(scenario):
    group, seed = REPLICATES[scenario]
    merged = deep_merge(config["defaults"], config["scenarios"][group])
    merged.pop("seeds", None)
    if seed is not None:
        merged["seed"] = seed
    return merged


def scenario_group(wildcards):
    """The configured scenario a seed replicate belongs to (itself without seeds)."""
    return REPLICATES[wildcards.scenario][0]


def scenario_config_json(wildcards):
    # A string param: Snakemake re-runs the scenario's chain only when it changes.
    return json.dumps(scenario_config(wildcards.scenario), sort_keys=True)




def stage_config_json(wildcards):
    merged = scenario_config(wildcards.scenario)
    sections = STAGE_SECTIONS[wildcards.stage]
    return json.dumps({key: merged[key] for key in sections if key in merged}, sort_keys=True)


def stage_config(stage):
    return f"{RESULTS}/{{scenario}}/config/{stage}.yaml"


def scenario_methods(scenario):
    return scenario_config(scenario).get("methods", METHODS)


def calibration_board(wildcards):
    """The checkerboard of `python -m sim render calibration` and `refflow calibrate` (config
    track.calibration_board, inner corners COLSxROWS)."""
    return str(scenario_config(wildcards.scenario)["track"]["calibration_board"])


def calibration_square_mm(wildcards):
    return float(scenario_config(wildcards.scenario)["track"]["calibration_square_mm"])


def track_config(scenario):
    return scenario_config(scenario).get("track", {})


def _options(cfg, keys):
    return [f"--{key.replace('_', '-')} {cfg[key]}" for key in keys if key in cfg]


def measure_args(wildcards):
    """`refflow track` options that decide what is measured in each frame."""
    cfg = track_config(wildcards.scenario)
    params = cfg.get("methods", {}).get(wildcards.method, {})
    args = [f"--param {key}={value}" for key, value in sorted(params.items())]
    return " ".join(args + _options(cfg, ("grid_step", "reference_frame", "reference_average")))


def filter_args(wildcards):
    """Options of the paper's filtering and averaging (eq. 10-12), given to track or merge."""
    return " ".join(_options(track_config(wildcards.scenario), ("filter", "threshold_ratio", "mcr_threshold")))


def uses_calibration(scenario):
    return bool(track_config(scenario).get("calibrate", True))


def track_inputs(wildcards):
    """What the tool is given, like a user: the video, the masks, the clicked scale points,
    the recording's place on the sensor and (by default) the calibration."""
    render = f"{RESULTS}/{wildcards.scenario}/render"
    inputs = {"video": f"{render}/video.mp4", "mask": f"{render}/mask.png",
              "background": f"{render}/background.png", "scale": f"{render}/scale.json",
              "recording": f"{render}/recording.json"}
    if uses_calibration(wildcards.scenario):
        inputs["calibration"] = f"{RESULTS}/{wildcards.scenario}/calibration/calibration.json"
    return inputs


def setup_args(wildcards, input):
    """--calibration and --background-mask, as the scenario asks (the paper's KLT baseline
    has no camera-motion compensation: only reference-frame methods get the background)."""
    return _setup_args(wildcards.scenario, wildcards.method, input)


def _setup_args(scenario, method, input):
    args = []
    if "calibration" in input.keys():
        args.append(f"--calibration {input.calibration} --video-origin {input.recording}")
    if track_config(scenario).get("background_compensation", False) and method_kind(method) == "dense":
        args.append(f"--background-mask {input.background}")
    return " ".join(args)


def regions_config(scenario):
    return scenario_config(scenario).get("regions")


def has_regions(scenario):
    """The scenario measures its sensor heights as regions of one run (a `regions` section)."""
    return regions_config(scenario) is not None


def regions_method(wildcards):
    return regions_config(wildcards.scenario).get("method", "deepflow")


def regions_track_args(wildcards, input):
    """`refflow track` options of the regions run: the scenario's reference and filtering
    options (no per-method --param: the tool's defaults) and its calibration."""
    cfg = track_config(wildcards.scenario)
    options = _options(cfg, ("grid_step", "reference_frame", "reference_average", "filter",
                             "threshold_ratio", "mcr_threshold"))
    return " ".join(options + [_setup_args(wildcards.scenario, regions_method(wildcards), input)])


def modal_args(wildcards):
    """`refflow modal` options of the regions run: --modes and --band."""
    cfg = regions_config(wildcards.scenario)
    args = [f"--modes {int(cfg.get('modes', 2))}"]
    if "band_hz" in cfg:
        low, high = cfg["band_hz"]
        args.append(f"--band {low},{high}")
    return " ".join(args)


def modal_video_files():
    return [f"{RESULTS}/{scenario}/metrics/modal_video_vs_model.json"
            for scenario in SCENARIOS if has_regions(scenario)]


def method_kind(method):
    # Imported on use: only the track rules need the registry.
    from flow.methods.registry import kinds

    known = kinds()
    if method not in known:
        raise ValueError(f"config lists method {method!r}, not registered: {', '.join(known)}")
    return known[method]


def methods_of_kind(kind):
    """Regex of the configured methods of one kind (a wildcard constraint of the track rules)."""
    used = sorted({m for s in SCENARIOS for m in scenario_methods(s)})
    return "|".join(re.escape(m) for m in used if method_kind(m) == kind) or "^$"


def frame_count(scenario):
    """Frames the render writes (sim.render: floor(duration_s * fps))."""
    cfg = scenario_config(scenario)
    return int(float(cfg["duration_s"]) * float(cfg.get("camera", {}).get("fps", 60.0)) + 1e-9)


def track_part_count(scenario):
    """Frame ranges a dense method's run is split into (`track.chunk_frames`; 0: one)."""
    chunk = int(track_config(scenario).get("chunk_frames", 0) or 0)
    return 1 if chunk <= 0 else max(1, round(frame_count(scenario) / chunk))


def part_frames(wildcards):
    """`--frames START:END` of one part; the last part runs to the end of the video."""
    part, parts = int(wildcards.part), track_part_count(wildcards.scenario)
    chunk = int(track_config(wildcards.scenario).get("chunk_frames", 0) or 0)
    start = part * chunk if parts > 1 else 0
    stop = "" if part == parts - 1 else (part + 1) * chunk
    return f"{start}:{stop}"


def track_parts(wildcards):
    return [
        f"{RESULTS}/{wildcards.scenario}/track/parts/{wildcards.method}.{part}.npz"
        for part in range(track_part_count(wildcards.scenario))
    ]


def metrics_files():
    return [
        f"{RESULTS}/{scenario}/metrics/{method}.json"
        for scenario in SCENARIOS
        for method in scenario_methods(scenario)
    ]


def all_outputs():
    outputs = [f"{RESULTS}/summary.csv", f"{RESULTS}/summary.md", f"{RESULTS}/table1.md"]
    outputs += key_figure_paths() + render_figure_paths()
    for scenario in SCENARIOS:
        outputs += [
            f"{RESULTS}/{scenario}/sim/modes.json",
            f"{RESULTS}/{scenario}/metrics/modal.json",
        ]
        # a scenario run only as regions (no methods) has no per-method figures
        if scenario_methods(scenario):
            outputs.append(f"{RESULTS}/{scenario}/figures")
    return outputs + modal_video_files()


KEY_SCENARIO = config.get("key_figures", {}).get("scenario", SCENARIOS[0])
OCCLUSION_SCENARIO = config.get("key_figures", {}).get("occlusion_scenario")
KEY_FIGURES = [
    "fig6_poi_vs_corners",
    "fig7_gradient_magnitude",
    "fig8_time_histories",
    "fig9_psd",
]


def key_figure_names():
    """The key scenario's figures kept in git (Fig. 11 where that scenario runs KLT)."""
    return KEY_FIGURES + (["fig11_klt_features"] if "klt" in scenario_methods(KEY_SCENARIO) else [])


def key_figure_paths():
    names = key_figure_names() + (["fig10_occlusion"] if OCCLUSION_SCENARIO else [])
    return [f"{RESULTS}/figures/{name}.png" for name in names]


def render_figure_paths():
    return [
        f"{RESULTS}/figures/render_{view}.png" for view in ("full", "crop", "occluded", "occluding")
    ]
