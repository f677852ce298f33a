"""``refflow``: measure structural displacement from a video against a reference frame.

Subcommands: ``track`` (measure), ``merge`` (join frame ranges tracked
separately), ``methods`` (list), ``calibrate`` (checkerboard), ``pois`` (figure
of the mask POIs next to the corners KLT would use), ``plot`` (time history and
spectrum of measured CSVs), ``modal`` (frequencies, damping and mode shapes of
several measured points), ``export`` (UFF time histories for modal software),
``gui`` (a page in the browser to draw, scale, run and look).

This module parses arguments and turns them into the options of :mod:`flow.options`;
:mod:`flow.pipeline` measures. Bad input ends with a one-line message on stderr and exit
code 2, and no output file; anything else that goes wrong is a bug and shows its traceback.
"""

from __future__ import annotations

import argparse
import errno
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from flow import pipeline
from flow.export import add_parser as add_export_parser
from flow.field.plot import add_parser as add_field_plot_parser
from flow.gui.command import add_parser as add_gui_parser
from flow.gui.project import PROJECT_HELP, expand_project_argv
from flow.io.errors import InputError
from flow.io.video import quiet_decoder_logs
from flow.measure.quality import MAX_TYPICAL_SIGMA_PX
from flow.methods import registry
from flow.modal import add_parser as add_modal_parser
from flow.options import (
    BackgroundOptions,
    FilterOptions,
    MergeOptions,
    OutputOptions,
    RegionOptions,
    ScaleOptions,
    SourceOptions,
    TrackOptions,
)
from flow.outputs import IMAGE_SUFFIXES, PLOT_SUFFIXES, check_outputs, check_suffix, claimed
from flow.scale import positive
from refflow.io import versions, write_json

EXIT_USAGE = 2

# Kept under their old names here: the GUI's and the tests' callers ask the CLI.
available_cores = pipeline.available_cores
_default_method = pipeline.default_method


def source_options(args: argparse.Namespace) -> SourceOptions:
    return SourceOptions(input=args.input, roi=args.roi, fps=args.fps, calibration=args.calibration,
                         video_origin=args.video_origin, allow_truncated=getattr(args, "allow_truncated", False))


def region_options(args: argparse.Namespace) -> RegionOptions:
    return RegionOptions(masks=tuple(args.mask or ()), rect=args.rect, polygon=args.polygon,
                         grid_step=args.grid_step)


def scale_options(args: argparse.Namespace) -> ScaleOptions:
    return ScaleOptions(mm_per_px=args.mm_per_px, known_length=args.known_length, between=args.between,
                        scale_file=args.scale_file)


def filter_options(args: argparse.Namespace) -> FilterOptions:
    return FilterOptions(mode=args.filter, threshold_ratio=args.threshold_ratio, mcr_threshold=args.mcr_threshold,
                         max_typical_sigma_px=args.max_typical_sigma)


def track_options(args: argparse.Namespace) -> TrackOptions:
    """What `refflow track` was asked, from its parsed arguments."""
    return TrackOptions(
        source=source_options(args), region=region_options(args), method=args.method,
        params=tuple(args.param or ()), preset=args.preset, reference_frame=args.reference_frame,
        reference_average=args.reference_average, frames=args.frames, max_frames=args.max_frames,
        background=BackgroundOptions(mask=args.background_mask, rect=args.background_rect,
                                     model=args.background_model),
        scale=scale_options(args), filter=filter_options(args),
        outputs=OutputOptions(csv=args.out, raw_tracks=args.raw_tracks, poi_tracks=args.save_poi_tracks,
                              field=args.field),
        jobs=args.jobs, progress=not args.no_progress)


def merge_options(args: argparse.Namespace) -> MergeOptions:
    return MergeOptions(parts=tuple(args.parts), scale=scale_options(args), filter=filter_options(args),
                        part_fields=tuple(args.part_field or ()),
                        outputs=OutputOptions(csv=args.out, poi_tracks=args.save_poi_tracks, field=args.field))


def cmd_track(args: argparse.Namespace) -> int:
    outcome = pipeline.track(track_options(args))
    tracks = outcome.tracks
    print(f"refflow track: {outcome.method}: {len(tracks.frame)} frames, {len(tracks.x_px)} POIs"
          f"{_counts(outcome.results)} -> {', '.join(outcome.written)}", file=sys.stderr)
    return 0


def cmd_merge(args: argparse.Namespace) -> int:
    n_parts, outcome = pipeline.merge(merge_options(args))
    print(f"refflow merge: {n_parts} parts, {len(outcome.tracks.frame)} frames, {len(outcome.tracks.x_px)} POIs"
          f"{_counts(outcome.results)} -> {args.out}", file=sys.stderr)
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


