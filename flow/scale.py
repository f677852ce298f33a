"""The image scale of a measurement, in mm per pixel: the one path `track` and `merge` share.

Scale points are raw video pixels; with a calibration they are undistorted first, because the
displacements are measured undistorted. `merge` once skipped that for a scale file's points
and read a different mm per pixel than `track` of the same frames (issue 14): both come here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from decimal import Decimal
from typing import Any

from flow.io.errors import InputError
from flow.io.jsonfiles import json_number, load_json, shown
from flow.options import ScaleOptions

# No camera images a structure at a kilometre per pixel: a larger scale is a typing error
# (and would overflow the mm columns).
MAX_MM_PER_PX = 1e6
NO_SCALE_NOTE = ("no scale given: measuring in pixels (the mm columns are NaN); pass --mm-per-px, "
                 "--known-length/--between or --scale-file for mm")


@dataclass(frozen=True)
class Scale:
    """``mm_per_px`` (NaN when no scale was given: the mm columns are then NaN) and how it
    was found (the sidecar's ``scale.source``)."""

    mm_per_px: float
    source: str

    @property
    def given(self) -> bool:
        return not self.source.startswith("none")


def positive(name: str, value: float | None, what: str) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} {value} is not a finite positive number: pass {what} > 0")


def check_scale_options(options: ScaleOptions) -> None:
    """Reject bad scale options before any frame is read."""
    positive("--mm-per-px", options.mm_per_px, "the image scale in mm per pixel")
    positive("--known-length", options.known_length, "the known length in mm")
    given = [options.mm_per_px is not None, options.known_length is not None, options.scale_file is not None]
    if sum(given) > 1:
        raise InputError("pass one scale: --mm-per-px, --known-length/--between or --scale-file")
    if (options.known_length is None) != (options.between is None):
        raise InputError("--known-length needs --between X1,Y1,X2,Y2 (and vice versa)")


def measurement_scale(options: ScaleOptions, calibration: dict[str, Any] | None,
                      frame_size: tuple[int, int] | None) -> Scale:
    """The scale of a measurement whose frames were undistorted by ``calibration`` (the run's
    calibration summary, :func:`flow.inputs.calibration_summary`, also what a part's sidecar
    holds; None without one)."""
    from flow.calibration import point_undistorter, scale_from_known_length

    undistort_points = point_undistorter(calibration)
    if options.scale_file is not None:
        mm_per_px, how = _scale_from_file(options.scale_file, undistort_points, frame_size)
    elif options.known_length is not None:
        mm_per_px = scale_from_known_length(options.known_length, options.between, undistort_points,
                                            frame_size=frame_size)
        where = " (undistorted)" if undistort_points is not None else ""
        how = f"known length {options.known_length} mm between {options.between}{where}"
    elif options.mm_per_px is not None:
        mm_per_px, how = options.mm_per_px, "--mm-per-px"
    else:
        return Scale(float("nan"), "none (mm columns are NaN)")
    if not mm_per_px < MAX_MM_PER_PX:
        raise InputError(f"scale {mm_per_px:g} mm per pixel ({how}) is beyond {MAX_MM_PER_PX:g} (a kilometre "
                         "per pixel): check the scale's units and points")
    return Scale(mm_per_px, how)


def _scale_from_file(path: str, undistort_points: Any, frame_size: tuple[int, int] | None) -> tuple[float, str]:
    """``(mm_per_px, how)`` from a JSON file: its ``mm_per_px``, or a known length
    ``known_length_mm`` between two raw video points ``between_px`` [X1, Y1, X2, Y2]
    (measured in the undistorted image with a calibration, like --known-length); a file
    holding both must give the same scale with each (:func:`_agree`)."""
    data = load_json(path, f"scale file {path}")
    data = data if isinstance(data, dict) else {}
    if "known_length_mm" in data or "between_px" in data:
        mm_per_px, how = _known_length_in_file(path, data, undistort_points, frame_size)
        if "mm_per_px" in data:
            _file_mm_per_px(path, data)
            _agree(path, data["mm_per_px"], mm_per_px)
        return mm_per_px, how
    return _file_mm_per_px(path, data), f"mm_per_px from {path}"


def _known_length_in_file(path: str, data: dict[str, Any], undistort_points: Any,
                          frame_size: tuple[int, int] | None) -> tuple[float, str]:
    from flow.calibration import scale_from_known_length

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


def _file_mm_per_px(path: str, data: dict[str, Any]) -> float:
    value = data.get("mm_per_px")
    number = json_number(value)
    if number is None or not 0 < number < math.inf:
        raise InputError(f"scale file {path} needs a positive number under 'mm_per_px' (or "
                         f"'known_length_mm' and 'between_px'), got {shown(value)}")
    return number


def _agree(path: str, written: int | float, from_length: float) -> None:
    """Refuse a scale file whose ``mm_per_px`` and known length give two scales.

    They agree when the written ``mm_per_px`` is the known length's scale rounded to the
    digits it was written with (0.052 stands for 0.0523, not for 0.06): a file that states
    its scale twice, once rounded, is consistent; one whose two statements differ is
    ambiguous, and picking one would silently make the other wrong.
    """
    half_unit = 0.5 * 10.0 ** Decimal(repr(written)).as_tuple().exponent  # 10 -> 0.5, 0.52 -> 0.005
    if abs(written - from_length) <= max(half_unit, 1e-9 * from_length):
        return
    raise InputError(f"scale file {path} gives two scales: 'mm_per_px' {written!r} and 'known_length_mm' over "
                     f"'between_px' {from_length:.6g} mm per pixel: keep one of them in the file")
