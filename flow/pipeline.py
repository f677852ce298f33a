"""The one path from a video to a measurement, in this order: open the source, undistort,
mask (labelled regions) and background, scale, track, measure, write.

:func:`track` is ``refflow track``; :func:`merge` joins the raw-tracks parts of one run
(``refflow merge``) through the same scale (:func:`flow.scale.measurement_scale`) and the same
writer. Both take the typed options of :mod:`flow.options` and refuse bad input with
:class:`flow.io.errors.InputError` before any frame is read where they can; notes and warnings
the user should see go to stderr as they happen.
"""

from __future__ import annotations

import math
import os
import sys
import time
import warnings
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from flow import inputs
from flow.io.errors import InputError
from flow.io.frames import COPY_WINDOW_PX, HISTORY_SHARE, FrameSource, check_fps
from flow.measure.reference import check as check_reference
from flow.methods import registry
from flow.options import FilterOptions, FramesInfo, InputInfo, MergeOptions, RunInfo, TrackOptions
from flow.scale import NO_SCALE_NOTE, Scale, check_scale_options, measurement_scale
from flow.write import output_names, write_outputs
from refflow.io import finite_or_none


@dataclass(frozen=True)
class Outcome:
    """What a run measured: the method, the tracks, each region's ``(label, Measurement)``
    (none without a CSV) and the files written."""

    method: str
    tracks: Any
    results: list[tuple[int, Any]]
    written: list[str]


@dataclass(frozen=True)
class _Setup:
    """The inputs of a track run in measured pixels (after open, undistort, mask, scale)."""

    source: FrameSource
    undistort: Any
    calibration: dict[str, Any] | None  # calibration_summary
    scale: Scale
    labels: np.ndarray
    mask_pixels_outside_roi: int
    poi_xy: np.ndarray
    regions: list[int]
    background: Any


def default_method() -> tuple[str, str | None]:
    """The method `track` runs without --method, and a note when it is not deepflow."""
    names = registry.available()
    if "deepflow" in names:
        return "deepflow", None
    reason = registry.unavailable().get("deepflow")
    return "deepflow-opencv", ("clean-room `deepflow` is not available"
                               + (f" ({reason})" if reason else "")
                               + "; using deepflow-opencv")


def available_cores() -> int:
    """Cores this process may run on (its CPU affinity where the system tells it)."""
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):
        return max(os.cpu_count() or 1, 1)


def method_params(items: tuple[str, ...], preset: str | None, name: str) -> dict[str, Any]:
    """The method's keyword values from ``KEY=VALUE`` texts (int, float, true/false/none, or text)."""
    params: dict[str, Any] = {}
    for item in items:
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
    if preset:
        if name != "dis":
            raise InputError(f"--preset applies to the dis method only, not {name!r}")
        params["preset"] = preset
    return params


def build_method(name: str, params: dict[str, Any]) -> Any:
    try:
        return registry.get_method(name, **params)
    except (TypeError, ValueError) as err:
        # The method constructors reject bad keyword values with ValueError: here that
        # value came from the command line, so it is the user's to fix.
        raise InputError(f"bad --param for {name}: {err} (see `refflow methods --params {name}`)") from None


def parse_frames(text: str | None) -> tuple[int, int | None] | None:
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


def check_filter_options(options: FilterOptions) -> None:
    if not 0 <= options.threshold_ratio:
        raise InputError(f"--threshold-ratio {options.threshold_ratio} is negative: pass a fraction >= 0")
    if not -1 <= options.mcr_threshold <= 1:
        raise InputError(f"--mcr-threshold {options.mcr_threshold} is outside [-1, 1]: it is a correlation")
    if not (math.isfinite(options.max_typical_sigma_px) and options.max_typical_sigma_px >= 0):
        raise InputError(f"--max-typical-sigma {options.max_typical_sigma_px} is not a number >= 0: pass pixels "
                         "(0 never flags a clip for its precision)")


def _note(notes: list[str], text: str) -> None:
    notes.append(text)
    print(f"refflow track: note: {text}", file=sys.stderr)