def cmd_methods(args: argparse.Namespace) -> int:
    if args.params:
        return _print_parameters(args.params)
    width = max(len(n) for n in registry.available())
    kinds = registry.kinds()
    for name, summary in registry.describe().items():
        print(f"{name:<{width}}  [{kinds[name]}]  {summary}")
    for name, reason in registry.unavailable().items():
        print(f"({name} unavailable: {reason})")
    return 0


def _print_parameters(name: str) -> int:
    """``refflow methods --params NAME``: every parameter of the method, with its type, default,
    range and meaning (what ``--param KEY=VALUE`` accepts)."""
    try:
        table = registry.parameters(name)
    except ValueError as err:
        raise InputError(f"{err} (see `refflow methods`)") from None
    print(f"{name}: {registry.describe()[name]}")
    print(f"parameters (`refflow track --method {name} --param KEY=VALUE`, repeatable):")
    rows = [("name", "type", "default", "range", "meaning")]
    rows += [(p.name, p.type_text(), _value_text(p.default), p.range_text(), p.meaning) for p in table]
    widths = [max(len(row[i]) for row in rows) for i in range(4)]
    for row in rows:
        print("  " + "  ".join(cell.ljust(width) for cell, width in zip(row[:4], widths, strict=True))
              + "  " + row[4])
    return 0


