"""``refflow``: measure structural displacement from a video against a reference frame.

Subcommands: ``track`` (measure), ``merge`` (join frame ranges tracked
separately), ``methods`` (list), ``calibrate`` (checkerboard), ``pois`` (figure
of the mask POIs next to the corners KLT would use), ``plot`` (time history and
spectrum of measured CSVs), ``modal`` (frequencies, damping and mode shapes of
several measured points), ``export`` (UFF time histories for modal software),
``gui`` (a page in the browser to draw, scale, run and look).

Bad input ends with a one-line message on stderr and exit code 2, and no output
file; anything else that goes wrong is a bug and shows its traceback.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from flow import registry
from flow.camfiles import companion_files
from flow.export import add_parser as add_export_parser
from flow.gui import add_parser as add_gui_parser
from flow.gui.project import PROJECT_HELP, expand_project_argv
from flow.io import FrameSource, InputError, Roi, quiet_decoder_logs
from flow.jsonfiles import json_number, load_json, shown
from flow.modal import add_parser as add_modal_parser
from flow.outputs import check_outputs, claimed
from refflow import trackcsv
from refflow.io import atomic_paths, json_text, versions, write_json

EXIT_USAGE = 2


def _default_method() -> tuple[str, str | None]:
    names = registry.available()
    if "deepflow" in names:
        return "deepflow", None
    reason = registry.unavailable().get("deepflow")
    return "deepflow-opencv", ("clean-room `deepflow` is not available"
                               + (f" ({reason})" if reason else "")
                               + "; using deepflow-opencv")


def _finite_or_none(value: float | None) -> float | None:
    return value if value is not None and math.isfinite(value) else None


def _positive(name: str, value: float | None, what: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} {value} is not positive: pass {what} > 0")


def _open(args: argparse.Namespace, *, need_time: bool = True) -> FrameSource:
    roi = Roi.parse(args.roi) if args.roi else None
    return FrameSource(args.input, roi=roi, fps=args.fps, require_fps=need_time,
                       allow_truncated=getattr(args, "allow_truncated", False))


def _video_origin(args: argparse.Namespace) -> tuple[int, int]:
    text = getattr(args, "video_origin", None)
    if text is None:
        return 0, 0
    if not args.calibration:
        raise InputError("--video-origin places the video on the calibrated sensor: pass --calibration too")
    if text.lower().endswith(".json"):
        data = load_json(text, f"--video-origin {text!r}")
        origin = data.get("video_origin_px") if isinstance(data, dict) else None
        if not (isinstance(origin, list) and len(origin) == 2
                and all(isinstance(v, int) and not isinstance(v, bool) for v in origin)):
            raise InputError(f"--video-origin {text!r} needs 'video_origin_px': [X, Y] (two integers), "
                             f"got {shown(origin)}")
        text = f"{origin[0]},{origin[1]}"
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--video-origin {text!r} is not X,Y (two integers) or a JSON file") from None
    if x < 0 or y < 0:
        raise InputError(f"--video-origin {text!r} must not be negative")
    return x, y


def _undistorter(args: argparse.Namespace, source: FrameSource) -> tuple[Any, dict[str, Any] | None]:
    """The undistortion of --calibration for the frames' ROI (None without a calibration).

    With ``--video-origin X,Y`` the video is a window of the calibrated sensor (a
    cropped recording) whose pixel (0, 0) is sensor pixel (X, Y).
    """
    origin = _video_origin(args)
    if not args.calibration:
        return None, None
    from flow.calibration import Undistorter, load_calibration

    calibration = load_calibration(args.calibration)
    if origin == (0, 0):
        return Undistorter(calibration, source.roi, source.size), calibration
    sensor = tuple(calibration.get("image_size", ()))
    if len(sensor) != 2:
        raise InputError(f"calibration file {args.calibration!r} has no image_size: --video-origin needs "
                         "the calibrated sensor's size")
    roi = source.roi
    on_sensor = Roi(roi.x + origin[0], roi.y + origin[1], roi.width, roi.height)
    if on_sensor.x + source.size[0] - roi.x > sensor[0] or on_sensor.y + source.size[1] - roi.y > sensor[1]:
        raise InputError(f"a {source.size[0]}x{source.size[1]} video at --video-origin {origin[0]},{origin[1]} "
                         f"reaches beyond the {sensor[0]}x{sensor[1]} calibrated sensor")
    return Undistorter(calibration, on_sensor, sensor, video_origin=origin), calibration


def _mask_for(args: argparse.Namespace, source: FrameSource, undistort: Any) -> np.ndarray:
    """The POI mask in the pixels the frames are measured in, as int32 region labels (0: no POI).

    Masks, rectangles and polygons are drawn on the raw video frames (what any
    viewer shows); with a calibration they are carried into the undistorted
    frames, where the flow is computed. Regions: a labelled mask PNG (grey values
    1..N), or several --mask files (one region each, or their labels in turn).
    """
    from flow import poi

    given = [a for a in ("mask", "rect", "polygon") if getattr(args, a)]
    if len(given) != 1:
        raise InputError("pass exactly one of --mask MASK.png, --rect X,Y,W,H or --polygon X1,Y1,...")
    if args.mask:
        labels = np.zeros((source.roi.height, source.roi.width), np.int32)
        for path in args.mask:
            found = poi.load_mask(path, frame_size=source.size, roi=source.roi,
                                  rotation_deg=source.rotation_deg, notes=source.notes, labels=True)
            both = int(((labels > 0) & (found > 0)).sum())
            if both:
                raise InputError(f"mask {path!r} overlaps the masks before it in {both} pixels: "
                                 "a pixel belongs to one region; draw the regions apart")
            labels = np.where(found > 0, found + labels.max(), labels).astype(np.int32)
    elif args.rect:
        labels = poi.rect_mask(args.rect, roi=source.roi).astype(np.int32)
    else:
        labels = poi.polygon_mask(args.polygon, roi=source.roi).astype(np.int32)
    if undistort is None:
        return labels
    moved = np.zeros(labels.shape, np.int32)
    for label in np.unique(labels[labels > 0]):
        moved[undistort.map_mask(labels == label)] = label
    return moved


def _regions(labels: np.ndarray, poi_xy: np.ndarray, grid_step: int) -> list[int]:
    """The labels of the regions measured; refuses a region the POI grid leaves empty."""
    present = [int(v) for v in np.unique(labels[labels > 0])]
    at_pois = set(np.unique(labels[poi_xy[:, 1], poi_xy[:, 0]]).tolist())
    empty = [label for label in present if label not in at_pois]
    if empty:
        raise InputError(f"region(s) {', '.join(map(str, empty))} of the mask hold no POI inside the ROI with "
                         f"--grid-step {grid_step}: draw them larger, lower --grid-step or widen --roi")
    return present


def _mask_cut_by_roi(args: argparse.Namespace, source: FrameSource, notes: list[str]) -> int:
    """Pixels of a full-frame --mask that --roi leaves out; warns (and notes) when any."""
    from flow import poi

    outside = sum(poi.pixels_outside_roi(path, frame_size=source.size, roi=source.roi)
                  for path in args.mask or [])
    if outside:
        message = (f"--roi {source.roi.as_text()} leaves {outside} of the mask's pixels out: only the mask "
                   "inside the ROI is measured (widen --roi to measure all of it)")
        notes.append(message)
        print(f"refflow {args.command}: warning: {message}", file=sys.stderr)
    return outside


def _background_for(args: argparse.Namespace, source: FrameSource, undistort: Any,
                    poi_mask: np.ndarray) -> Any:
    """The static points of --background-mask/--background-rect (None without them)."""
    from flow import poi
    from flow.background import Background

    if args.background_mask and args.background_rect:
        raise InputError("pass one of --background-mask and --background-rect, not both")
    if args.background_mask:
        mask = poi.load_mask(args.background_mask, frame_size=source.size, roi=source.roi,
                             what="background mask", instead="--background-rect",
                             rotation_deg=source.rotation_deg, notes=source.notes)
    elif args.background_rect:
        mask = poi.rect_mask(args.background_rect, roi=source.roi)
    else:
        return None
    if undistort is not None:
        mask = undistort.map_mask(mask)
    overlap = int((mask & poi_mask).sum())
    if overlap:
        raise InputError(f"the background region overlaps the POIs in {overlap} pixels: mark only "
                         "parts of the scene that do not move (a wall, the ground), away from the structure")
    if mask.sum() < 3:
        raise InputError("the background region holds no pixel inside the ROI: mark a static area "
                         "within --roi")
    return Background.from_mask(mask, model=args.background_model)


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


def _build_method(name: str, params: dict[str, Any]) -> Any:
    try:
        return registry.get_method(name, **params)
    except (TypeError, ValueError) as err:
        # The method constructors reject bad keyword values with ValueError: here that
        # value came from the command line, so it is the user's to fix.
        raise InputError(f"bad --param for {name}: {err} (see `refflow methods`)") from None


def cmd_methods(args: argparse.Namespace) -> int:
    width = max(len(n) for n in registry.available())
    kinds = registry.kinds()
    for name, summary in registry.describe().items():
        print(f"{name:<{width}}  [{kinds[name]}]  {summary}")
    for name, reason in registry.unavailable().items():
        print(f"({name} unavailable: {reason})")
    return 0


def _scale_from_file(path: str, undistort_points: Any, frame_size: tuple[int, int] | None) -> tuple[float, str]:
    """``(mm_per_px, how)`` from a JSON file: its ``mm_per_px``, or a known length
    ``known_length_mm`` between two raw video points ``between_px`` [X1, Y1, X2, Y2]
    (measured in the undistorted image with a calibration, like --known-length)."""
    from flow.calibration import scale_from_known_length

    data = load_json(path, f"scale file {path}")
    data = data if isinstance(data, dict) else {}
    if "known_length_mm" in data or "between_px" in data:
        length, between = data.get("known_length_mm"), data.get("between_px")
        number = json_number(length)
        points = [json_number(v) for v in between] if isinstance(between, list) else []
        if not (number is not None and 0 < number < math.inf and len(points) == 4
                and all(v is not None and math.isfinite(v) for v in points)):
            raise InputError(f"scale file {path}: 'known_length_mm' needs a positive number and 'between_px' "
                             f"four numbers X1,Y1,X2,Y2, got {shown(length)} and {shown(between)}")
        text = ",".join(f"{v:.6f}" for v in points)
        mm_per_px = scale_from_known_length(number, text, undistort_points, frame_size=frame_size)
        where = " (undistorted)" if undistort_points is not None else ""
        return mm_per_px, f"known length {number} mm between {text} from {path}{where}"
    value = data.get("mm_per_px")
    number = json_number(value)
    if number is None or not 0 < number < math.inf:
        raise InputError(f"scale file {path} needs a positive number under 'mm_per_px' (or "
                         f"'known_length_mm' and 'between_px'), got {shown(value)}")
    return number, f"mm_per_px from {path}"


def _check_scale_options(args: argparse.Namespace) -> None:
    """Reject bad scale options before any frame is read."""
    _positive("--mm-per-px", args.mm_per_px, "the image scale in mm per pixel")
    _positive("--known-length", args.known_length, "the known length in mm")
    given = [args.mm_per_px is not None, args.known_length is not None, args.scale_file is not None]
    if sum(given) > 1:
        raise InputError("pass one scale: --mm-per-px, --known-length/--between or --scale-file")
    if (args.known_length is None) != (args.between is None):
        raise InputError("--known-length needs --between X1,Y1,X2,Y2 (and vice versa)")


# No camera images a structure at a kilometre per pixel: a larger scale is a typing error
# (and would overflow the mm columns).
MAX_MM_PER_PX = 1e6


def _scale(args: argparse.Namespace, calibration: dict[str, Any] | None,
           frame_size: tuple[int, int] | None) -> tuple[float, str]:
    """``(mm_per_px, how)``; NaN when no scale was given (mm columns are then NaN).

    ``calibration``: the run's calibration summary (``_calibration_summary``, also what a
    part's sidecar holds) or None. Scale points are raw video pixels; with a calibration
    they are undistorted first, because the displacements are measured undistorted. `track`
    and `merge` both come here, so the two give the same mm per pixel.
    """
    from flow.calibration import point_undistorter, scale_from_known_length

    undistort_points = point_undistorter(calibration)
    if args.scale_file is not None:
        mm_per_px, how = _scale_from_file(args.scale_file, undistort_points, frame_size)
    elif args.known_length is not None:
        mm_per_px = scale_from_known_length(args.known_length, args.between, undistort_points,
                                            frame_size=frame_size)
        where = " (undistorted)" if undistort_points is not None else ""
        how = f"known length {args.known_length} mm between {args.between}{where}"
    elif args.mm_per_px is not None:
        mm_per_px, how = args.mm_per_px, "--mm-per-px"
    else:
        return float("nan"), "none (mm columns are NaN)"
    if not mm_per_px < MAX_MM_PER_PX:
        raise InputError(f"scale {mm_per_px:g} mm per pixel ({how}) is beyond {MAX_MM_PER_PX:g} (a kilometre "
                         "per pixel): check the scale's units and points")
    return mm_per_px, how


def _parse_frames(text: str | None) -> tuple[int, int | None] | None:
    if text is None:
        return None
    start_text, sep, stop_text = text.partition(":")
    try:
        start = int(start_text) if start_text else 0
        stop = int(stop_text) if stop_text else None
    except ValueError:
        start, stop = -1, None
    if not sep or start < 0 or (stop is not None and stop <= start):
        raise InputError(f"--frames {text!r} is not START:END with 0 <= START < END (END exclusive, "
                         "may be left out for 'to the end'), e.g. 0:300")
    return start, stop


def _check_measure_options(args: argparse.Namespace) -> None:
    if not 0 <= args.threshold_ratio:
        raise InputError(f"--threshold-ratio {args.threshold_ratio} is negative: pass a fraction >= 0")
    if not -1 <= args.mcr_threshold <= 1:
        raise InputError(f"--mcr-threshold {args.mcr_threshold} is outside [-1, 1]: it is a correlation")


def _output_names(args: argparse.Namespace) -> list[Path]:
    """The files a run writes, in writing order (the CSV last); checked before any work."""
    raw, poi_tracks = getattr(args, "raw_tracks", None), args.save_poi_tracks
    names = ([Path(raw)] if raw else []) + ([Path(poi_tracks)] if poi_tracks else []) \
        + ([Path(args.out).with_suffix(".json"), Path(args.out)] if args.out else [])
    check_outputs(names, _input_paths(args), option="--out (the sidecar is <out>.json)")
    return names


def _input_paths(args: argparse.Namespace) -> list[tuple[str, Path]]:
    """``(option, path)`` of every file the run reads (outputs must not be one of them)."""
    found: list[tuple[str, Path]] = []
    for option in ("input", "mask", "calibration", "scale_file", "background_mask", "video_origin"):
        values = getattr(args, option, None)
        for value in values if isinstance(values, list) else [values]:
            if isinstance(value, str) and value and Path(value).exists():
                found.append(("the video" if option == "input" else "--" + option.replace("_", "-"), Path(value)))
    found += [("a part", Path(part)) for part in getattr(args, "parts", None) or []]
    if isinstance(getattr(args, "input", None), str):  # a camera header's frames file (.mraw)
        found += [("the recording's frames", path) for path in companion_files(args.input)]
    return found


def _write_outputs(args: argparse.Namespace, tracks: Any, run: dict[str, Any], notes: list[str],
                   mm_per_px: float, scale_source: str, started: float) -> list[tuple[int, Any]]:
    """Filter, average and write the run's outputs as one all-or-nothing set; returns each
    region's ``(label, Measurement)`` (none without --out).

    Every file is written to a temporary name; only when all are complete are they
    renamed (the CSV last), so a failure or Ctrl-C leaves none of them. A run of several
    regions filters and averages each on its own and writes one row per frame and region.
    """
    from flow import formats, quality, storage

    raw = getattr(args, "raw_tracks", None)
    sparse = run["method_kind"] == "sparse"
    multi = tracks.region is not None
    results: list[tuple[int, Any]] = []
    sidecar: dict[str, Any] = {}
    columns = trackcsv.columns(regions=multi)
    if args.out:
        filter_mode = args.filter or ("none" if sparse else "paper")
        results = [(label, quality.measure(tracks.select(label), filter_enabled=filter_mode != "none",
                                           average="median" if filter_mode == "median" else "mean",
                                           threshold_ratio=args.threshold_ratio, mcr_threshold=args.mcr_threshold,
                                           # KLT mixes background and structure features by design (the
                                           # paper's baseline): their disagreement is no sign of a blocked view
                                           check_coherence=not sparse))
                   for label in tracks.labels()]
        sidecar = _sidecar(args, run, notes, results, mm_per_px, scale_source, filter_mode, columns, started)
    sidecar_text = json_text(sidecar) if args.out else ""  # a bad value fails before any file exists
    with atomic_paths(*_output_names(args)) as temporaries:
        pending = list(temporaries)
        if raw:
            formats.save_raw_tracks(pending.pop(0), tracks, {**run, "notes": notes, "versions": versions()})
        if args.save_poi_tracks:
            roi = run["roi"]
            kept = np.zeros(len(tracks.x_px), bool)
            mcr = np.full(len(tracks.x_px), np.nan)
            for label, result in results:
                where = slice(None) if not multi else tracks.region == label
                kept[where] = result.filtered.kept
                mcr[where] = result.filtered.mcr
            valid = np.column_stack([result.valid for _, result in results])
            storage.write_npz(pending.pop(0), {
                "frame": tracks.frame, "time_s": tracks.time_s, "dx_px": tracks.dx, "dy_px": tracks.dy,
                "x_px": tracks.x_px + roi["x"], "y_px": tracks.y_px + roi["y"],
                "valid": valid if multi else valid[:, 0], "kept": kept, "mcr": mcr, "residual": tracks.residual,
                "offset_dx_px": tracks.offset_dx, "offset_dy_px": tracks.offset_dy,
                **({"region": tracks.region} if multi else {})}, compress=True)
        if args.out:
            pending.pop(0).write_text(sidecar_text)
            with pending.pop(0).open("w", newline="") as handle:
                trackcsv.write(handle, [(label, formats.iter_rows(result, mm_per_px)) for label, result in results])
    return results


def _sidecar(args: argparse.Namespace, run: dict[str, Any], notes: list[str], results: list[tuple[int, Any]],
             mm_per_px: float, scale_source: str, filter_mode: str, columns: list[str],
             started: float) -> dict[str, Any]:
    """The measurement's sidecar: the run, the scale, the filter and the quality (per region
    under ``regions`` for a run of several)."""
    multi = len(results) > 1

    def quality(result: Any) -> dict[str, Any]:
        n_valid = int(result.valid.sum())
        return {"frames_valid": n_valid, "frames_invalid": int(len(result.valid) - n_valid),
                "residual_threshold": _finite_or_none(result.residual_threshold),
                "consistency_band_px": _finite_or_none(result.consistency_band_px)}

    first = results[0][1]
    every = np.logical_and.reduce([result.valid for _, result in results])
    sidecar: dict[str, Any] = {
        **{k: v for k, v in run.items() if k not in ("identity", "timings")},
        "scale": {"mm_per_px": _finite_or_none(mm_per_px), "source": scale_source},
        "filter": {"mode": filter_mode, "threshold_ratio": args.threshold_ratio,
                   "threshold_px": None if multi else first.filtered.threshold_px,
                   "mcr_threshold": args.mcr_threshold},
        "quality": ({"frames_valid": int(every.sum()), "frames_invalid": int(len(every) - every.sum()),
                     "counted": "frames valid in every region (each region's own: see regions)"}
                    if multi else quality(first)),
        "units": trackcsv.units(regions=multi),
        "columns": columns,
        "notes": notes + [(f"region {label}: {note}" if multi else note)
                          for label, result in results for note in result.filtered.notes],
        "versions": versions(),
        "timings": {**run.get("timings", {}), "total_s": time.perf_counter() - started},
    }
    sidecar["poi"] = {**run["poi"], "kept_after_filter": sum(int(r.filtered.kept.sum()) for _, r in results),
                      "kept_after_eq10": sum(int(r.filtered.kept_threshold.sum()) for _, r in results)}
    if multi:
        described = {entry["label"]: entry for entry in run["poi"].get("regions", [])}
        sidecar["regions"] = [
            {**described.get(label, {"label": label}), "threshold_px": result.filtered.threshold_px,
             "kept_after_filter": int(result.filtered.kept.sum()),
             "kept_after_eq10": int(result.filtered.kept_threshold.sum()), **quality(result)}
            for label, result in results]
    return sidecar


def _calibration_summary(args: argparse.Namespace, calibration: dict[str, Any] | None) -> dict[str, Any] | None:
    if calibration is None:
        return None
    return {"file": str(args.calibration), "rms_px": calibration.get("rms_px"),
            "camera_matrix": calibration["camera_matrix"], "dist_coeffs": calibration["dist_coeffs"],
            "video_origin": list(_video_origin(args))}


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return max(os.cpu_count() or 1, 1)


def cmd_track(args: argparse.Namespace) -> int:
    from flow import driver, poi

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
    _check_scale_options(args)
    _check_measure_options(args)
    _positive("--fps", args.fps, "the camera frame rate in frames per second")
    if args.max_frames is not None and args.max_frames < 1:
        raise InputError(f"--max-frames {args.max_frames} must be >= 1")
    if args.jobs is not None and args.jobs < 1:
        raise InputError(f"--jobs {args.jobs} must be >= 1")
    cores = available_cores()
    if args.jobs is not None and args.jobs > cores:
        # More jobs than cores only builds more method instances (memory) for no speed.
        note = f"--jobs {args.jobs} is more than the {cores} cores this process may use: {cores} jobs"
        notes.append(note)
        print(f"refflow track: note: {note}", file=sys.stderr)
    args.jobs = min(args.jobs or cores, cores)
    if not args.out and not args.raw_tracks:
        raise InputError("nothing to write: pass --out CSV (measurement) and/or --raw-tracks NPZ (unfiltered part)")
    if args.save_poi_tracks and not args.out:
        raise InputError("--save-poi-tracks records the filtered measurement: pass --out CSV too "
                         "(--raw-tracks alone keeps the unfiltered tracks)")
    frames = _parse_frames(args.frames)
    params = _method_params(args, name)
    method = _build_method(name, params)
    sparse = getattr(method, "kind", "dense") == "sparse"
    if sparse and frames is not None:
        raise InputError(f"--frames needs a reference-frame (dense) method: {name} follows its features "
                         "from frame to frame, so its run cannot be split")
    if sparse and (args.background_mask or args.background_rect):
        raise InputError(f"--background-mask/--background-rect need a dense method: {name} picks its own "
                         "features (the paper's KLT baseline has no camera-motion compensation)")
    _output_names(args)
    source = _open(args)
    undistort, calibration = _undistorter(args, source)
    calibration_info = _calibration_summary(args, calibration)
    mm_per_px, scale_source = _scale(args, calibration_info, tuple(source.size))
    labels = _mask_for(args, source, undistort)
    mask = labels > 0
    outside = _mask_cut_by_roi(args, source, notes)
    poi_xy = poi.poi_coordinates(mask, grid_step=args.grid_step)
    regions = _regions(labels, poi_xy, args.grid_step)
    if sparse and len(regions) > 1:
        raise InputError(f"the mask has {len(regions)} regions but {name} picks its own features in one region: "
                         "use a dense method (the default) or one region per run")
    background = _background_for(args, source, undistort, mask)
    # The per-POI store goes beside the output: a real disk, unlike a memory-backed /tmp.
    store_dir = Path(args.out or args.raw_tracks).resolve().parent
    store_dir = store_dir if store_dir.is_dir() else None

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if sparse:
            tracks = driver.track_sparse(source, method, mask, reference_frame=args.reference_frame,
                                         reference_average=args.reference_average,
                                         max_frames=args.max_frames, undistort=undistort,
                                         progress=not args.no_progress, store_dir=store_dir)
        else:
            tracks = driver.track_dense(source, lambda: _build_method(name, params), poi_xy,
                                        reference_frame=args.reference_frame,
                                        reference_average=args.reference_average, jobs=args.jobs,
                                        max_frames=args.max_frames, frames=frames, undistort=undistort,
                                        progress=not args.no_progress, store_dir=store_dir,
                                        background=background, mask=labels)
    notes.extend(source.notes)
    for warning in caught:
        notes.append(str(warning.message))
        print(f"refflow track: warning: {warning.message}", file=sys.stderr)
    if scale_source.startswith("none"):
        notes.append("no scale given: pass --mm-per-px or --known-length/--between for mm")
    if source.bit_depth > 8 and not method.full_depth:
        notes.append(f"{name} takes 8-bit images: the {source.bit_depth}-bit data was rounded to 8 bits for it "
                     "(the default method measures at full depth)")
    roi = source.roi
    # Where the points are (full-frame pixels; undistorted with a calibration): a measurement
    # point's position, e.g. for mode shapes (`refflow modal`).
    def centroid(x_px: np.ndarray, y_px: np.ndarray) -> list[float]:
        return [round(float(np.mean(x_px)) + roi.x, 3), round(float(np.mean(y_px)) + roi.y, 3)]

    poi_info = {"count": int(len(tracks.x_px)), "source": "features" if sparse else "mask",
                "mask_pixels": int(mask.sum()), "mask_pixels_outside_roi": outside, "grid_step": args.grid_step,
                "centroid_px": centroid(tracks.x_px, tracks.y_px)}
    if tracks.region is not None:
        poi_info["regions"] = [
            {"label": label, "count": int(np.sum(tracks.region == label)),
             "mask_pixels": int(np.sum(labels == label)),
             "centroid_px": centroid(tracks.x_px[tracks.region == label], tracks.y_px[tracks.region == label])}
            for label in tracks.labels()]
    background_info = None if background is None else {
        "source": args.background_mask or f"rect {args.background_rect}", "points": int(len(background.xy)),
        "model": background.model, "requested_model": args.background_model}
    run = {
        "tool": "refflow track",
        "input": {"path": str(args.input), "frame_size": list(source.size), "fps": _finite_or_none(source.fps),
                  "rotation_deg": source.rotation_deg, "bit_depth": source.bit_depth,
                  "measured_bits": source.bit_depth if method.full_depth else min(source.bit_depth, 8),
                  "header_frames": tracks.header_frames, "frames_decoded": source.frames_read,
                  "frames_measured": len(tracks.frame), "truncated": tracks.truncated},
        "frames": {"first": int(tracks.frame[0]), "stop": int(tracks.frame[-1]) + 1, "requested": args.frames},
        "method": name, "method_kind": "sparse" if sparse else "dense", "parameters": method.params(),
        "reference_frame": args.reference_frame, "reference_average": args.reference_average,
        "jobs": args.jobs if not sparse else 1,
        "roi": roi.as_dict(), "calibration": calibration_info, "poi": poi_info,
        "background": background_info,
        "timings": tracks.timings_s,
        # What every part of one run shares; `refflow merge` refuses parts that differ.
        "identity": {"method": name, "parameters": method.params(), "reference_frame": args.reference_frame,
                     "reference_average": args.reference_average,
                     "reference_digest": tracks.reference_digest, "roi": roi.as_dict(),
                     "frame_size": list(source.size), "header_frames": tracks.header_frames,
                     "calibration": calibration_info, "poi": poi_info, "background": background_info},
    }
    results = _write_outputs(args, tracks, run, notes, mm_per_px, scale_source, started)
    written = [p for p in (args.raw_tracks, args.out) if p]
    print(f"refflow track: {name}: {len(tracks.frame)} frames, {len(tracks.x_px)} POIs{_counts(results)} -> "
          f"{', '.join(written)}", file=sys.stderr)
    return 0


def _counts(results: list[tuple[int, Any]]) -> str:
    """" (K kept), V valid" for the console; per region for a run of several."""
    if not results:
        return ""
    if len(results) == 1:
        result = results[0][1]
        return f" ({int(result.filtered.kept.sum())} kept), {int(result.valid.sum())} valid"
    return "".join(f"; region {label}: {int(r.filtered.kept.sum())} kept, {int(r.valid.sum())} valid"
                   for label, r in results)


def cmd_merge(args: argparse.Namespace) -> int:
    from flow import formats

    started = time.perf_counter()
    _check_scale_options(args)
    _check_measure_options(args)
    _output_names(args)
    store_dir = Path(args.out).resolve().parent
    tracks, metas = formats.load_raw_tracks(args.parts, store_dir=store_dir if store_dir.is_dir() else None)
    first = metas[0]
    # The parts were measured undistorted: the scale points are carried through the same
    # calibration, exactly as `track` does (one code path, _scale).
    mm_per_px, scale_source = _scale(args, first["calibration"], tuple(first["input"]["frame_size"]))
    notes = [note for meta in metas for note in meta.get("notes", []) if "no scale given" not in note]
    if scale_source.startswith("none"):
        notes.append("no scale given: pass --mm-per-px or --known-length/--between for mm")
    run = {**first, "tool": "refflow merge",
           "input": {**first["input"], "frames_decoded": max(m["input"]["frames_decoded"] for m in metas),
                     "frames_measured": len(tracks.frame), "truncated": tracks.truncated},
           "frames": {"first": int(tracks.frame[0]), "stop": int(tracks.frame[-1]) + 1, "requested": None},
           "parts": [{"file": str(p), "frames": [m["frames"]["first"], m["frames"]["stop"]]}
                     for p, m in zip(args.parts, metas, strict=True)],
           "timings": tracks.timings_s}
    run.pop("notes", None)
    run.pop("versions", None)
    results = _write_outputs(args, tracks, run, notes, mm_per_px, scale_source, started)
    print(f"refflow merge: {len(metas)} parts, {len(tracks.frame)} frames, {len(tracks.x_px)} POIs"
          f"{_counts(results)} -> {args.out}", file=sys.stderr)
    return 0


def cmd_calibrate(args: argparse.Namespace) -> int:
    from flow.calibration import calibrate, parse_board

    check_outputs([Path(args.out)], [("the board images", Path(args.input))])
    result = calibrate(args.input, board=parse_board(args.board), square_mm=args.square_mm,
                       fix_k3=not args.with_k3, step=args.step, max_views=args.max_views)
    result["versions"] = versions()
    write_json(args.out, result)
    print(f"refflow calibrate: {result['views_used']} views, RMS {result['rms_px']:.3f} px -> {args.out}",
          file=sys.stderr)
    return 0


def cmd_pois(args: argparse.Namespace) -> int:
    from flow import poi
    from flow.driver import read_reference
    from flow.figures import poi_figure
    from flow.methods.klt import KLT

    source = _open(args, need_time=False)
    undistort, _ = _undistorter(args, source)
    labels = _mask_for(args, source, undistort)
    mask = labels > 0
    _mask_cut_by_roi(args, source, [])
    poi_xy = poi.poi_coordinates(mask, grid_step=args.grid_step)
    regions = _regions(labels, poi_xy, args.grid_step)
    reference = read_reference(source, args.reference_frame, undistort, args.reference_average)
    corners = KLT(detector=args.detector).detect(reference)
    poi_figure(reference, poi_xy, corners, args.out,
               region=labels[poi_xy[:, 1], poi_xy[:, 0]] if len(regions) > 1 else None)
    cells = np.round(corners).astype(int).reshape(-1, 2)
    inside = (cells[:, 0] >= 0) & (cells[:, 1] >= 0) & (cells[:, 0] < mask.shape[1]) & (cells[:, 1] < mask.shape[0])
    on_mask = int(mask[cells[inside, 1], cells[inside, 0]].sum())
    in_regions = f" in {len(regions)} regions" if len(regions) > 1 else ""
    print(f"POIs: {len(poi_xy)}{in_regions}; {args.detector} corners in ROI: {len(corners)} ({on_mask} on the mask) "
          f"-> {args.out}")
    return 0


def cmd_plot(args: argparse.Namespace) -> int:
    from flow.figures import read_measurements, spectrum_figure

    labels = args.label or []
    if labels and len(labels) != len(args.csv):
        raise InputError(f"--label given {len(labels)} times for {len(args.csv)} CSV files: one per file or none")
    _positive("--min-hz", args.min_hz, "a frequency in Hz")
    # Every region of every CSV is a series of its own.
    measured = [(i, path, data) for i, path in enumerate(args.csv) for data in read_measurements(path)]
    units = args.units
    if units == "auto":
        units = "mm" if all(m["has_mm"] for _, _, m in measured) else "px"
    series = {}
    for i, path, data in measured:
        if units == "mm" and not data["has_mm"]:
            raise InputError(f"{path} has no mm columns (tracked without a scale): use --units px")
        label = labels[i] if labels else data["label"]
        if labels and data["region"] is not None:
            label = f"{label} region {data['region']}"
        if label in series:
            label = f"{label} ({Path(path).stem})"
        series[label] = (data["time_s"], data[f"dx_{units}"], data[f"dy_{units}"])
    summary = spectrum_figure(series, args.out, units=units, title=args.title or "", min_hz=args.min_hz)
    for label, peaks in summary.items():
        found = ", ".join(f"{axis} {hz:.3f} Hz" for axis, hz in peaks.items() if axis != "main" and hz is not None)
        print(f"{label}: dominant frequency {found or 'n/a'} (spectra plotted: {peaks['main']})")
    print(f"-> {args.out}")
    return 0


def _add_input_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("input", help="video file (any format OpenCV reads), folder of images, or a high-speed "
                   "camera recording (Photron .cih/.cihx with its .mraw, Phantom .cine)")
    p.add_argument("--roi", help="crop X,Y,W,H in raw full-frame pixels (4K frames are never processed whole)")
    p.add_argument("--fps", type=float, help="frame rate of an image folder (required there); on a video, the capture rate where it "
                   "differs from the file's playback rate (slow motion, high-speed export): time_s follows it")
    p.add_argument("--calibration", help="calibration JSON from `refflow calibrate`: frames are undistorted, "
                   "and the mask/--rect/--polygon/--between drawn on raw frames are carried along")
    p.add_argument("--video-origin", metavar="X,Y", help="the video is a window of the calibrated sensor "
                   "whose top-left pixel is sensor pixel X,Y (a cropped recording); or a JSON file "
                   "holding 'video_origin_px': [X, Y]")
    p.add_argument("--mask", action="append", help="mask PNG (full-frame or ROI size, raw video pixels): "
                   "white = POI; or grey values 1..N = regions 1..N, each measured on its own in one run; "
                   "repeat --mask for one region per file")
    p.add_argument("--rect", help="POIs in rectangle X,Y,W,H (raw full-frame pixels)")
    p.add_argument("--polygon", help="POIs in polygon X1,Y1,X2,Y2,... (raw full-frame pixels)")
    p.add_argument("--grid-step", type=int, default=1, help="keep every N-th mask pixel in x and y")
    p.add_argument("--reference-frame", type=int, default=0, help="index of the fixed reference frame")
    p.add_argument("--reference-average", type=int, default=1, metavar="N",
                   help="the reference is the mean of N frames from --reference-frame, taken while the "
                        "structure is at rest (a key frame of a compressed video reads as a sub-pixel "
                        "shift against the frames that follow it; default 1: the frame itself)")

def _add_measure_options(p: argparse.ArgumentParser, *, out_required: bool) -> None:
    p.add_argument("--out", required=out_required,
                   help="output CSV; a JSON sidecar is written beside it")
    p.add_argument("--mm-per-px", type=float, help="image scale at the structure, mm per pixel")
    p.add_argument("--known-length", type=float, help="known length in mm between the --between points")
    p.add_argument("--between", help="X1,Y1,X2,Y2 raw image points spanning --known-length")
    p.add_argument("--scale-file", help="JSON file holding a positive 'mm_per_px', or 'known_length_mm' and "
                   "'between_px' [X1, Y1, X2, Y2] (raw video pixels, like --known-length/--between)")
    p.add_argument("--save-poi-tracks", help="write the per-POI displacement matrix to this .npz")
    p.add_argument("--filter", choices=("paper", "median", "none"),
                   help="paper: eq. 10-12 (default for dense); median: same filters, median average; "
                        "none: plain average (default for KLT, as in the paper)")
    p.add_argument("--threshold-ratio", type=float, default=0.5,
                   help="eq. 10 threshold as a fraction of the median POI peak |d| (default 0.5)")
    p.add_argument("--mcr-threshold", type=float, default=0.5,
                   help="eq. 11 threshold on the mean cross-correlation (default 0.5)")


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
    p.add_argument("--background-mask", help="mask PNG of static scene (wall, ground; raw video pixels): "
                   "the camera's motion measured there is removed from the POIs' (tripod shake, drift)")
    p.add_argument("--background-rect", help="static region X,Y,W,H (raw full-frame pixels), like --background-mask")
    p.add_argument("--background-model", choices=("affine", "translation"), default="affine",
                   help="camera image motion fitted to the background (affine falls back to translation "
                        "on a narrow strip)")
    _add_measure_options(p, out_required=False)
    p.add_argument("--jobs", type=int, help="threads measuring frames (or chains of frames) in parallel "
                   "(dense methods; default: the cores this process may use). The numbers do not "
                   "depend on it")
    p.add_argument("--max-frames", type=int, help="stop before this frame index")
    p.add_argument("--frames", metavar="START:END",
                   help="measure frames START..END-1 only (dense methods; the reference frame may lie outside)")
    p.add_argument("--raw-tracks", metavar="NPZ",
                   help="write the unfiltered per-POI tracks of the measured frames, for `refflow merge`")
    p.add_argument("--allow-truncated", action="store_true",
                   help="measure the frames of a truncated video that decode (default: refuse it)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--project", metavar="FILE", help=PROJECT_HELP)
    p.set_defaults(func=cmd_track)

    p = sub.add_parser("merge", help="join raw-tracks parts (track --frames ... --raw-tracks) into one measurement")
    p.add_argument("parts", nargs="+", help="raw-tracks .npz files of one run, contiguous frame ranges")
    _add_measure_options(p, out_required=True)
    p.set_defaults(func=cmd_merge)

    p = sub.add_parser("calibrate", help="intrinsics and distortion from checkerboard images or a video")
    p.add_argument("input", help="folder of images or a video of the board")
    p.add_argument("--board", required=True, help="inner corners COLSxROWS, e.g. 9x6")
    p.add_argument("--square-mm", type=float, required=True, help="square side in mm")
    p.add_argument("--with-k3", action="store_true", help="also estimate k3 (default: k3 = 0)")
    p.add_argument("--step", type=int, default=1, help="try every N-th frame (videos)")
    p.add_argument("--max-views", type=int, default=60, help="use at most this many views, evenly spread")
    p.add_argument("--out", required=True, help="calibration JSON")
    p.set_defaults(func=cmd_calibrate)

    p = sub.add_parser("pois", help="PNG of the mask POIs next to the corners KLT would use (paper Fig. 6)")
    _add_input_options(p)
    p.add_argument("--detector", choices=("harris", "shi-tomasi"), default="harris")
    p.add_argument("--out", required=True, help="output PNG")
    p.set_defaults(func=cmd_pois)

    p = sub.add_parser("plot", help="time history and spectrum of measured CSVs, dominant frequency marked")
    p.add_argument("csv", nargs="+", help="CSV files of `refflow track` (several methods are overlaid)")
    p.add_argument("--out", required=True, help="output PNG")
    p.add_argument("--label", action="append", help="legend label per CSV (default: the method in its sidecar)")
    p.add_argument("--units", choices=("auto", "px", "mm"), default="auto",
                   help="auto: mm where every CSV has a scale, else px")
    p.add_argument("--min-hz", type=float, help="ignore peaks below this frequency (default: one cycle per record)")
    p.add_argument("--title", help="figure title")
    p.set_defaults(func=cmd_plot)
    add_modal_parser(sub)
    add_export_parser(sub)
    add_gui_parser(sub)
    return parser


def _claims(args: argparse.Namespace) -> list[Path]:
    """The files a command writes that a second run at the same time must not write too."""
    names = [getattr(args, option, None) for option in ("out", "raw_tracks")]
    return [Path(name) for name in names if isinstance(name, str) and name]


class Terminated(BaseException):
    """SIGTERM (what `timeout`, SLURM and `kill` send), raised where the run is, so that
    every ``finally`` and all-or-nothing output set cleans up as on Ctrl-C."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


def main(argv: Sequence[str] | None = None) -> int:
    import signal
    import threading

    quiet_decoder_logs()
    parser = build_parser()
    try:
        argv = expand_project_argv(sys.argv[1:] if argv is None else argv)
    except InputError as err:
        print(f"refflow track: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    args = parser.parse_args(argv)
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        with claimed(_claims(args)) as existing:
            code = args.func(args)
            if code == 0 and existing:
                print(f"refflow {args.command}: note: replaced the earlier {', '.join(map(str, existing))}",
                      file=sys.stderr)
            return code
    except Terminated:
        print(f"refflow {args.command}: terminated (SIGTERM); no output written", file=sys.stderr)
        return 143
    except InputError as err:
        print(f"refflow {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        # Files the user named that cannot be read or written (permissions, full disk).
        print(f"refflow {args.command}: error: {err.strerror or err}: "
              f"{err.filename or ''} (check the path and permissions)", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"refflow {args.command}: interrupted; no output written", file=sys.stderr)
        return 130
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