def track(options: TrackOptions) -> Outcome:
    """Measure the POIs' displacement against the reference frame and write the outputs."""
    started = time.perf_counter()
    notes: list[str] = []
    name = _method_name(options.method, notes)
    jobs = _checked_jobs(options, notes)
    frames = parse_frames(options.frames)
    params = method_params(options.params, options.preset, name)
    method = build_method(name, params)
    sparse = getattr(method, "kind", "dense") == "sparse"
    _check_method_fits(options, name, sparse, frames)
    read_paths = options.input_paths()
    output_names(options.outputs, read_paths)
    setup = _set_up(options, notes, name, sparse)
    params, method = _for_source(name, params, method, setup.source, notes)
    saturated = check_reference(setup.source, options.reference_frame, options.reference_average,
                                setup.labels > 0, setup.undistort)
    if saturated is not None:
        _note(notes, saturated)
    field = _field_stream(options, setup, sparse, name)
    try:
        return _track_and_write(options, setup, method, name, params, sparse, jobs, frames, notes, read_paths,
                                started, field)
    finally:
        if field is not None:
            field.discard()


def _field_stream(options: TrackOptions, setup: _Setup, sparse: bool, name: str) -> Any:
    """The ``--field`` file's stream (None without one)."""
    if not options.outputs.field:
        return None
    if sparse:
        raise InputError(f"--field needs a dense method: {name} follows a few features, it has no field")
    from flow.field.stream import FieldStream

    roi = setup.source.roi
    return FieldStream(options.outputs.field, setup.labels, setup.poi_xy, reference_frame=options.reference_frame,
                       origin_px=(roi.x, roi.y), background=setup.background)


def _track_and_write(options: TrackOptions, setup: _Setup, method: Any, name: str, params: dict[str, Any],
                     sparse: bool, jobs: int, frames: tuple[int, int | None] | None, notes: list[str],
                     read_paths: list[tuple[str, Path]], started: float, field: Any) -> Outcome:
    tracks = _track_frames(options, setup, method, lambda: build_method(name, params), sparse, jobs, frames, notes,
                           field)
    if not setup.scale.given:  # on the console too where a CSV's mm columns stay empty
        if options.outputs.csv:
            _note(notes, NO_SCALE_NOTE)
        else:
            notes.append(NO_SCALE_NOTE)
    source = setup.source
    if source.bit_depth > 8 and not method.full_depth:
        notes.append(f"{name} takes 8-bit images: the {source.bit_depth}-bit data was rounded to 8 bits for it "
                     "(the default method measures at full depth)")
    run = _run_info(options, setup, tracks, name, method, sparse, jobs)
    results = write_outputs(options.outputs, options.filter, read_paths, tracks, run, notes, setup.scale, started,
                            field=field)
    written = [p for p in (options.outputs.raw_tracks, options.outputs.field, options.outputs.csv) if p]
    return Outcome(name, tracks, results, written)


# A lossy stream whose encoder did not write its quality (a phone's hardware encoder, a JPEG
# folder) is taken as libx264's default, about a phone's quality: the codec floor of the texture
# readings' sigma is measured at it (see flow.methods.deepflow.codecfloor).
DEFAULT_CRF = 23.0


def _for_source(name: str, params: dict[str, Any], method: Any, source: Any,
                notes: list[str]) -> tuple[dict[str, Any], Any]:
    """A method's parameters that depend on the input, resolved from it where the user left them
    (``bias_correction``: on for lossless frames only, see :attr:`flow.io.frames.FrameSource.lossless`,
    and not for lossless files of a lossy codec's frames, see :func:`_lossy_history`, unless the user
    turned it on; ``codec_crf``: a lossy stream's quality as its encoder wrote it, :data:`DEFAULT_CRF`
    where it did not), and the method built with them; the sidecar records the value taken."""
    declared = {param.name for param in getattr(method, "parameters", ())}
    given = {key for key, value in params.items() if value is not None}
    unset = ({"bias_correction", "codec_crf"} & declared) - given
    # A bias correction the user turned on says the frames are a camera's own: not looked into.
    trusted = params.get("bias_correction") is True
    lossless = bool(unset) and source.lossless and (trusted or not _lossy_history(source, notes))
    resolved = {}
    if "bias_correction" in unset:
        resolved["bias_correction"] = lossless
    if "codec_crf" in unset and not lossless:
        crf = getattr(source, "codec_crf", None)
        resolved["codec_crf"] = DEFAULT_CRF if crf is None else crf
    if not resolved:
        return params, method
    params = {**params, **resolved}
    return params, build_method(name, params)


