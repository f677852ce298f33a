"""The reference-frame driver (paper section 3.5) and its sparse counterpart.

Dense methods: every frame is compared with the one fixed reference frame, so
frames are independent (``jobs`` threads work on them at once) and tracking
resumes by itself after an occlusion. The driver keeps only the small ``(F, P)``
per-POI tracks and filters them at the end (eq. 10-12 need the whole series).

Sparse methods (KLT) follow their own features through the sequence in order.
"""

from __future__ import annotations

import sys
import threading
import time
import warnings
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from flow.filtering import FilterResult, filter_and_average
from flow.io import FrameSource, InputError


@dataclass
class Tracks:
    """Raw per-POI measurement of a run, before filtering."""

    frame: np.ndarray  # (F,) int
    time_s: np.ndarray  # (F,)
    dx: np.ndarray  # (F, P) float32, px, NaN where unknown
    dy: np.ndarray
    residual: np.ndarray  # (F,) mean |I_cur(x + d) - I_ref(x)| over POIs, grey levels
    x_px: np.ndarray  # (P,) POI / feature positions in the reference (ROI pixels)
    y_px: np.ndarray
    reference_row: int
    timings_s: dict[str, float] = field(default_factory=dict)
    truncated: bool = False
    header_frames: int = 0


@dataclass
class Measurement:
    """Filtered, averaged displacement with quality flags."""

    tracks: Tracks
    filtered: FilterResult
    valid: np.ndarray  # (F,) bool
    poi_kept_frac: np.ndarray  # (F,)
    flow_spread_px: np.ndarray  # (F,) robust spread of the kept POIs' displacement
    residual_threshold: float