def _value_text(value: Any) -> str:
    """A default as ``--param`` spells it."""
    if value is None or isinstance(value, bool):
        return str(value).lower()
    return f"{value:g}" if isinstance(value, float) else str(value)


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
    from flow import inputs
    from flow.figures import poi_figure
    from flow.measure import poi
    from flow.measure.driver import read_reference
    from flow.methods.klt import KLT

    out = Path(args.out)
    check_suffix(out, IMAGE_SUFFIXES)
    read = [("the video", args.input), *(("--mask", m) for m in args.mask or ()),
            ("--calibration", args.calibration), ("--video-origin", args.video_origin)]
    check_outputs([out], [(what, Path(p)) for what, p in read if p and Path(p).exists()])
    source_given, region = source_options(args), region_options(args)
    source = inputs.source_from(source_given, need_time=False)
    undistort, _ = inputs.undistorter(source_given, source)
    labels = inputs.poi_labels(region, source, undistort)
    mask = labels > 0
    inputs.mask_cut_by_roi(region, source, [], args.command)
    poi_xy = poi.poi_coordinates(mask, grid_step=args.grid_step)
    regions = inputs.measured_regions(labels, poi_xy, args.grid_step)
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

    out = Path(args.out)
    check_suffix(out, PLOT_SUFFIXES)
    check_outputs([out], [(f"the CSV {p}", Path(p)) for p in args.csv]
                  + [(f"{p}'s sidecar", Path(p).with_suffix(".json")) for p in args.csv])
    labels = args.label or []
    if labels and len(labels) != len(args.csv):
        raise InputError(f"--label given {len(labels)} times for {len(args.csv)} CSV files: one per file or none")
    positive("--min-hz", args.min_hz, "a frequency in Hz")
    # Every region of every CSV is a series of its own.
    measured = [(i, path, data) for i, path in enumerate(args.csv) for data in read_measurements(path)]
    units = args.units
    if units == "auto":
        units = "mm" if all(m["has_mm"] for _, _, m in measured) else "px"
    series, flagged = {}, {}
    for i, path, data in measured:
        if units == "mm" and not data["has_mm"]:
            raise InputError(f"{path} has no mm columns (tracked without a scale): use --units px")
        label = labels[i] if labels else data["label"]
        if labels and data["region"] is not None:
            label = f"{label} region {data['region']}"
        if label in series:
            label = f"{label} ({Path(path).stem})"
        series[label] = (data["time_s"], data[f"dx_{units}"], data[f"dy_{units}"])
        flagged[label] = (data["time_s"], data["flagged"][f"dx_{units}"], data["flagged"][f"dy_{units}"])
        if not np.isfinite(series[label][1]).any():
            grey = ": its flagged readings are drawn grey" if np.isfinite(flagged[label][1]).any() else ""
            print(f"refflow plot: note: {label} has no valid frame{grey} (see its sidecar's notes)", file=sys.stderr)
    summary = spectrum_figure(series, args.out, units=units, title=args.title or "", min_hz=args.min_hz,
                              flagged=flagged)
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
                   "white = POI; or grey values 1..N (any labels up to 127) = regions, each measured on its own in one run; "
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
    p.add_argument("--field", metavar="FIELD.h5",
                   help="write the whole displacement field (every mask pixel, every frame; HDF5, streamed; "
                        "dense methods; see docs/formats.md)")
    p.add_argument("--filter", choices=("paper", "median", "none"),
                   help="paper: eq. 10-12 (default for dense); median: same filters, median average; "
                        "none: plain average (default for KLT, as in the paper)")
    p.add_argument("--threshold-ratio", type=float, default=0.5,
                   help="eq. 10 threshold as a fraction of the median POI peak |d| (default 0.5)")
    p.add_argument("--mcr-threshold", type=float, default=0.5,
                   help="eq. 11 threshold on the mean cross-correlation (default 0.5)")
    p.add_argument("--max-typical-sigma", type=float, default=MAX_TYPICAL_SIGMA_PX, metavar="PX",
                   help="flag every frame when the typical frame's standard uncertainty exceeds PX on both "
                        f"axes (a video compressed past sub-pixel detail; default {MAX_TYPICAL_SIGMA_PX}, "
                        "0: never; methods that report the images' uncertainty)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="refflow", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("methods", help="list measurement methods, or one method's parameters")
    p.add_argument("--params", metavar="NAME", help="list every parameter of method NAME: type, default, "
                   "range and meaning (what --param KEY=VALUE accepts)")
    p.set_defaults(func=cmd_methods)

    p = sub.add_parser("track", help="measure displacement of the POIs against the reference frame")
    _add_input_options(p)
    p.add_argument("--method", help="method name (default: deepflow, else deepflow-opencv); see `refflow methods`")
    p.add_argument("--preset", choices=("ultrafast", "fast", "medium"), help="DIS preset")
    p.add_argument("--param", action="append", metavar="KEY=VALUE",
                   help="method parameter (repeatable); `refflow methods --params NAME` lists them with their ranges")
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
    p.add_argument("--part-field", action="append", metavar="FIELD.h5",
                   help="a part's field file (track --frames ... --field), once per part in the parts' order; "
                        "with --field, the merged field")
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
    p.add_argument("--out", required=True, help=f"output image ({', '.join(IMAGE_SUFFIXES)})")
    p.set_defaults(func=cmd_pois)

    p = sub.add_parser("plot", help="time history and spectrum of measured CSVs, dominant frequency marked")
    p.add_argument("csv", nargs="+", help="CSV files of `refflow track` (several methods are overlaid)")
    p.add_argument("--out", required=True, help=f"output figure ({', '.join(PLOT_SUFFIXES)})")
    p.add_argument("--label", action="append", help="legend label per CSV (default: the method in its sidecar)")
    p.add_argument("--units", choices=("auto", "px", "mm"), default="auto",
                   help="auto: mm where every CSV has a scale, else px")
    p.add_argument("--min-hz", type=float, help="ignore peaks below this frequency (default: one cycle per record)")
    p.add_argument("--title", help="figure title")
    p.set_defaults(func=cmd_plot)
    add_modal_parser(sub)
    add_export_parser(sub)
    add_field_plot_parser(sub)
    add_gui_parser(sub)
    return parser


def _claims(args: argparse.Namespace) -> list[Path]:
    """The files a command writes that a second run at the same time must not write too: its
    outputs, and the sidecar of a measurement (``--out a`` and ``--out a.csv`` share ``a.json``)."""
    if args.command == "field-plot":  # --out is a prefix: the pictures it always writes
        from flow.field.plot import outputs_of

        return outputs_of(args.out, args.movie, args.hz) if isinstance(args.out, str) and args.out else []
    written = ("out", "raw_tracks", "save_poi_tracks") + (("field",) if args.command in ("track", "merge") else ())
    names = [getattr(args, option, None) for option in written]
    paths = [Path(name) for name in names if isinstance(name, str) and name]
    if args.command in ("track", "merge") and isinstance(args.out, str) and args.out:
        paths.append(Path(args.out).with_suffix(".json"))
    return list(dict.fromkeys(paths))


def _os_error_text(err: OSError, args: argparse.Namespace) -> str:
    """The one line of a file that could not be read or written, naming it (where the system
    names none, as on a full disk, the command's outputs)."""
    what = err.strerror or str(err)
    where = err.filename or ", ".join(map(str, _claims(args))) or "a file it reads or writes"
    if err.errno in (errno.ENOSPC, errno.EDQUOT):
        return f"{what}: could not write {where} (free space on that disk, or choose another --out)"
    return f"{what}: {where} (check the path and permissions)"


def _stamps(paths: list[Path]) -> dict[Path, tuple[int, int] | None]:
    """Each path's (inode, modification time), None where it does not exist."""
    stamps: dict[Path, tuple[int, int] | None] = {}
    for path in paths:
        try:
            found = path.stat()
            stamps[path] = (found.st_ino, found.st_mtime_ns)
        except OSError:
            stamps[path] = None
    return stamps


def _outcome(claims: list[Path], before: dict[Path, tuple[int, int] | None]) -> str:
    """What an interrupted run left: nothing (its all-or-nothing output set was taken back or
    never published), or, interrupted after publishing it (while it said its last line), the
    outputs, complete; a set that is neither is named as such."""
    now = _stamps(claims)
    written = [path for path in claims if now[path] is not None and now[path] != before.get(path)]
    if not written:
        return "no output written"
    if len(written) == len(claims):
        return f"its outputs had been written, complete: {', '.join(map(str, written))}"
    others = [path for path in claims if path not in written]
    return (f"only part of its outputs was written ({', '.join(map(str, written))}; not "
            f"{', '.join(map(str, others))}): run it again")


def _signal_cause(err: BaseException) -> BaseException | None:
    """The KeyboardInterrupt or Terminated at the end of ``err``'s chain of causes (None: none)."""
    seen: set[int] = set()
    cause = err.__cause__
    while cause is not None and id(cause) not in seen:
        if isinstance(cause, (KeyboardInterrupt, Terminated)):
            return cause
        seen.add(id(cause))
        cause = cause.__cause__
    return None


class Terminated(BaseException):
    """SIGTERM (what `timeout`, SLURM and `kill` send), raised where the run is, so that
    every ``finally`` and all-or-nothing output set cleans up as on Ctrl-C."""


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated()


def _options_taking_a_value(parser: argparse.ArgumentParser) -> set[str]:
    """Every ``--option`` of every subcommand that takes one value."""
    found: set[str] = set()
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for subparser in action.choices.values():
                found |= _options_taking_a_value(subparser)
        elif action.option_strings and action.nargs is None:
            found.update(o for o in action.option_strings if o.startswith("--"))
    return found


def _attach_dashed_values(argv: list[str], options: set[str]) -> list[str]:
    """``--frames -10:5`` as ``--frames=-10:5``: argparse takes a value that starts with '-' and is
    not a plain negative number for an option and dumps the usage; attached, the option's own
    check says in one line what is wrong with it."""
    out: list[str] = []
    for token in argv:
        if out and out[-1] in options and re.match(r"-[0-9.]", token):
            out[-1] = f"{out[-1]}={token}"
        else:
            out.append(token)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    import signal
    import threading

    quiet_decoder_logs()
    program = argv is None and threading.current_thread() is threading.main_thread()  # not a caller's
    parser = build_parser()
    try:
        argv = expand_project_argv(sys.argv[1:] if argv is None else argv)
    except InputError as err:
        print(f"refflow track: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    args = parser.parse_args(_attach_dashed_values(list(argv), _options_taking_a_value(parser)))
    previous = None
    if threading.current_thread() is threading.main_thread():
        previous = signal.signal(signal.SIGTERM, _raise_terminated)
    claims = _claims(args)
    before = _stamps(claims)  # again under the claim (below); an interruption before it has these
    try:
        with claimed(claims) as existing:
            before = _stamps(claims)  # under the claim: no other run writes them now
            code = args.func(args)
            if code == 0 and existing:
                print(f"refflow {args.command}: note: replaced the earlier {', '.join(map(str, existing))}",
                      file=sys.stderr)
            return code
    except Terminated:
        print(f"refflow {args.command}: terminated (SIGTERM); {_outcome(claims, before)}", file=sys.stderr)
        return 143
    except InputError as err:
        print(f"refflow {args.command}: error: {err}", file=sys.stderr)
        return EXIT_USAGE
    except OSError as err:
        # Files the user named that cannot be read or written (permissions, full disk).
        print(f"refflow {args.command}: error: {_os_error_text(err, args)}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        print(f"refflow {args.command}: interrupted; {_outcome(claims, before)}", file=sys.stderr)
        return 130
    except SystemError as err:
        # A signal's exception raised inside a compiled kernel (numba calls back into Python,
        # e.g. to unpickle a constant) comes out as "returned a result with an exception set",
        # once per kernel it crossed, the signal's own exception at the end of the causes (CI:
        # Ctrl-C in DeepMatching's pooling ended the run with exit 1 and a traceback).
        cause = _signal_cause(err)
        if isinstance(cause, Terminated):
            print(f"refflow {args.command}: terminated (SIGTERM); {_outcome(claims, before)}", file=sys.stderr)
            return 143
        if isinstance(cause, KeyboardInterrupt):
            print(f"refflow {args.command}: interrupted; {_outcome(claims, before)}", file=sys.stderr)
            return 130
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
        if program:
            # The outcome is decided and said: a Ctrl-C from here on (the interpreter's exit,
            # joining threads) would end the process by the signal, or print a traceback, after
            # the run's line, whatever the outputs' state. (Not for callers in the same process.)
            signal.signal(signal.SIGINT, signal.SIG_IGN)


if __name__ == "__main__":
    sys.exit(main())