def _lossy_history(source: Any, notes: list[str]) -> bool:
    """Whether frames in lossless files show a lossy codec's copied blocks (see
    :func:`flow.io.frames.copied_share`), noted for the user where they do."""
    share = source.copied_share()
    if share <= HISTORY_SHARE:
        return False
    _note(notes, f"{source.path.name}: lossless files, but {share:.0%} of a frame's textured {COPY_WINDOW_PX}x"
                 f"{COPY_WINDOW_PX} px windows are the frame before's bit for bit, as a lossy codec leaves them "
                 f"(frames exported from a video): read as a lossy stream of unknown quality (codec_crf "
                 f"{DEFAULT_CRF:g}); pass --param codec_crf=N with the video's quality where known, or "
                 f"--param bias_correction=true where the frames are a camera's own or a render without noise")
    return True


def _method_name(asked: str | None, notes: list[str]) -> str:
    name = asked
    if name is None:
        name, note = default_method()
        if note:
            _note(notes, note)
    if name not in registry.available():
        raise InputError(f"unknown method {name!r}; available: {', '.join(registry.available())} "
                         "(see `refflow methods`)")
    return name


def _checked_jobs(options: TrackOptions, notes: list[str]) -> int:
    """Check the options that need no file; returns the threads to measure with."""
    check_scale_options(options.scale)
    check_filter_options(options.filter)
    check_fps(options.source.fps)
    if options.max_frames is not None and options.max_frames < 1:
        raise InputError(f"--max-frames {options.max_frames} must be >= 1")
    if options.jobs is not None and options.jobs < 1:
        raise InputError(f"--jobs {options.jobs} must be >= 1")
    cores = available_cores()
    if options.jobs is not None and options.jobs > cores:
        # More jobs than cores only builds more method instances (memory) for no speed.
        _note(notes, f"--jobs {options.jobs} is more than the {cores} cores this process may use: {cores} jobs")
    outputs = options.outputs
    if not outputs.csv and not outputs.raw_tracks:
        raise InputError("nothing to write: pass --out CSV (measurement) and/or --raw-tracks NPZ (unfiltered part)")
    if outputs.poi_tracks and not outputs.csv:
        raise InputError("--save-poi-tracks records the filtered measurement: pass --out CSV too "
                         "(--raw-tracks alone keeps the unfiltered tracks)")
    return min(options.jobs or cores, cores)


def _check_method_fits(options: TrackOptions, name: str, sparse: bool, frames: tuple[int, int | None] | None) -> None:
    if sparse and frames is not None:
        raise InputError(f"--frames needs a reference-frame (dense) method: {name} follows its features "
                         "from frame to frame, so its run cannot be split")
    if sparse and (options.background.mask or options.background.rect):
        raise InputError(f"--background-mask/--background-rect need a dense method: {name} picks its own "
                         "features (the paper's KLT baseline has no camera-motion compensation)")


def _set_up(options: TrackOptions, notes: list[str], name: str, sparse: bool) -> _Setup:
    """Open the source, undistort, scale, mask and background, in this order."""
    from flow.measure import poi

    source = inputs.source_from(options.source, others=tuple(path for _, path in options.input_paths()))
    undistort, calibration = inputs.undistorter(options.source, source)
    calibration_info = inputs.calibration_summary(options.source, calibration)
    scale = measurement_scale(options.scale, calibration_info, tuple(source.size))
    labels = inputs.poi_labels(options.region, source, undistort)
    mask = labels > 0
    outside = inputs.mask_cut_by_roi(options.region, source, notes, "track")
    poi_xy = poi.poi_coordinates(mask, grid_step=options.region.grid_step)
    regions = inputs.measured_regions(labels, poi_xy, options.region.grid_step)
    if sparse and len(regions) > 1:
        raise InputError(f"the mask has {len(regions)} regions but {name} picks its own features in one region: "
                         "use a dense method (the default) or one region per run")
    background = inputs.background_for(options.background, source, undistort, mask)
    return _Setup(source, undistort, calibration_info, scale, labels, outside, poi_xy, regions, background)


