"""``refflow``: measure structural displacement from a video against a reference frame.

Subcommands: ``track`` (measure), ``methods`` (list), ``calibrate`` (checkerboard),
``pois`` (figure of the mask POIs next to the corners KLT would use).
Bad input ends with a one-line message on stderr and exit code 2, and no output file.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from flow import registry
from flow.io import FrameSource, InputError, Roi
from refflow.io import atomic_path, versions, write_json

EXIT_USAGE = 2
CSV_COLUMNS = ("frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid",
               "poi_kept_frac", "residual", "flow_spread_px")


def _default_method() -> tuple[str, str | None]:
    names = registry.available()
    if "deepflow" in names:
        return "deepflow", None
    from flow import methods

    return "deepflow-opencv", ("clean-room `deepflow` is not available"
                               + (f" ({methods.DEEPFLOW_IMPORT_ERROR})" if methods.DEEPFLOW_IMPORT_ERROR else "")
                               + "; using deepflow-opencv")


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} {value} is not positive: pass a scale > 0 (mm per pixel)")


def _mask_for(args: argparse.Namespace, source: FrameSource) -> np.ndarray:
    from flow import poi

    given = [a for a in ("mask", "rect", "polygon") if getattr(args, a)]
    if len(given) != 1:
        raise InputError("pass exactly one of --mask MASK.png, --rect X,Y,W,H or --polygon X1,Y1,...")
    if args.mask:
        return poi.load_mask(args.mask, frame_size=source.size, roi=source.roi)
    if args.rect:
        return poi.rect_mask(args.rect, roi=source.roi)
    return poi.polygon_mask(args.polygon, roi=source.roi)


def _open(args: argparse.Namespace) -> FrameSource:
    roi = Roi.parse(args.roi) if args.roi else None
    return FrameSource(args.input, roi=roi, fps=args.fps)


def _undistorter(args: argparse.Namespace, source: FrameSource) -> tuple[Any, dict[str, Any] | None]:
    if not args.calibration:
        return None, None
    from flow.calibration import Undistorter, load_calibration

    calibration = load_calibration(args.calibration)
    return Undistorter(calibration, source.roi, source.size), calibration


def _method_params(args: argparse.Namespace, name: str) -> dict[str, Any]:
    params: dict[str, Any] = {}
    for item in args.param or []:
        key, sep, value = item.partition("=")
        if not sep:
            raise InputError(f"--param {item!r} is not KEY=VALUE")
        for cast in (int, float):
            try:
                params[key] = cast(value)
                break
            except ValueError:
                continue
        else:
            params[key] = {"true": True, "false": False, "none": None}.get(value.lower(), value)
    if args.preset:
        if name != "dis":
            raise InputError(f"--preset applies to the dis method only, not {name!r}")
        params["preset"] = args.preset
    return params


def cmd_methods(args: argparse.Namespace) -> int:
    width = max(len(n) for n in registry.available())
    kinds = {n: registry._REGISTRY[n].kind for n in registry.available()}
    for name, summary in registry.describe().items():
        print(f"{name:<{width}}  [{kinds[name]}]  {summary}")
    import cv2

    if "tvl1" not in kinds:
        print(f"(tvl1 unavailable: this OpenCV {cv2.__version__} build lacks optflow.DualTVL1OpticalFlow)")
    from flow import methods

    if methods.DEEPFLOW_IMPORT_ERROR:
        print(f"(deepflow unavailable: {methods.DEEPFLOW_IMPORT_ERROR})")
    return 0


def _scale_from_file(path: str) -> float:
    """``mm_per_px`` from a JSON file (a scale file, or any sidecar that records one)."""
    try:
        data = json.loads(Path(path).read_text())
    except FileNotFoundError:
        raise InputError(f"scale file {path} does not exist") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"scale file {path} is not readable JSON: {err}") from None
    value = data.get("mm_per_px") if isinstance(data, dict) else None
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not value > 0:
        raise InputError(f"scale file {path} needs a positive number under 'mm_per_px', got {value!r}")
    return float(value)


def cmd_track(args: argparse.Namespace) -> int:
    from flow import poi, track
    from flow.calibration import scale_from_known_length

    started = time.perf_counter()
    notes: list[str] = []
    name = args.method
    if name is None:
        name, note = _default_method()
        if note:
            notes.append(note)
            print(f"refflow track: note: {note}", file=sys.stderr)
    if name not in registry.available():
        raise InputError(f"unknown method {name!r}; available: {', '.join(registry.available())} "
                         "(see `refflow methods`)")
    _positive("--mm-per-px", args.mm_per_px)
    given = [args.mm_per_px is not None, args.known_length is not None, args.scale_file is not None]
    if sum(given) > 1:
        raise InputError("pass one scale: --mm-per-px, --known-length/--between or --scale-file")
    if args.scale_file is not None:
        mm_per_px = _scale_from_file(args.scale_file)
        scale_source = f"mm_per_px from {args.scale_file}"
    elif args.known_length is not None or args.between is not None:
        if args.known_length is None or args.between is None:
            raise InputError("--known-length needs --between X1,Y1,X2,Y2 (and vice versa)")
        mm_per_px = scale_from_known_length(args.known_length, args.between)
        scale_source = f"known length {args.known_length} mm between {args.between}"
    elif args.mm_per_px is not None:
        mm_per_px, scale_source = args.mm_per_px, "--mm-per-px"
    else:
        mm_per_px, scale_source = float("nan"), "none (mm columns are NaN)"
        notes.append("no scale given: pass --mm-per-px or --known-length/--between for mm")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError(f"--max-frames {args.max_frames} must be >= 1")
    params = _method_params(args, name)
    try:
        method = registry.get_method(name, **params)
    except TypeError as err:
        raise InputError(f"bad --param for {name}: {err}") from None
    source = _open(args)
    mask = _mask_for(args, source)
    poi_xy = poi.poi_coordinates(mask, grid_step=args.grid_step)
    undistort, calibration = _undistorter(args, source)
    out = Path(args.out)
    sparse = getattr(method, "kind", "dense") == "sparse"
    filter_mode = args.filter or ("none" if sparse else "paper")

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if sparse:
            tracks = track.track_sparse(source, method, mask, reference_frame=args.reference_frame,
                                        max_frames=args.max_frames, undistort=undistort,
                                        progress=not args.no_progress)
        else:
            tracks = track.track_dense(source, lambda: registry.get_method(name, **params), poi_xy,
                                       reference_frame=args.reference_frame, jobs=args.jobs,
                                       max_frames=args.max_frames, undistort=undistort,
                                       progress=not args.no_progress)
    for warning in caught:
        notes.append(str(warning.message))
        print(f"refflow track: warning: {warning.message}", file=sys.stderr)
    result = track.measure(tracks, filter_enabled=filter_mode != "none",
                           average="median" if filter_mode == "median" else "mean",
                           threshold_ratio=args.threshold_ratio, mcr_threshold=args.mcr_threshold,
                           # KLT mixes background and structure features by design (the paper's
                           # baseline): their disagreement is no sign of a blocked view
                           check_coherence=not sparse)
    notes.extend(result.filtered.notes)

    roi = source.roi
    with atomic_path(out) as tmp, tmp.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in track.iter_rows(result, mm_per_px):
            writer.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in row.items()})
    if args.save_poi_tracks:
        with atomic_path(args.save_poi_tracks) as tmp:
            np.savez_compressed(
                tmp, frame=tracks.frame, time_s=tracks.time_s, dx_px=tracks.dx, dy_px=tracks.dy,
                x_px=tracks.x_px + roi.x, y_px=tracks.y_px + roi.y, valid=result.valid,
                kept=result.filtered.kept, mcr=result.filtered.mcr, residual=tracks.residual)
    n_valid = int(result.valid.sum())
    sidecar = {
        "tool": "refflow track",
        "input": {"path": str(args.input), "frame_size": list(source.size), "fps": source.fps,
                  "header_frames": tracks.header_frames, "frames_decoded": source.frames_read,
                  "frames_measured": len(tracks.frame), "truncated": tracks.truncated},
        "method": name, "method_kind": "sparse" if sparse else "dense", "parameters": method.params(),
        "reference_frame": args.reference_frame, "jobs": args.jobs if not sparse else 1,
        "roi": roi.as_dict(),
        "scale": {"mm_per_px": mm_per_px if math.isfinite(mm_per_px) else None, "source": scale_source},
        "calibration": None if calibration is None else {
            "file": str(args.calibration), "rms_px": calibration.get("rms_px"),
            "camera_matrix": calibration["camera_matrix"], "dist_coeffs": calibration["dist_coeffs"]},
        "poi": {"count": int(len(tracks.x_px)), "source": "features" if sparse else "mask",
                "mask_pixels": int(mask.sum()), "grid_step": args.grid_step,
                "kept_after_filter": int(result.filtered.kept.sum()),
                "kept_after_eq10": int(result.filtered.kept_threshold.sum())},
        "filter": {"mode": filter_mode, "threshold_ratio": args.threshold_ratio,
                   "threshold_px": result.filtered.threshold_px, "mcr_threshold": args.mcr_threshold},
        "quality": {"frames_valid": n_valid, "frames_invalid": int(len(result.valid) - n_valid),
                    "residual_threshold": result.residual_threshold},
        "units": {"time_s": "s", "dx_px": "px, + = image right", "dy_px": "px, + = image down",
                  "dx_mm": "mm", "dy_mm": "mm", "residual": "grey levels (0-255)",
                  "flow_spread_px": "px (1.4826 MAD over kept POIs)", "poi_kept_frac": "fraction"},
        "columns": list(CSV_COLUMNS),
        "notes": notes,
        "versions": versions(),
        "timings": {**tracks.timings_s, "total_s": time.perf_counter() - started},
    }
    write_json(out.with_suffix(".json"), sidecar)
    print(f"refflow track: {name}: {len(tracks.frame)} frames, {len(tracks.x_px)} POIs "
          f"({int(result.filtered.kept.sum())} kept), {n_valid} valid -> {out}", file=sys.stderr)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from flow.calibration import calibrate, parse_board

    result = calibrate(args.input, board=parse_board(args.board), square_mm=args.square_mm,
                       fix_k3=not args.with_k3)
    result["versions"] = versions()
    write_json(args.out, result)
    print(f"refflow calibrate: {result['views_used']} views, RMS {result['rms_px']:.3f} px -> {args.out}",
          file=sys.stderr)
    return 0


def cmd_pois(args: argparse.Namespace) -> int:
    from flow import poi
    from flow.figures import poi_figure
    from flow.methods.klt import KLT
    from flow.track import read_reference

    source = _open(args)
    mask = _mask_for(args, source)
    poi_xy = poi.poi_coordinates(mask, grid_step=args.grid_step)
    undistort, _ = _undistorter(args, source)
    reference = read_reference(source, args.reference_frame, undistort)
    corners = KLT(detector=args.detector).detect(reference)
    poi_figure(reference, poi_xy, corners, args.out)
    inside = int(sum(mask[int(round(y)), int(round(x))] for x, y in corners
                     if 0 <= round(y) < mask.shape[0] and 0 <= round(x) < mask.shape[1]))
    print(f"POIs: {len(poi_xy)}; {args.detector} corners in ROI: {len(corners)} ({inside} on the mask) -> {args.out}")
    return 0


def _add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="video file (any format OpenCV reads) or folder of images")
    p.add_argument("--roi", help="crop X,Y,W,H in full-frame pixels (4K frames are never processed whole)")
    p.add_argument("--fps", type=float, help="frame rate of an image folder (videos: from the file)")
    p.add_argument("--calibration", help="calibration JSON from `refflow calibrate`; frames are undistorted")
    p.add_argument("--mask", help="binary mask PNG (full-frame or ROI size), white = POI")
    p.add_argument("--rect", help="POIs in rectangle X,Y,W,H (full-frame pixels)")
    p.add_argument("--polygon", help="POIs in polygon X1,Y1,X2,Y2,... (full-frame pixels)")
    p.add_argument("--grid-step", type=int, default=1, help="keep every N-th mask pixel in x and y")
    p.add_argument("--reference-frame", type=int, default=0, help="index of the fixed reference frame")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="refflow", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("methods", help="list measurement methods")
    p.set_defaults(func=cmd_methods)

    p = sub.add_parser("track", help="measure displacement of the POIs against the reference frame")
    _add_input_options(p)
    p.add_argument("--method", help="method name (default: deepflow, else deepflow-opencv); see `refflow methods`")
    p.add_argument("--preset", choices=("ultrafast", "fast", "medium"), help="DIS preset")
    p.add_argument("--param", action="append", metavar="KEY=VALUE", help="method parameter (repeatable)")
    p.add_argument("--mm-per-px", type=float, help="image scale at the structure, mm per pixel")
    p.add_argument("--known-length", type=float, help="known length in mm between the --between points")
    p.add_argument("--between", help="X1,Y1,X2,Y2 image points spanning --known-length")
    p.add_argument("--scale-file", help="JSON file holding a positive 'mm_per_px'")
    p.add_argument("--out", required=True, help="output CSV; a JSON sidecar is written beside it")
    p.add_argument("--jobs", type=int, default=1, help="frames measured in parallel (dense methods)")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--save-poi-tracks", help="write the per-POI displacement matrix to this .npz")
    p.add_argument("--filter", choices=("paper", "median", "none"),
                   help="paper: eq. 10-12 (default for dense); median: same filters, median average; "
                        "none: plain average (default for KLT, as in the paper)")
    p.add_argument("--threshold-ratio", type=float, default=0.5,
                   help="eq. 10 threshold as a fraction of the median POI peak |d| (default 0.5)")
    p.add_argument("--mcr-threshold", type=float, default=0.5,
                   help="eq. 11 threshold on the mean cross-correlation (default 0.5)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=cmd_track)

    p = sub.add_parser("calibrate", help="intrinsics and distortion from checkerboard views")
    p.add_argument("input", help="folder of images or a video of the board")
    p.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    p.add_argument("--square-mm", type=float, required=True, help="square side in mm")
    p.add_argument("--with-k3", action="store_true", help="also estimate k3 (default: k3 = 0)")
    p.add_argument("--out", required=True, help="calibration JSON")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("pois", help="PNG of the mask POIs next to the corners KLT would use (paper Fig. 6)")
    _add_input_options(p)
    p.add_argument("--detector", choices=("harris", "shi-tomasi"), default="harris")
    p.add_argument("--out", required=True, help="output PNG")
    p.set_defaults(func=cmd_pois)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (InputError, ValueError) as err:
        print(f"refflow {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        print(f"refflow {args.command}: error: {err.strerror or err}: "
              f"{err.filename or ''} (check the path and permissions)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"refflow {args.command}: interrupted; no output written", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
