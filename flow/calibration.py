"""Camera calibration (checkerboard), ROI-consistent undistortion and image scale.

References
----------
Z. Zhang, "A flexible new technique for camera calibration", IEEE TPAMI 22(11), 2000.
OpenCV ``calibrateCamera`` / ``initUndistortRectifyMap``.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from flow.io.errors import InputError
from flow.io.frames import Roi, as_uint8
from flow.io.jsonfiles import json_number, load_json, shown
from flow.io.source import open_source


def board_points(cols: int, rows: int, square_mm: float) -> np.ndarray:
    """Inner-corner coordinates of a planar board, ``(cols*rows, 3)`` float32 in mm."""
    grid = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2).astype(np.float32)
    return np.hstack([grid * np.float32(square_mm), np.zeros((len(grid), 1), np.float32)])


def parse_board(text: str) -> tuple[int, int]:
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board {text!r} is not COLSxROWS of inner corners, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise InputError(f"--board {text!r} needs at least 2x2 inner corners")
    return cols, rows


SEARCH_SIDE_PX = 1600  # the board is searched for at this size, then refined at full size


def find_corners(grey: np.ndarray, board: tuple[int, int]) -> np.ndarray | None:
    """Sub-pixel inner corners of the board in a grey image, or None.

    The board search of ``findChessboardCorners`` takes tens of seconds on a 4K
    frame, and minutes where the board is not wholly in view; it runs on a copy
    reduced to :data:`SEARCH_SIDE_PX`. Where that finds nothing (a board too small
    for the reduced copy, or one cut by the frame's edge), the sector-based search
    (``findChessboardCornersSB``, about a second on a 4K frame) looks at full size.
    ``cornerSubPix`` then refines the corners on the full-resolution image with a
    window matched to the board's square size.
    """
    flags = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE
    shrink = min(1.0, SEARCH_SIDE_PX / max(grey.shape))
    found, corners = False, None
    if shrink < 1.0:
        small = cv2.resize(grey, None, fx=shrink, fy=shrink, interpolation=cv2.INTER_AREA)
        found, corners = cv2.findChessboardCorners(small, board, flags=flags)
        if found:
            # INTER_AREA maps pixel centres by (x + 0.5) * shrink - 0.5
            corners = ((corners + 0.5) / shrink - 0.5).astype(np.float32)
    if not found:
        found, corners = cv2.findChessboardCornersSB(grey, board)
    if not found:
        return None
    # Half the smallest spacing of neighbouring corners keeps the window inside one square.
    grid = corners.reshape(board[1], board[0], 2)
    spacing = min(np.linalg.norm(np.diff(grid, axis=1), axis=2).min(),
                  np.linalg.norm(np.diff(grid, axis=0), axis=2).min())
    half = int(np.clip(spacing / 4, 3, 15))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
    return cv2.cornerSubPix(grey, corners, (half, half), (-1, -1), criteria)


# A calibration whose corners reproject worse than this is not a calibration (a good one is
# below 0.5 px; a degenerate set of views reads thousands or millions of px).
MAX_RMS_PX = 2.0
# Views whose corners all lie within this of an earlier view's are the same view.
DISTINCT_VIEW_PX = 1.0


def _distinct_views(image_points: list[np.ndarray]) -> int:
    """How many views differ from every earlier one (some corner moved > DISTINCT_VIEW_PX)."""
    kept: list[np.ndarray] = []
    for corners in image_points:
        points = corners.reshape(-1, 2)
        if all(np.abs(points - other).max() > DISTINCT_VIEW_PX for other in kept):
            kept.append(points)
    return len(kept)


def calibrate(source: str | Path, *, board: tuple[int, int], square_mm: float,
              max_views: int = 60, fix_k3: bool = True, step: int = 1) -> dict[str, Any]:
    """Calibrate intrinsics and distortion from checkerboard views.

    Parameters
    ----------
    source : path
        Folder of images or a video showing the board (every frame is tried,
        at most ``max_views`` evenly spread detections are used).
    board : (cols, rows)
        Inner corners per row and column.
    square_mm : float
        Square side in mm (only the extrinsics depend on it).
    fix_k3 : bool
        Keep ``k3 = 0`` (default): with views that do not reach the image corners,
        k2 and k3 trade off against each other and k3 mostly fits noise.
    step : int
        Try every ``step``-th frame only (a video of a slowly moved board holds
        many near-identical views; the board search is the slow part).

    Returns
    -------
    dict
        ``camera_matrix`` (3x3), ``dist_coeffs`` (k1, k2, p1, p2, k3),
        ``rms_px`` reprojection error, ``image_size`` [w, h], ``views_used``.
    """
    if not (math.isfinite(square_mm) and square_mm > 0):
        raise InputError(f"--square-mm {square_mm} is not positive: pass the square side in mm")
    if step < 1:
        raise InputError(f"--step {step} must be >= 1")
    # A cut calibration video still holds good views: use the ones that decode.
    frames = open_source(source, require_fps=False, allow_truncated=True)
    obj = board_points(*board, square_mm)
    image_points = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for index, _, grey in frames:
            if index % step:
                continue
            corners = find_corners(as_uint8(grey), board)  # the board search takes 8 bits
            if corners is not None:
                image_points.append(corners)
    if len(image_points) < 3:
        raise InputError(
            f"the {board[0]}x{board[1]} board was found in {len(image_points)} of "
            f"{frames.frames_read} images; need at least 3: check --board (inner corners) and the images")
    distinct = _distinct_views(image_points)
    if distinct < 3:
        raise InputError(
            f"the board views are (nearly) the same: {distinct} of the {len(image_points)} views differ by "
            f"more than {DISTINCT_VIEW_PX:g} px; move or tilt the board (or the camera) between views, "
            "across the whole frame")
    if len(image_points) > max_views:
        keep = np.linspace(0, len(image_points) - 1, max_views).round().astype(int)
        image_points = [image_points[i] for i in keep]
    size = (frames.width, frames.height)
    rms, camera_matrix, dist, _, _ = cv2.calibrateCamera(
        [obj] * len(image_points), image_points, size, None, None,
        flags=cv2.CALIB_FIX_K3 if fix_k3 else 0)
    if not (math.isfinite(rms) and rms <= MAX_RMS_PX and np.isfinite(camera_matrix).all()
            and np.isfinite(dist).all() and camera_matrix[0, 0] > 0 and camera_matrix[1, 1] > 0):
        raise InputError(
            f"the calibration failed: its reprojection error is {rms:.3g} px (a usable one is below "
            f"{MAX_RMS_PX:g} px, a good one below 0.5 px); take 10 or more sharp views of the whole board, "
            "tilted and spread across the frame, and check --board and --square-mm")
    return {
        "camera_matrix": camera_matrix.tolist(),
        "dist_coeffs": dist.ravel()[:5].tolist(),
        "rms_px": float(rms),
        "image_size": list(size),
        "board": list(board),
        "square_mm": float(square_mm),
        "views_used": len(image_points),
        "fix_k3": bool(fix_k3),
        "notes": frames.notes + [str(w.message) for w in caught],
    }


# Distortion models OpenCV knows: k1 k2 p1 p2 [k3 [k4 k5 k6 [s1 s2 s3 s4 [tx ty]]]].
DIST_COEFF_COUNTS = (4, 5, 8, 12, 14)


def _json_numbers(value: Any) -> list[float] | None:
    """The numbers of a JSON list, or of a list of equal rows, flattened; None if ``value`` is
    not one or holds anything but numbers (booleans included)."""
    if not isinstance(value, list):
        return None
    if value and all(isinstance(row, list) for row in value):
        if len({len(row) for row in value}) != 1:
            return None
        value = [v for row in value for v in row]
    numbers = [json_number(v) for v in value]
    return None if any(v is None for v in numbers) else numbers


def load_calibration(path: str | Path) -> dict[str, Any]:
    """The calibration JSON of `refflow calibrate` at ``path``, checked and cleaned: a finite 3x3
    ``camera_matrix`` with positive focal lengths, finite ``dist_coeffs`` (4, 5, 8, 12 or 14),
    ``image_size`` [width, height] of positive integers where given, ``rms_px`` a finite
    number or None. Anything else raises :class:`InputError` naming the entry."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"calibration file {str(path)!r} does not exist: run `refflow calibrate` first")
    name = f"calibration file {str(path)!r}"
    data = load_json(path, name)
    again = "run `refflow calibrate` again or fix the file"
    if not isinstance(data, dict):
        raise InputError(f"{name} is not a refflow calibration (a JSON object with 'camera_matrix' and "
                         f"'dist_coeffs'): {again}")
    camera = _json_numbers(data.get("camera_matrix"))
    if camera is None or len(camera) != 9 or not all(math.isfinite(v) for v in camera) \
            or not (camera[0] > 0 and camera[4] > 0):
        raise InputError(f"{name}: 'camera_matrix' needs 3x3 finite numbers with positive focal lengths "
                         f"(fx, fy), got {shown(data.get('camera_matrix'))}: {again}")
    dist = _json_numbers(data.get("dist_coeffs"))
    if dist is None or len(dist) not in DIST_COEFF_COUNTS or not all(math.isfinite(v) for v in dist):
        raise InputError(f"{name}: 'dist_coeffs' needs {', '.join(map(str, DIST_COEFF_COUNTS))} finite "
                         f"numbers, got {shown(data.get('dist_coeffs'))}: {again}")
    if camera[6:] != [0.0, 0.0, 1.0]:
        raise InputError(f"{name}: 'camera_matrix' has the last row {shown(camera[6:])}, a camera matrix's is "
                         f"[0, 0, 1]: {again}")
    cleaned = {**data, "camera_matrix": np.reshape(camera, (3, 3)).tolist(), "dist_coeffs": dist}
    if "image_size" in data:
        size = _json_numbers(data["image_size"])
        if size is None or len(size) != 2 or not all(0 < v < math.inf and v == int(v) for v in size):
            raise InputError(f"{name}: 'image_size' needs [width, height] in pixels (two positive integers), "
                             f"got {shown(data['image_size'])}: {again}")
        cleaned["image_size"] = [int(v) for v in size]
    rms = json_number(data.get("rms_px"))
    cleaned["rms_px"] = rms if rms is not None and math.isfinite(rms) else None  # only reported
    return cleaned


# A focal length (px) outside these multiples of the frame's diagonal is no lens on that sensor:
# 0.1x is a fisheye far beyond 180 degrees, 100x a telescope's 0.6 degree field.
FOCAL_PER_DIAGONAL = (0.1, 100.0)
# Raw pixels on the frame's border, undistorted and distorted again, must land this close to
# where they started: the scale points and the mask are carried through this inversion.
ROUND_TRIP_PX = 0.05
# The radial distortion's factor (distorted over ideal radius) stays within this either way over
# the frame: the widest rectilinear lenses calibrated with OpenCV's model reach about 0.6 at the
# corners; beyond 3 the undistorted image squeezes or stretches the frame's content out of view.
MAX_RADIAL_SCALE = 3.0


def check_fits_frame(camera: np.ndarray, dist: np.ndarray, frame_size: tuple[int, int],
                     name: str = "calibration") -> None:
    """Refuse a calibration that cannot belong to frames of ``frame_size`` (the calibrated
    sensor's ``(width, height)``): its principal point outside them, a focal length no lens
    has on them, or a distortion OpenCV's model cannot invert over them (a raw pixel of the
    frame's border that does not come back from undistortion and distortion, a radial term
    that folds back within the frame, so that two points of the scene land on one pixel, or
    one that scales the frame's edge beyond :data:`MAX_RADIAL_SCALE`).

    Another camera's intrinsics on a smaller video read the scale wrong by tens of per cent and
    move every undistorted pixel: a number that looks right and is not.
    """
    width, height = frame_size
    fx, fy, cx, cy = camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2]
    other = "the calibration is for another camera or image size: calibrate at the video's resolution"
    if not (0 <= cx <= width and 0 <= cy <= height):
        raise InputError(f"{name}: its principal point ({cx:.6g}, {cy:.6g}) lies outside the {width}x{height} "
                         f"frame: {other} (a cropped recording: pass --video-origin)")
    diagonal = math.hypot(width, height)
    low, high = (k * diagonal for k in FOCAL_PER_DIAGONAL)
    if not (low <= fx <= high and low <= fy <= high):
        raise InputError(f"{name}: its focal length (fx {fx:.6g}, fy {fy:.6g} px) is not between "
                         f"{FOCAL_PER_DIAGONAL[0]:g}x and {FOCAL_PER_DIAGONAL[1]:g}x the {width}x{height} frame's "
                         f"diagonal ({low:.3g}-{high:.3g} px): {other}")
    points = _border_points(frame_size)
    rays = _undistorted_rays(camera, dist, points)
    worst = _round_trip_px(camera, dist, points, rays)
    radial = _radial_problem(camera, dist, frame_size, rays)
    if not worst <= ROUND_TRIP_PX or radial:
        why = radial or f"a pixel of the frame's border comes back {worst:.3g} px away from undistortion"
        raise InputError(f"{name}: its distortion {shown([round(float(v), 6) for v in dist])} is beyond what "
                         f"OpenCV's model inverts over the {width}x{height} frame ({why}): {other}, or calibrate again with views "
                         "that reach the frame's corners")