def _sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at float positions (NaN outside the image)."""
    height, width = image.shape
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    inside = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= width - 1) & (y <= height - 1)
    xc = np.clip(np.where(inside, x, 0.0), 0, width - 1)
    yc = np.clip(np.where(inside, y, 0.0), 0, height - 1)
    x0 = np.minimum(xc.astype(np.intp), max(width - 2, 0))
    y0 = np.minimum(yc.astype(np.intp), max(height - 2, 0))
    fx, fy = xc - x0, yc - y0
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    img = image.astype(np.float32, copy=False)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, np.nan).astype(np.float32)


def _residual(reference_values: np.ndarray, current: np.ndarray, x: np.ndarray, y: np.ndarray,
              dx: np.ndarray, dy: np.ndarray) -> float:
    warped = _sample(current, x + dx, y + dy)
    diff = np.abs(warped - reference_values)
    diff = diff[np.isfinite(diff)]
    return float(diff.mean()) if diff.size else float("nan")


def _frames(source: FrameSource, max_frames: int | None,
            undistort: Callable[[np.ndarray], np.ndarray] | None) -> Iterator[tuple[int, float, np.ndarray]]:
    for index, time_s, grey in source:
        if max_frames is not None and index >= max_frames:
            break
        yield index, time_s, (undistort(grey) if undistort is not None else grey)


def read_reference(source: FrameSource, reference_frame: int,
                   undistort: Callable[[np.ndarray], np.ndarray] | None = None) -> np.ndarray:
    """Grey (undistorted) ROI of frame ``reference_frame``."""
    if reference_frame < 0:
        raise InputError(f"--reference-frame {reference_frame} is negative: pass a frame index >= 0")
    for index, _, grey in _frames(source, None, undistort):
        if index == reference_frame:
            return grey
    raise InputError(f"--reference-frame {reference_frame} is beyond the {source.frames_read} "
                     "decodable frames: pick an earlier frame")


def _progress(source: FrameSource, max_frames: int | None, show: bool) -> tqdm:
    total = source.header_frames or None
    if max_frames is not None:
        total = min(total, max_frames) if total else max_frames
    return tqdm(total=total, unit="frame", file=sys.stderr, disable=not show, leave=False)


def track_dense(source: FrameSource, factory: Callable[[], Any], poi_xy: np.ndarray, *,
                reference_frame: int = 0, jobs: int = 1, max_frames: int | None = None,
                undistort: Callable[[np.ndarray], np.ndarray] | None = None,
                progress: bool = False) -> Tracks:
    """Run a dense method of ``factory()`` on every frame against the reference frame.

    ``factory`` builds a method instance; each worker thread gets its own (OpenCV
    flow objects are not thread-safe), and OpenCV releases the GIL while it computes.
    """
    if jobs < 1:
        raise InputError(f"--jobs {jobs} must be >= 1")
    t0 = time.perf_counter()
    reference = read_reference(source, reference_frame, undistort)
    xs = poi_xy[:, 0].astype(np.float32)
    ys = poi_xy[:, 1].astype(np.float32)
    ref_values = reference[poi_xy[:, 1], poi_xy[:, 0]].astype(np.float32)
    local = threading.local()

    def measure(current: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        method = getattr(local, "method", None)
        if method is None:
            method = local.method = factory()
        flow = method.calc(reference, current)
        dx = flow[poi_xy[:, 1], poi_xy[:, 0], 0].astype(np.float32)
        dy = flow[poi_xy[:, 1], poi_xy[:, 0], 1].astype(np.float32)
        return dx, dy, _residual(ref_values, current, xs, ys, dx, dy)

    frames: list[int] = []
    times: list[float] = []
    rows_x: list[np.ndarray] = []
    rows_y: list[np.ndarray] = []
    residuals: list[float] = []

    def collect(index: int, time_s: float, result: tuple[np.ndarray, np.ndarray, float]) -> None:
        frames.append(index)
        times.append(time_s)
        rows_x.append(result[0])
        rows_y.append(result[1])
        residuals.append(result[2])
        bar.update(1)

    t1 = time.perf_counter()
    bar = _progress(source, max_frames, progress)
    threads_before = cv2.getNumThreads()
    try:
        if jobs == 1:
            for index, time_s, grey in _frames(source, max_frames, undistort):
                collect(index, time_s, measure(grey))
        else:
            # One OpenCV thread per job avoids oversubscribing the cores; a bounded queue keeps
            # memory constant and results in frame order.
            cv2.setNumThreads(1)
            with ThreadPoolExecutor(max_workers=jobs) as pool:
                pending: deque = deque()
                for index, time_s, grey in _frames(source, max_frames, undistort):
                    pending.append((index, time_s, pool.submit(measure, grey)))
                    if len(pending) >= 2 * jobs:
                        i, t, fut = pending.popleft()
                        collect(i, t, fut.result())
                while pending:
                    i, t, fut = pending.popleft()
                    collect(i, t, fut.result())
    finally:
        cv2.setNumThreads(threads_before)
        bar.close()
    t2 = time.perf_counter()
    if not frames:
        raise InputError("no frame to measure: the video is empty or --max-frames is 0")
    reference_row = frames.index(reference_frame) if reference_frame in frames else 0
    return Tracks(np.asarray(frames), np.asarray(times), np.vstack(rows_x), np.vstack(rows_y),
                  np.asarray(residuals), xs, ys, reference_row,
                  {"setup_s": t1 - t0, "frames_s": t2 - t1, "frames_per_s": len(frames) / max(t2 - t1, 1e-9)},
                  source.truncated, source.header_frames)


def track_sparse(source: FrameSource, method: Any, mask: np.ndarray | None, *,
                 reference_frame: int = 0, max_frames: int | None = None,
                 undistort: Callable[[np.ndarray], np.ndarray] | None = None,
                 progress: bool = False) -> Tracks:
    """Run a sparse method: detect features in the reference, follow them frame by frame.

    Frames before the reference frame cannot be reached by a forward tracker; they are
    reported as unknown (NaN).
    """
    t0 = time.perf_counter()
    reference = read_reference(source, reference_frame, undistort)
    points = method.start(reference, mask)
    if len(points) == 0:
        raise InputError("no corner feature found in the ROI of the reference frame: "
                         "the sparse method cannot track; use a dense method or a larger --roi")
    xs, ys = points[:, 0], points[:, 1]
    ref_values = _sample(reference, xs, ys)
    frames, times, rows_x, rows_y, residuals = [], [], [], [], []
    t1 = time.perf_counter()
    bar = _progress(source, max_frames, progress)
    try:
        for index, time_s, grey in _frames(source, max_frames, undistort):
            if index < reference_frame:
                d = np.full((len(points), 2), np.nan, np.float32)
                res = float("nan")
            else:
                d = method.step(reference if index == reference_frame else grey)
                res = _residual(ref_values, grey, xs, ys, d[:, 0], d[:, 1])
            frames.append(index)
            times.append(time_s)
            rows_x.append(d[:, 0])
            rows_y.append(d[:, 1])
            residuals.append(res)
            bar.update(1)
    finally:
        bar.close()
    t2 = time.perf_counter()
    if not frames:
        raise InputError("no frame to measure: the video is empty or --max-frames is 0")
    return Tracks(np.asarray(frames), np.asarray(times), np.vstack(rows_x), np.vstack(rows_y),
                  np.asarray(residuals), xs.astype(np.float32), ys.astype(np.float32),
                  frames.index(reference_frame) if reference_frame in frames else 0,
                  {"setup_s": t1 - t0, "frames_s": t2 - t1, "frames_per_s": len(frames) / max(t2 - t1, 1e-9)},
                  source.truncated, source.header_frames)


def flag_invalid(residual: np.ndarray, *, k_mad: float = 8.0, ratio: float = 2.5,
                 floor: float = 3.0) -> tuple[np.ndarray, float]:
    """Frames whose photometric residual is far above its robust baseline (view blocked).

    A frame is invalid when its residual exceeds ``max(median + k_mad * sigma,
    ratio * median, floor)`` with ``sigma = 1.4826 * MAD`` over all frames, or is NaN.
    Returns ``(valid, threshold)``.
    """
    residual = np.asarray(residual, float)
    finite = residual[np.isfinite(residual)]
    if finite.size == 0:
        return np.zeros(residual.shape, bool), float("nan")
    median = float(np.median(finite))
    sigma = 1.4826 * float(np.median(np.abs(finite - median)))
    threshold = max(median + k_mad * sigma, ratio * median, floor)
    return np.isfinite(residual) & (residual <= threshold), threshold


def poi_spread(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Per frame, the robust spread (px) of the POI displacements: 1.4826 x MAD, x and y combined.

    POIs on one structural member move almost alike; an occluder, a lost view
    or a failed flow scatters them.
    """
    spread = np.full(dx.shape[0], np.nan)
    if dx.shape[1] == 0:
        return spread
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        mad_x = np.nanmedian(np.abs(dx - np.nanmedian(dx, axis=1, keepdims=True)), axis=1)
        mad_y = np.nanmedian(np.abs(dy - np.nanmedian(dy, axis=1, keepdims=True)), axis=1)
    return 1.4826 * np.hypot(mad_x, mad_y)


