"""Command line: ``python -m analysis {evaluate,summary,table1,figures,modal,gates} ...``.

Bad input (missing file or column, NaN in data) prints one line naming the
file and column and exits with status 2.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from refflow.config import load_config
from refflow.io import versions, write_json

from .metrics import DEFAULTS, clean, evaluate
from .readers import model_modes_hz, read_json, read_sensor, read_track, read_truth, render_scale


def _analysis_params(config: str | None) -> dict[str, Any]:
    if not config:
        return {}
    path = Path(config)
    data = load_config(path)
    section = data.get("analysis") or {}
    unknown = sorted(set(section) - set(DEFAULTS) - {"methods", "figures"})
    if unknown:
        print(f"note: {path}: analysis keys not used by evaluate: {', '.join(unknown)}", file=sys.stderr)
    return {k: v for k, v in section.items() if k in DEFAULTS}


def cmd_evaluate(args: argparse.Namespace) -> None:
    start = time.perf_counter()
    params = _analysis_params(args.config)
    if args.max_lag_s is not None:
        params["max_lag_s"] = args.max_lag_s
    sensor = read_sensor(args.sensor)
    sim_json = read_json(args.sim_json)
    model_modes_hz(sim_json, str(args.sim_json))
    truth = read_truth(args.truth)
    render_json = read_json(args.render_json)
    mm_per_px, fps = render_scale(render_json, str(args.render_json))
    track = read_track(args.track)
    metrics = evaluate(sensor, sim_json, truth, mm_per_px, fps, track, params,
                       nominal_lag_s=float(render_json.get("camera_start_offset_s", 0.0) or 0.0))
    metrics.update({
        "method": args.method, "scenario": args.scenario, "group": args.group or args.scenario,
        "seed": sim_json.get("seed"),
        "inputs": {"sensor": args.sensor, "sim_json": args.sim_json, "truth": args.truth,
                   "render_json": args.render_json, "track": args.track},
        "conventions": "error = measured - reference, world x sign, mm unless the key says px; "
                       "reference = laser sensor low-passed (zero-phase Butterworth) and resampled at "
                       "frame time + sync_lag_s",
        "versions": versions(), "wall_s": time.perf_counter() - start,
    })
    write_json(args.out, clean(metrics))
    if "unmeasured" in metrics:
        print(f"{args.scenario}/{args.method}: valid_frac={metrics['valid_frac']:.3f}, unmeasured "
              f"({metrics['unmeasured']}) -> {args.out}")
        return
    print(f"{args.scenario}/{args.method}: rmse_mm={metrics['rmse_mm']:.4g} "
          f"max_disp_error_pct={metrics['max_disp_error_pct']:.3g} sync_lag_s={metrics['sync_lag_s']:.5f} -> {args.out}")


def cmd_summary(args: argparse.Namespace) -> None:
    from .report import (
        load_metrics,
        modal_markdown,
        summary_markdown,
        write_summary_csv,
        write_text,
    )
    rows = load_metrics(args.metrics)
    write_summary_csv(rows, args.out)
    if args.markdown:
        text = summary_markdown(rows)
        if args.modal:
            text = text.rstrip("\n") + "\n\n" + modal_markdown([read_json(p) for p in args.modal])
        write_text(args.markdown, text)
    print(f"{len(rows)} rows -> {args.out}" + (f", {args.markdown}" if args.markdown else ""))


def cmd_table1(args: argparse.Namespace) -> None:
    from .report import load_metrics
    from .table1 import write_table1
    info = write_table1(load_metrics(args.metrics), args.out_md, args.out_csv, scenario=args.scenario,
                        proposed=args.proposed, klt=args.klt)
    print(f"table 1 for scenario {info['scenario']} -> {args.out_md}, {args.out_csv}")


def _parse_tracks(items: list[str]) -> list[tuple[str, str]]:
    tracks = []
    for item in items:
        name, sep, path = item.partition("=")
        tracks.append((name, path) if sep else (Path(item).stem, item))
    return tracks


def cmd_figures(args: argparse.Namespace) -> None:
    from . import figures
    written = figures.make_all(
        sensor=args.sensor, truth=args.truth, tracks=_parse_tracks(args.track or []), out_dir=args.out_dir,
        sim_json=args.sim_json, render_json=args.render_json, video=args.video, mask=args.mask,
        params=_analysis_params(args.config), klt_raw=args.klt_raw)
    for path in written:
        print(path)


def _nested(data: dict[str, Any], *paths: tuple[str, ...]) -> Any:
    """First value found along any of ``paths`` (sim.json keeps the config under ``parameters``)."""
    for path in paths:
        node: Any = data
        for key in path:
            node = node.get(key) if isinstance(node, dict) else None
        if node is not None:
            return node
    return None


def cmd_modal(args: argparse.Namespace) -> None:
    from .modal import compare_with_model, identify, model_damping
    start = time.perf_counter()
    sensor = read_sensor(args.sensor)
    sim_json = read_json(args.sim_json)
    model_hz = model_modes_hz(sim_json, str(args.sim_json))
    heights = dict(sensor.heights)
    height = args.sensor_height_mm
    if height is None:
        height = _nested(sim_json, ("parameters", "sensor", "height_mm"), ("sensor", "height_mm"))
    if height is not None:
        heights[float(height)] = sensor.dx_mm
    if len(heights) < 2:
        raise ValueError(f"{args.sensor}: modal identification needs >= 2 heights: add dx_mm_zNNNN "
                         "columns (sensor.extra_heights_mm) or pass --sensor-height-mm")
    zs = np.array(sorted(heights))
    y = np.vstack([heights[z] for z in zs])
    length = args.beam_length_mm
    if length is None:
        length = float(_nested(sim_json, ("parameters", "beam", "length_mm"), ("beam", "length_mm")) or 1000.0)
    # band up to 1.5x the highest wanted model mode: decimates, and keeps the
    # next mode out of the peak picking
    top = float(model_hz[min(args.n_modes, model_hz.size) - 1])
    modes = identify(y, sensor.rate_hz, n_modes=args.n_modes,
                     band_hz=(0.5, min(1.5 * top, 0.4 * sensor.rate_hz)))
    out = compare_with_model(modes, zs, model_hz, beam_length_mm=length,
                             model_zeta=model_damping(sim_json, len(model_hz)))
    out.update({"method": "FDD peaks + SSI-cov (median over model orders)", "inputs": {
        "sensor": args.sensor, "sim_json": args.sim_json}, "versions": versions(),
        "wall_s": time.perf_counter() - start})
    write_json(args.out, clean(out))
    for i in range(1, len(modes) + 1):
        print(f"mode {i}: {out[f'mode{i}_freq_hz']:.4f} Hz (model {out[f'mode{i}_freq_model_hz']:.4f}), "
              f"zeta={out[f'mode{i}_damping_ratio']:.4g}, MAC={out[f'mode{i}_mac']:.4f}")


def cmd_modal_video(args: argparse.Namespace) -> None:
    import yaml

    from .modal import compare_video_modes, model_damping, video_modes_by_height
    start = time.perf_counter()
    config_path = Path(args.config)
    if not config_path.is_file():
        raise ValueError(f"{config_path}: config file not found")
    config = yaml.safe_load(config_path.read_text()) or {}
    sensor_cfg = config.get("sensor") or {}
    # region k of the run is the k-th sensor height, sorted (sim render regions)
    heights = np.unique([float(sensor_cfg.get("height_mm", 750.0)),
                         *[float(h) for h in sensor_cfg.get("extra_heights_mm") or []]])
    length = float((config.get("beam") or {}).get("length_mm", 1000.0))
    sim_json = read_json(args.sim_json)
    model_hz = model_modes_hz(sim_json, str(args.sim_json))
    modes = video_modes_by_height(read_json(args.video_modal), heights.size, str(args.video_modal))
    sensor = read_json(args.sensor_modal) if args.sensor_modal else None
    out = compare_video_modes(modes, heights, model_hz, beam_length_mm=length,
                              model_zeta=model_damping(sim_json, len(model_hz)), sensor=sensor)
    out.update({"scenario": args.scenario, "what": "modes identified by `refflow modal` from one `refflow "
                "track` run of the sensor heights as regions, against the model (Euler-Bernoulli shapes "
                "at the heights) and the modes identified from the simulated laser at the same heights",
                "units": {"freq_hz": "Hz", "freq_error_pct": "% of the model's", "damping_ratio":
                          "fraction of critical", "mac": "1", "heights_mm": "mm"},
                "inputs": {"video_modal": args.video_modal, "sensor_modal": args.sensor_modal,
                           "sim_json": args.sim_json, "config": args.config},
                "versions": versions(), "wall_s": time.perf_counter() - start})
    write_json(args.out, clean(out))
    for i in range(1, out["n_modes"] + 1):
        print(f"mode {i}: {out[f'mode{i}_freq_hz']:.4f} Hz (model {out[f'mode{i}_freq_model_hz']:.4f}, "
              f"{out[f'mode{i}_freq_error_pct']:+.2f} %), zeta={out[f'mode{i}_damping_ratio']:.4g}, "
              f"MAC={out[f'mode{i}_mac']:.4f}")


def cmd_gates(args: argparse.Namespace) -> int:
    from .gates import check, format_table, load_metrics

    spec = load_config(args.gates)
    if not isinstance(spec.get("gates"), list) or not spec["gates"]:
        raise ValueError(f"{args.gates}: needs a non-empty list under 'gates'")
    rows = check(spec["gates"], load_metrics(args.metrics))
    print(format_table(rows))
    if args.out:
        write_json(args.out, {"gates": rows, "passed": all(r["passed"] for r in rows)})
    return 0 if all(r["passed"] for r in rows) else 1


def cmd_timings(args: argparse.Namespace) -> None:
    from .timings import write_timings
    n = write_timings(args.results_dir, args.rules, args.out)
    print(f"{n} benchmark files -> {args.out}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="python -m analysis", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    ev = sub.add_parser("evaluate", help="metrics of one tracked series vs the reference")
    for name in ("sensor", "sim-json", "truth", "render-json", "track", "method", "scenario", "out"):
        ev.add_argument(f"--{name}", required=True)
    ev.add_argument("--config", help="merged scenario config.yaml (reads its `analysis` section)")
    ev.add_argument("--group", help="the scenario this run is a seed replicate of (default: --scenario)")
    ev.add_argument("--max-lag-s", type=float, help=f"sync search window (default {DEFAULTS['max_lag_s']})")
    ev.set_defaults(func=cmd_evaluate)

    su = sub.add_parser("summary", help="one row per scenario x method")
    su.add_argument("metrics", nargs="+")
    su.add_argument("--out", required=True)
    su.add_argument("--markdown")
    su.add_argument("--modal", action="append", default=[],
                    help="`analysis modal-video` JSON, repeatable: a table of the modes from the video")
    su.set_defaults(func=cmd_summary)

    t1 = sub.add_parser("table1", help="paper's Table 1 beside ours (simulated)")
    t1.add_argument("metrics", nargs="+")
    t1.add_argument("--out-md", required=True)
    t1.add_argument("--out-csv", required=True)
    t1.add_argument("--scenario", help="default: the first scenario without occlusion")
    t1.add_argument("--proposed", help="method name of the proposed method (default: first non-KLT)")
    t1.add_argument("--klt", default="klt", help="method name of KLT (default: klt)")
    t1.set_defaults(func=cmd_table1)

    fi = sub.add_parser("figures", help="Fig. 6-11 style figures (PNG + SVG)")
    fi.add_argument("--sensor", required=True)
    fi.add_argument("--truth", required=True)
    fi.add_argument("--track", action="append", help="[NAME=]PATH, repeatable")
    fi.add_argument("--sim-json")
    fi.add_argument("--render-json")
    fi.add_argument("--video", help="video for Fig. 6/7 (first frame)")
    fi.add_argument("--mask", help="mask.png for Fig. 6")
    fi.add_argument("--klt-raw", help="--raw-tracks file of a KLT run: the corners it tracked (Fig. 6) "
                    "and what each one reads (Fig. 11)")
    fi.add_argument("--config")
    fi.add_argument("--out-dir", required=True)
    fi.set_defaults(func=cmd_figures)

    mo = sub.add_parser("modal", help="multi-point modal identification vs the model")
    mo.add_argument("--sensor", required=True)
    mo.add_argument("--sim-json", required=True)
    mo.add_argument("--out", required=True)
    mo.add_argument("--sensor-height-mm", type=float, help="height of the dx_mm column")
    mo.add_argument("--beam-length-mm", type=float)
    mo.add_argument("--n-modes", type=int, default=2)
    mo.set_defaults(func=cmd_modal)

    mv = sub.add_parser("modal-video", help="modes identified from the video (refflow modal) vs the model")
    mv.add_argument("--video-modal", required=True, help="`refflow modal` JSON of the run of the sensor heights")
    mv.add_argument("--sensor-modal", help="`analysis modal` JSON: the modes of the simulated laser")
    mv.add_argument("--sim-json", required=True)
    mv.add_argument("--config", required=True, help="the scenario's config.yaml (sensor heights, beam length)")
    mv.add_argument("--scenario", required=True)
    mv.add_argument("--out", required=True)
    mv.set_defaults(func=cmd_modal_video)

    ga = sub.add_parser("gates", help="check metrics against config/gates.yaml (exit 1 on a failed gate)")
    ga.add_argument("metrics", nargs="+", help="metrics JSON files from evaluate")
    ga.add_argument("--gates", required=True, help="gates YAML")
    ga.add_argument("--out", help="JSON with every gate's result")
    ga.set_defaults(func=cmd_gates)
    ti = sub.add_parser("timings", help="per-rule wall time and memory from Snakemake benchmark files")
    ti.add_argument("results_dir", help="folder holding <scenario>/benchmarks/*.tsv")
    ti.add_argument("--rules", nargs="+", required=True, help="the workflow's rule names")
    ti.add_argument("--out", required=True, help="Markdown file to write")
    ti.set_defaults(func=cmd_timings)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        status = args.func(args)
    except ValueError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return int(status or 0)


if __name__ == "__main__":
    sys.exit(main())