def _border_points(frame_size: tuple[int, int], per_side: int = 33) -> np.ndarray:
    """Points along the frame's four edges and a coarse grid inside, ``(N, 2)`` raw pixels."""
    width, height = frame_size
    xs = np.linspace(0.0, width - 1.0, per_side)
    ys = np.linspace(0.0, height - 1.0, per_side)
    grid = np.stack(np.meshgrid(xs[::4], ys[::4]), axis=-1).reshape(-1, 2)
    edges = [np.c_[xs, np.zeros_like(xs)], np.c_[xs, np.full_like(xs, height - 1.0)],
             np.c_[np.zeros_like(ys), ys], np.c_[np.full_like(ys, width - 1.0), ys]]
    return np.vstack([*edges, grid])


def _undistorted_rays(camera: np.ndarray, dist: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Raw pixels ``(N, 2)`` undistorted as :func:`undistort_points` does it, in normalised
    image coordinates (focal lengths from the principal point)."""
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    rays = cv2.undistortPoints(points.reshape(-1, 1, 2), camera, dist, None, None, None, criteria)
    return rays.reshape(-1, 2)


def _round_trip_px(camera: np.ndarray, dist: np.ndarray, points: np.ndarray, rays: np.ndarray) -> float:
    """The largest distance (px) between ``points`` and their undistorted ``rays`` distorted
    again; inf where the inversion gave no finite point."""
    if not np.isfinite(rays).all():
        return math.inf
    back, _ = cv2.projectPoints(np.c_[rays, np.ones(len(rays))], np.zeros(3), np.zeros(3), camera, dist)
    error = np.hypot(*(back.reshape(-1, 2) - points).T)
    return float(error.max()) if np.isfinite(error).all() else math.inf


def _radial_problem(camera: np.ndarray, dist: np.ndarray, frame_size: tuple[int, int],
                    rays: np.ndarray) -> str | None:
    """What is wrong with the radial distortion within the radius the frame reaches, or None:
    it stops growing with the radius (it folds: two radii land on one), or it scales a radius by
    more than :data:`MAX_RADIAL_SCALE` either way (no rectilinear lens that OpenCV's model
    describes does; a fisheye needs its own model).

    That radius is the larger of the undistorted frame's corners (what the undistorted image
    shows) and the raw border's points once undistorted (a barrel-distorted frame's lie further
    out)."""
    width, height = frame_size
    corners = np.array([[0.0, 0.0], [width, 0.0], [0.0, height], [width, height]])
    reach = float(np.max(np.hypot((corners[:, 0] - camera[0, 2]) / camera[0, 0],
                                  (corners[:, 1] - camera[1, 2]) / camera[1, 1])))
    if np.isfinite(rays).all():
        reach = max(reach, float(np.hypot(*rays.T).max()))
    k = np.zeros(6)
    radial = np.r_[dist[:2], dist[4:8]]  # k1 k2 (p1 p2) k3 k4 k5 k6
    k[:radial.size] = radial
    k1, k2, k3, k4, k5, k6 = k
    r = np.linspace(0.0, reach, 2049)[1:]
    r2 = r * r
    denominator = 1 + r2 * (k4 + r2 * (k5 + r2 * k6))
    factor = (1 + r2 * (k1 + r2 * (k2 + r2 * k3))) / np.where(denominator > 0, denominator, np.nan)
    distorted = r * factor
    grows = np.isfinite(distorted) & (np.diff(np.r_[0.0, distorted]) > 0)
    if not grows.all():
        return (f"the radial term folds back within the frame, at {r[~grows][0]:.3g} focal lengths from the "
                "centre")
    worst = float(np.max(np.maximum(factor, 1 / factor)))
    if worst > MAX_RADIAL_SCALE:
        return (f"it scales a radius within the frame by {worst:.3g} against the centre, more than "
                f"{MAX_RADIAL_SCALE:g}x")
    return None


class Undistorter:
    """Undistort ROI crops with the full-sensor camera model.

    The remap tables are computed for the ROI window only: the principal point
    is shifted by the ROI offset, so pixel (u, v) of the output is the ideal
    pinhole pixel (u + roi.x, v + roi.y) of the full sensor.
    """

    def __init__(self, calibration: dict[str, Any], roi: Roi, frame_size: tuple[int, int], *,
                 video_origin: tuple[int, int] = (0, 0), name: str = "calibration") -> None:
        camera = np.asarray(calibration["camera_matrix"], np.float64).reshape(3, 3)
        dist = np.asarray(calibration["dist_coeffs"], np.float64).ravel()
        cal_size = tuple(calibration.get("image_size", frame_size))
        if tuple(cal_size) != tuple(frame_size):
            raise InputError(
                f"{name} is for {cal_size[0]}x{cal_size[1]} images but frames are "
                f"{frame_size[0]}x{frame_size[1]}: calibrate at the video resolution")
        check_fits_frame(camera, dist, frame_size, name)
        shifted = camera.copy()
        shifted[0, 2] -= roi.x
        shifted[1, 2] -= roi.y
        # Same camera matrix for input and output; the input lives in full-sensor pixels,
        # so compute maps in full-sensor coordinates, then express them in ROI pixels.
        map_x, map_y = cv2.initUndistortRectifyMap(camera, dist, None, shifted,
                                                   (roi.width, roi.height), cv2.CV_32FC1)
        self.map_x = map_x - np.float32(roi.x)
        self.map_y = map_y - np.float32(roi.y)
        self.camera = camera
        self.dist = dist
        # Raw video pixels are sensor pixels minus this (a cropped recording, --video-origin).
        self.origin = np.asarray(video_origin, np.float64)

    def __call__(self, grey_roi: np.ndarray) -> np.ndarray:
        return cv2.remap(grey_roi, self.map_x, self.map_y, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)

    def map_mask(self, mask_roi: np.ndarray) -> np.ndarray:
        """Carry a mask drawn on the raw (distorted) ROI into the undistorted ROI.

        Each undistorted pixel takes the mask value at its raw source position
        (bilinear, threshold 1/2); where that lies outside the ROI crop it is off.
        """
        moved = cv2.remap(mask_roi.astype(np.uint8) * np.uint8(255), self.map_x, self.map_y,
                          cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
        return moved > 127

    def undistort_points(self, points_xy: np.ndarray) -> np.ndarray:
        """Raw video pixel ``(x, y)`` points to undistorted sensor pixels."""
        return undistort_points(points_xy, self.camera, self.dist, self.origin)


def undistort_points(points_xy: np.ndarray, camera_matrix: Any, dist_coeffs: Any,
                     video_origin: Any = (0, 0)) -> np.ndarray:
    """Raw video pixel ``(x, y)`` points to undistorted sensor pixels.

    ``video_origin``: the sensor pixel of the video's pixel (0, 0) (a cropped recording).
    """
    camera = np.asarray(camera_matrix, np.float64).reshape(3, 3)
    points = (np.asarray(points_xy, np.float64).reshape(-1, 2) + np.asarray(video_origin, np.float64))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-10)
    ideal = cv2.undistortPoints(points.reshape(-1, 1, 2), camera, np.asarray(dist_coeffs, np.float64),
                                None, None, camera, criteria)
    return ideal.reshape(-1, 2)


def point_undistorter(calibration: dict[str, Any] | None) -> Callable[[np.ndarray], np.ndarray] | None:
    """Raw video pixels to undistorted sensor pixels for a calibration dict holding
    ``camera_matrix``, ``dist_coeffs`` and optionally ``video_origin`` (None: no calibration)."""
    if calibration is None:
        return None
    camera, dist = calibration["camera_matrix"], calibration["dist_coeffs"]
    origin = tuple(calibration.get("video_origin") or (0, 0))

    def undistort(points_xy: np.ndarray) -> np.ndarray:
        return undistort_points(points_xy, camera, dist, origin)

    return undistort


def scale_from_known_length(length_mm: float, between: str,
                            undistort_points: Callable[[np.ndarray], np.ndarray] | None = None, *,
                            frame_size: tuple[int, int] | None = None) -> float:
    """mm per pixel from a known length between two image points ``X1,Y1,X2,Y2``.

    The points are raw video pixels; with ``undistort_points`` (a calibration's
    :meth:`Undistorter.undistort_points`) their distance is measured in the
    undistorted image, whose pixels the displacement is measured in.
    """
    if not (math.isfinite(length_mm) and length_mm > 0):
        raise InputError(f"--known-length {length_mm} is not a finite positive number: pass the length in mm")
    try:
        x1, y1, x2, y2 = (float(v) for v in between.split(","))
    except ValueError:
        raise InputError(f"--between {between!r} is not X1,Y1,X2,Y2 (pixel coordinates)") from None
    if not all(math.isfinite(v) for v in (x1, y1, x2, y2)):
        raise InputError(f"--between {between!r} holds a NaN or infinite coordinate: pass four pixel "
                         "coordinates X1,Y1,X2,Y2")
    if frame_size is not None:
        width, height = frame_size
        if not all(0 <= x <= width and 0 <= y <= height for x, y in ((x1, y1), (x2, y2))):
            raise InputError(f"--between {between!r} lies outside the {width}x{height} video frame: "
                             "click both points on the frame (raw video pixels)")
    if undistort_points is not None:
        (x1, y1), (x2, y2) = undistort_points(np.array([[x1, y1], [x2, y2]]))
    distance_px = math.hypot(x2 - x1, y2 - y1)
    if distance_px <= 0:
        raise InputError(f"--between {between!r}: the two points coincide; pick two distinct points")
    return length_mm / distance_px
