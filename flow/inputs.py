"""A measurement's inputs in the pixels the flow is measured in: the frame source, the lens
undistortion of a calibration, the POI region labels and the static background.

Masks, rectangles and polygons are drawn on the raw video frames (what any viewer shows);
with a calibration they are carried into the undistorted frames, where the flow is computed.
`refflow track` and `refflow pois` read their inputs through these, in this order.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

from flow.io.errors import InputError
from flow.io.frames import FrameSource, Roi
from flow.io.jsonfiles import load_json, shown
from flow.io.source import open_source
from flow.options import BackgroundOptions, RegionOptions, SourceOptions


def source_from(options: SourceOptions, *, need_time: bool = True, others: tuple[Path, ...] = ()) -> FrameSource:
    """The frames the command's source options name (``--roi``, ``--fps``, ``--allow-truncated``);
    ``others``: the run's other input files, never frames of an image folder."""
    roi = Roi.parse(options.roi) if options.roi else None
    return open_source(options.input, roi=roi, fps=options.fps, require_fps=need_time,
                       allow_truncated=options.allow_truncated, exclude=others)


def video_origin(options: SourceOptions) -> tuple[int, int]:
    """Sensor pixel of the video's pixel (0, 0) (``--video-origin``; 0, 0 without it)."""
    text = options.video_origin
    if text is None:
        return 0, 0
    if not options.calibration:
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


def undistorter(options: SourceOptions, source: FrameSource) -> tuple[Any, dict[str, Any] | None]:
    """The undistortion of the calibration for the frames' ROI, and the calibration (None, None
    without one).

    With ``--video-origin X,Y`` the video is a window of the calibrated sensor (a
    cropped recording) whose pixel (0, 0) is sensor pixel (X, Y).
    """
    origin = video_origin(options)
    if not options.calibration:
        return None, None
    from flow.calibration import Undistorter, load_calibration

    calibration = load_calibration(options.calibration)
    name = f"calibration file {str(options.calibration)!r}"
    if origin == (0, 0):
        return Undistorter(calibration, source.roi, source.size, name=name), calibration
    sensor = tuple(calibration.get("image_size", ()))
    if len(sensor) != 2:
        raise InputError(f"calibration file {options.calibration!r} has no image_size: --video-origin needs "
                         "the calibrated sensor's size")
    roi = source.roi
    on_sensor = Roi(roi.x + origin[0], roi.y + origin[1], roi.width, roi.height)
    if on_sensor.x + source.size[0] - roi.x > sensor[0] or on_sensor.y + source.size[1] - roi.y > sensor[1]:
        raise InputError(f"a {source.size[0]}x{source.size[1]} video at --video-origin {origin[0]},{origin[1]} "
                         f"reaches beyond the {sensor[0]}x{sensor[1]} calibrated sensor")
    return Undistorter(calibration, on_sensor, sensor, video_origin=origin, name=name), calibration


def calibration_summary(options: SourceOptions, calibration: dict[str, Any] | None) -> dict[str, Any] | None:
    """What the sidecar (and a part, for `merge`'s scale points) records of the calibration."""
    if calibration is None:
        return None
    return {"file": str(options.calibration), "rms_px": calibration.get("rms_px"),
            "camera_matrix": calibration["camera_matrix"], "dist_coeffs": calibration["dist_coeffs"],
            "video_origin": list(video_origin(options))}


def poi_labels(options: RegionOptions, source: FrameSource, undistort: Any) -> np.ndarray:
    """The POI mask in the pixels the frames are measured in, as int32 region labels (0: no POI).

    Regions: a labelled mask PNG (grey values 1..N), or several masks (one region each,
    or their labels in turn).
    """
    from flow.measure import poi

    given = [a for a in (options.masks, options.rect, options.polygon) if a]
    if len(given) != 1:
        raise InputError("pass exactly one of --mask MASK.png, --rect X,Y,W,H or --polygon X1,Y1,...")
    if options.masks:
        labels = np.zeros((source.roi.height, source.roi.width), np.int32)
        for path in options.masks:
            found = poi.load_mask(path, frame_size=source.size, roi=source.roi,
                                  rotation_deg=source.rotation_deg, notes=source.notes, labels=True)
            both = int(((labels > 0) & (found > 0)).sum())
            if both:
                raise InputError(f"mask {path!r} overlaps the masks before it in {both} pixels: "
                                 "a pixel belongs to one region; draw the regions apart")
            labels = np.where(found > 0, found + labels.max(), labels).astype(np.int32)
    elif options.rect:
        labels = poi.rect_mask(options.rect, roi=source.roi).astype(np.int32)
    else:
        labels = poi.polygon_mask(options.polygon, roi=source.roi).astype(np.int32)
    if undistort is None:
        return labels
    moved = np.zeros(labels.shape, np.int32)
    for label in np.unique(labels[labels > 0]):
        moved[undistort.map_mask(labels == label)] = label
    return moved


def measured_regions(labels: np.ndarray, poi_xy: np.ndarray, grid_step: int) -> list[int]:
    """The labels of the regions measured; refuses a region the POI grid leaves empty."""
    present = [int(v) for v in np.unique(labels[labels > 0])]
    at_pois = set(np.unique(labels[poi_xy[:, 1], poi_xy[:, 0]]).tolist())
    empty = [label for label in present if label not in at_pois]
    if empty:
        raise InputError(f"region(s) {', '.join(map(str, empty))} of the mask hold no POI inside the ROI with "
                         f"--grid-step {grid_step}: draw them larger, lower --grid-step or widen --roi")
    return present


def mask_cut_by_roi(options: RegionOptions, source: FrameSource, notes: list[str], command: str) -> int:
    """Pixels of full-frame masks that the ROI leaves out; warns (and notes) when any."""
    from flow.measure import poi

    outside = sum(poi.pixels_outside_roi(path, frame_size=source.size, roi=source.roi)
                  for path in options.masks)
    if outside:
        message = (f"--roi {source.roi.as_text()} leaves {outside} of the mask's pixels out: only the mask "
                   "inside the ROI is measured (widen --roi to measure all of it)")
        notes.append(message)
        print(f"refflow {command}: warning: {message}", file=sys.stderr)
    return outside


def background_for(options: BackgroundOptions, source: FrameSource, undistort: Any,
                   poi_mask: np.ndarray) -> Any:
    """The static points of the background mask or rectangle (None without them)."""
    from flow.measure import poi
    from flow.measure.background import Background

    if options.mask and options.rect:
        raise InputError("pass one of --background-mask and --background-rect, not both")
    if options.mask:
        mask = poi.load_mask(options.mask, frame_size=source.size, roi=source.roi,
                             what="background mask", instead="--background-rect",
                             rotation_deg=source.rotation_deg, notes=source.notes)
    elif options.rect:
        mask = poi.rect_mask(options.rect, roi=source.roi)
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
    return Background.from_mask(mask, model=options.model)