def flag_incoherent(spread: np.ndarray, *, ratio: float = 4.0, floor_px: float = 1.5) -> np.ndarray:
    """Frames whose POIs disagree far more than usual: ``spread > max(ratio * median, floor_px)``.

    Catches an occluder whose brightness happens to match the structure's
    (the photometric residual then stays low while the flow is garbage).
    NaN spread (no POI measured) counts as coherent here; ``all_nan`` handles it.
    """
    finite = spread[np.isfinite(spread)]
    if finite.size == 0:
        return np.zeros(spread.shape, bool)
    threshold = max(ratio * float(np.median(finite)), floor_px)
    return np.isfinite(spread) & (spread > threshold)


def measure(tracks: Tracks, *, filter_enabled: bool = True, average: str = "mean",
            threshold_ratio: float = 0.5, threshold_px: float | None = None,
            mcr_threshold: float = 0.5, residual_ratio: float = 2.5,
            residual_k_mad: float = 8.0, residual_floor: float = 3.0,
            spread_ratio: float = 4.0, spread_floor_px: float = 1.5,
            check_coherence: bool = True) -> Measurement:
    """Quality flags, eq. (10)-(12) filtering and averaging of a run's tracks.

    A frame is invalid when its photometric residual is far above its baseline
    (:func:`flag_invalid`), when no POI was measured, or, with
    ``check_coherence``, when its POIs scatter far more than usual
    (:func:`flag_incoherent`).
    """
    valid, threshold = flag_invalid(tracks.residual, k_mad=residual_k_mad, ratio=residual_ratio,
                                    floor=residual_floor)
    all_nan = ~np.isfinite(tracks.dx).any(axis=1)
    valid &= ~all_nan
    if check_coherence:
        valid &= ~flag_incoherent(poi_spread(tracks.dx, tracks.dy), ratio=spread_ratio,
                                  floor_px=spread_floor_px)
    filtered = filter_and_average(tracks.dx, tracks.dy, valid=valid, reference_row=tracks.reference_row,
                                  threshold_ratio=threshold_ratio, threshold_px=threshold_px,
                                  mcr_threshold=mcr_threshold, average=average, enabled=filter_enabled)
    n_points = tracks.dx.shape[1]
    kept = filtered.kept
    finite = np.isfinite(tracks.dx[:, kept])
    poi_kept_frac = finite.sum(axis=1) / max(n_points, 1)
    spread = poi_spread(tracks.dx[:, kept], tracks.dy[:, kept])
    return Measurement(tracks, filtered, valid, poi_kept_frac, spread, threshold)


def iter_rows(result: Measurement, mm_per_px: float) -> Iterable[dict[str, Any]]:
    """CSV rows; invalid frames report NaN displacement instead of a fake motion."""
    tr = result.tracks
    for i in range(len(tr.frame)):
        ok = bool(result.valid[i])
        dx = float(result.filtered.dx[i]) if ok else float("nan")
        dy = float(result.filtered.dy[i]) if ok else float("nan")
        yield {"frame": int(tr.frame[i]), "time_s": float(tr.time_s[i]), "dx_px": dx, "dy_px": dy,
               "dx_mm": dx * mm_per_px, "dy_mm": dy * mm_per_px, "valid": int(ok),
               "poi_kept_frac": float(result.poi_kept_frac[i]), "residual": float(tr.residual[i]),
               "flow_spread_px": float(result.flow_spread_px[i])}
