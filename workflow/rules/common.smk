# Helpers shared by the stage files: scenario configs, targets, paths.
import json
import os
import re

from refflow.config import deep_merge

RESULTS = config.get("results_dir", "results")
SCENARIOS = list(config["scenarios"])
METHODS = list(config["methods"])


def scenario_config(scenario):
    return deep_merge(config["defaults"], config["scenarios"][scenario])


def scenario_config_json(wildcards):
    # A string param: Snakemake re-runs the scenario's chain only when it changes.
    return json.dumps(scenario_config(wildcards.scenario), sort_keys=True)


# The config sections each stage reads: a stage re-runs only when its own sections change
# (a new tracking parameter does not re-render the video).
STAGE_SECTIONS = {
    "sim": ["seed", "duration_s", "beam", "damping", "excitation", "sensor", "simulation"],
    "render": ["seed", "duration_s", "camera", "scene", "occlusion", "codec", "sensor"],
}


def stage_config_json(wildcards):
    merged = scenario_config(wildcards.scenario)
    sections = STAGE_SECTIONS[wildcards.stage]
    return json.dumps({key: merged[key] for key in sections if key in merged}, sort_keys=True)


def stage_config(stage):
    return f"{RESULTS}/{{scenario}}/config/{stage}.yaml"


def scenario_methods(scenario):
    return scenario_config(scenario).get("methods", METHODS)


def track_args(wildcards):
    """`refflow track` options from the scenario's `track` section."""
    cfg = scenario_config(wildcards.scenario).get("track", {})
    params = cfg.get("methods", {}).get(wildcards.method, {})
    args = [f"--param {key}={value}" for key, value in sorted(params.items())]
    for key in ("filter", "threshold_ratio", "mcr_threshold", "grid_step", "reference_frame"):
        if key in cfg:
            args.append(f"--{key.replace('_', '-')} {cfg[key]}")
    return " ".join(args)


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
            f"{RESULTS}/{scenario}/figures",
            f"{RESULTS}/{scenario}/sim/modes.json",
            f"{RESULTS}/{scenario}/metrics/modal.json",
        ]
    return outputs


KEY_SCENARIO = config.get("key_figures", {}).get("scenario", SCENARIOS[0])
OCCLUSION_SCENARIO = config.get("key_figures", {}).get("occlusion_scenario")
KEY_FIGURES = [
    "fig6_poi_vs_corners",
    "fig7_gradient_magnitude",
    "fig8_time_histories",
    "fig9_psd",
]


def key_figure_paths():
    names = KEY_FIGURES + (["fig10_occlusion"] if OCCLUSION_SCENARIO else [])
    return [f"{RESULTS}/figures/{name}.png" for name in names]


def render_figure_paths():
    return [
        f"{RESULTS}/figures/render_{view}.png" for view in ("full", "crop", "occluded", "occluding")
    ]