def _track_frames(options: TrackOptions, setup: _Setup, method: Any, new_method: Any, sparse: bool, jobs: int,
                  frames: tuple[int, int | None] | None, notes: list[str], field: Any = None) -> Any:
    """The unfiltered tracks; the source's notes and the warnings raised meanwhile join ``notes``."""
    from flow.measure import driver

    # The per-POI store goes beside the output: a real disk, unlike a memory-backed /tmp.
    store_dir = Path(options.outputs.csv or options.outputs.raw_tracks).resolve().parent
    store_dir = store_dir if store_dir.is_dir() else None
    reference = {"reference_frame": options.reference_frame, "reference_average": options.reference_average}
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if sparse:
            tracks = driver.track_sparse(setup.source, method, setup.labels > 0, **reference,
                                         max_frames=options.max_frames, undistort=setup.undistort,
                                         progress=options.progress, store_dir=store_dir)
        else:
            tracks = driver.track_dense(setup.source, new_method, setup.poi_xy, **reference, jobs=jobs,
                                        max_frames=options.max_frames, frames=frames, undistort=setup.undistort,
                                        progress=options.progress, store_dir=store_dir,
                                        background=setup.background, mask=setup.labels, field=field)
    notes.extend(setup.source.notes)
    time_s, clock_notes = setup.source.clock(tracks.frame, tracks.time_s)
    for note in clock_notes:
        _note(notes, note)
    timings = tracks.timings_s or {}
    if timings.get("mask_past_outline_px", 0):
        filled = int(timings.get("rim_filled_frames", 0))
        _note(notes, f"the mask reaches up to {timings['mask_past_outline_px']:g} px past a sharp step of its grey "
              "or texture, taken for the member's outline or end: the outline found there read "
              + (f"{filled} of {len(tracks.frame)} frames, and in those the mask's pixels beyond it took the member's "
                 "motion (in the others, their own)" if filled else "no frame, and the mask's pixels beyond it kept "
                 "their own flow")
              + "; draw the mask inside the structure to keep to its own pixels")
    if timings.get("texture_light_blocks", 0):
        _note(notes, f"the light changed across the mask's texture in {int(timings['texture_light_blocks'])} of its "
              "fits (a shadow's or a cloud's edge passing over it): those were read with a gain and offset of "
              "their own in every block of 16 px or more (texture_light_blocks in the sidecar)")
    tracks = replace(tracks, time_s=time_s)
    for warning in caught:
        notes.append(str(warning.message))
        print(f"refflow track: warning: {warning.message}", file=sys.stderr)
    return tracks


def _run_info(options: TrackOptions, setup: _Setup, tracks: Any, name: str, method: Any, sparse: bool,
              jobs: int) -> RunInfo:
    source, background = setup.source, setup.background
    background_info = None if background is None else {
        "source": options.background.mask or f"rect {options.background.rect}", "points": int(len(background.xy)),
        "model": background.model, "requested_model": options.background.model}
    return RunInfo(
        tool="refflow track",
        input=InputInfo(path=str(options.source.input), frame_size=list(source.size),
                        fps=finite_or_none(source.fps), rotation_deg=source.rotation_deg,
                        bit_depth=source.bit_depth,
                        measured_bits=source.bit_depth if method.full_depth else min(source.bit_depth, 8),
                        header_frames=tracks.header_frames, frames_decoded=source.frames_read,
                        frames_measured=len(tracks.frame), truncated=tracks.truncated),
        frames=FramesInfo(first=int(tracks.frame[0]), stop=int(tracks.frame[-1]) + 1, requested=options.frames),
        method=name, method_kind="sparse" if sparse else "dense", parameters=method.params(),
        reference_frame=options.reference_frame, reference_average=options.reference_average,
        jobs=jobs if not sparse else 1, roi=source.roi.as_dict(), calibration=setup.calibration,
        poi=_poi_info(setup, tracks, sparse, options.region.grid_step), background=background_info,
        reference_digest=tracks.reference_digest, timings=tracks.timings_s)


def _poi_info(setup: _Setup, tracks: Any, sparse: bool, grid_step: int) -> dict[str, Any]:
    """The POIs measured, with where they are: full-frame pixels (undistorted with a
    calibration), e.g. a measurement point's position for mode shapes (`refflow modal`)."""
    roi, labels = setup.source.roi, setup.labels

    def centroid(x_px: np.ndarray, y_px: np.ndarray) -> list[float]:
        return [round(float(np.mean(x_px)) + roi.x, 3), round(float(np.mean(y_px)) + roi.y, 3)]

    info = {"count": int(len(tracks.x_px)), "source": "features" if sparse else "mask",
            "mask_pixels": int((labels > 0).sum()), "mask_pixels_outside_roi": setup.mask_pixels_outside_roi,
            "grid_step": grid_step, "centroid_px": centroid(tracks.x_px, tracks.y_px)}
    if tracks.region is not None:
        info["regions"] = [
            {"label": label, "count": int(np.sum(tracks.region == label)),
             "mask_pixels": int(np.sum(labels == label)),
             "centroid_px": centroid(tracks.x_px[tracks.region == label], tracks.y_px[tracks.region == label])}
            for label in tracks.labels()]
    return info


def merge(options: MergeOptions) -> tuple[int, Outcome]:
    """Join raw-tracks parts of one run into one measurement; returns the number of parts
    and what was measured."""
    from flow.measure import formats

    started = time.perf_counter()
    check_scale_options(options.scale)
    check_filter_options(options.filter)
    read_paths = options.input_paths()
    output_names(options.outputs, read_paths)
    if options.part_fields and not options.outputs.field:
        raise InputError("--part-field gives the parts' fields to merge: pass --field FIELD.h5 for the merged one")
    if options.outputs.field and len(options.part_fields) != len(options.parts):
        raise InputError(f"--field needs each part's field: {len(options.parts)} parts but "
                         f"{len(options.part_fields)} --part-field (one per part, in the parts' order)")
    store_dir = Path(options.outputs.csv).resolve().parent
    tracks, metas = formats.load_raw_tracks(list(options.parts), store_dir=store_dir if store_dir.is_dir() else None)
    first = RunInfo.from_part(metas[0])
    # The parts were measured undistorted: the scale points go through the same calibration.
    scale = measurement_scale(options.scale, first.calibration, tuple(first.input.frame_size))
    notes = [note for meta in metas for note in meta.get("notes", []) if "no scale given" not in note]
    if not scale.given:
        notes.append(NO_SCALE_NOTE)
        print(f"refflow merge: note: {NO_SCALE_NOTE}", file=sys.stderr)
    run = replace(
        first, tool="refflow merge",
        input=replace(first.input, frames_decoded=max(m["input"]["frames_decoded"] for m in metas),
                      frames_measured=len(tracks.frame), truncated=tracks.truncated),
        frames=FramesInfo(first=int(tracks.frame[0]), stop=int(tracks.frame[-1]) + 1, requested=None),
        parts=[{"file": str(p), "frames": [m["frames"]["first"], m["frames"]["stop"]]}
               for p, m in zip(options.parts, metas, strict=True)],
        timings=tracks.timings_s)
    field = None
    if options.outputs.field:
        from flow.field.stream import merge_parts

        field = merge_parts(options.outputs.field, list(options.part_fields))
    try:
        results = write_outputs(options.outputs, options.filter, read_paths, tracks, run, notes, scale, started,
                                field=field, field_offset_removed=True)
    finally:
        if field is not None:
            field.discard()
    return len(metas), Outcome(first.method, tracks, results, [options.outputs.csv])
