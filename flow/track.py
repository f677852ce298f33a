"""The reference-frame driver (paper section 3.5) and its sparse counterpart.

Dense methods: every frame is compared with the one fixed reference frame, so
frames are independent (``jobs`` threads work on them at once), a run can be
split into frame ranges measured separately and merged, and tracking resumes
by itself after an occlusion. Sparse methods (KLT) follow their own features
through the sequence in order.

Memory stays constant whatever the clip length: frames are streamed, and the
per-POI tracks (``frames x POIs``, which eq. 10-12 need whole) go to a
disk-backed :class:`PoiStore` and are read back in blocks of frames.
"""

from __future__ import annotations

import hashlib
import json
import os
import queue
import sys
import tempfile
import time
import warnings
import zipfile
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from flow.background import Background
from flow.filtering import (
    MCR_THRESHOLD,
    THRESHOLD_RATIO,
    FilterResult,
    block_rows,
    filter_and_average,
    reference_offset,
    row_blocks,
)
from flow.io import FrameSource, InputError
from flow.robust import MAD_TO_SIGMA

Undistort = Callable[[np.ndarray], np.ndarray] | None


class DiskMatrix:
    """A read-only ``(frames, points)`` float32 matrix in a file, read a block of rows at a time.

    Rows are read with ``pread`` rather than memory-mapped: pages of a mapped
    file count as the process's resident memory while they stay cached, so a
    mapping would look (to ``top``, to a scheduler's memory limit) as if the
    whole matrix were in memory. Indexing supports what the filters need:
    ``m[i]``, ``m[a:b]``, ``m[rows, columns]``; ``np.asarray(m)`` reads it all.
    """

    dtype = np.dtype(np.float32)
    ndim = 2

    def __init__(self, handle: Any, shape: tuple[int, int]) -> None:
        self._handle = handle
        self.shape = (int(shape[0]), int(shape[1]))

    def __len__(self) -> int:
        return self.shape[0]

    def _rows(self, start: int, stop: int) -> np.ndarray:
        n_points = self.shape[1]
        count = max(stop - start, 0)
        data = os.pread(self._handle.fileno(), count * n_points * 4, start * n_points * 4)
        return np.frombuffer(data, np.float32).reshape(count, n_points)

    def __getitem__(self, key: Any) -> np.ndarray:
        rest: tuple = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, (int, np.integer)):
            index = int(key) + (self.shape[0] if key < 0 else 0)
            if not 0 <= index < self.shape[0]:
                raise IndexError(f"row {key} out of range for {self.shape[0]} rows")
            return self._rows(index, index + 1)[(0, *rest)]
        if isinstance(key, slice):
            start, stop, step = key.indices(self.shape[0])
            return self._rows(start, max(stop, start))[(slice(None, None, step), *rest)]
        raise TypeError(f"DiskMatrix rows take an int or a slice, not {type(key).__name__}")

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = self._rows(0, self.shape[0])
        return whole if dtype is None else whole.astype(dtype)

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None:
            handle.close()


class ColumnView:
    """A column subset of a ``(frames, points)`` matrix (array or :class:`DiskMatrix`), indexed
    by rows like the matrix: what one region's POIs read of a run's tracks."""

    dtype = np.dtype(np.float32)
    ndim = 2

    def __init__(self, matrix: Any, columns: np.ndarray) -> None:
        self._matrix = matrix
        self._columns = np.asarray(columns, np.intp)
        self.shape = (int(matrix.shape[0]), int(self._columns.size))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: Any) -> np.ndarray:
        """Rows ``m[i]`` or ``m[a:b]`` of the matrix, this view's columns only."""
        return np.asarray(self._matrix[key])[..., self._columns]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = np.asarray(self._matrix[0:self.shape[0]])[:, self._columns]
        return whole if dtype is None else whole.astype(dtype)


class PoiStore:
    """Per-POI displacement rows, appended frame by frame to disk, read back as :class:`DiskMatrix`.

    Two unlinked temporary files (dx, dy) hold ``float32`` rows of ``n_points``;
    the operating system deletes them when the run ends, however it ends.
    ``directory`` should be on a real disk (``/tmp`` may be memory-backed):
    the CLI puts it beside the output.
    """

    def __init__(self, n_points: int, *, directory: str | Path | None = None) -> None:
        self.n_points = int(n_points)
        self.n_frames = 0
        self._files = [tempfile.TemporaryFile(prefix=".refflow-poi-", dir=directory) for _ in range(2)]

    def append(self, dx: np.ndarray, dy: np.ndarray) -> None:
        self.extend(np.asarray(dx)[None], np.asarray(dy)[None])

    def extend(self, dx: np.ndarray, dy: np.ndarray) -> None:
        """Append a block of rows ``(n, n_points)``."""
        for handle, rows in zip(self._files, (dx, dy), strict=True):
            handle.write(np.ascontiguousarray(rows, np.float32).tobytes())
        self.n_frames += len(dx)

    def arrays(self) -> tuple[DiskMatrix, DiskMatrix]:
        """Finish the store: its rows as read-only ``(n_frames, n_points)`` matrices (they own the files)."""
        for handle in self._files:
            handle.flush()
        matrices = tuple(DiskMatrix(handle, (self.n_frames, self.n_points)) for handle in self._files)
        self._files = []
        return matrices  # type: ignore[return-value]

    def __del__(self) -> None:
        # A run that fails half-way drops its store unfinished.
        for handle in getattr(self, "_files", []):
            handle.close()


def write_npz(path: str | Path, arrays: dict[str, Any], *, compress: bool = False) -> None:
    """Write arrays as an ``.npz`` that ``np.load`` reads; :class:`DiskMatrix` members are streamed.

    ``np.savez`` would first read a disk matrix whole into memory.
    """
    compression = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=compression, allowZip64=True) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                if isinstance(value, DiskMatrix):
                    header = {"descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False,
                              "shape": value.shape}
                    np.lib.format.write_array_header_2_0(member, header)
                    for rows in block_rows(*value.shape):
                        member.write(value[rows].tobytes())
                else:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)


@dataclass
class Tracks:
    """Raw per-POI measurement of a run (or of a range of its frames), before filtering."""

    frame: np.ndarray  # (F,) int
    time_s: np.ndarray  # (F,)
    dx: Any  # (F, P) float32 (a DiskMatrix or an array), px, NaN where unknown
    dy: Any
    residual: np.ndarray  # (F,) mean |I_cur(x + d) - I_ref(x)| over POIs, grey levels
    x_px: np.ndarray  # (P,) POI / feature positions in the reference (ROI pixels)
    y_px: np.ndarray
    reference_frame: int
    # The method's own output at the reference frame (ideally zero), removed by the
    # filtering as the paper's offset; kept here so a range without the reference frame
    # is filtered exactly like the whole run.
    offset_dx: np.ndarray  # (P,) float64
    offset_dy: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    truncated: bool = False
    header_frames: int = 0
    reference_digest: str = ""  # hash of the reference image the run compared against
    # The camera's own image motion at the POIs' centroid (--background-mask), already
    # taken out of dx, dy; None without a background.
    camera_dx: np.ndarray | None = None  # (F,) px
    camera_dy: np.ndarray | None = None
    # Standard uncertainty of the frame's mean displacement over the POIs (px); None:
    # estimated from the kept POIs' spread when measured (sparse methods).
    sigma_dx: np.ndarray | None = None  # (F,) px
    sigma_dy: np.ndarray | None = None
    # Regions (a labelled mask): each POI's label; None for one region. With regions, the
    # per-frame values above (residual, camera, sigma) are (F, R), one column per label in
    # ascending order, each over (or at the centroid of) that region's POIs.
    region: np.ndarray | None = None  # (P,) int

    def labels(self) -> list[int]:
        """The regions' labels, ascending ([1] for a run of one region)."""
        return [1] if self.region is None else [int(v) for v in np.unique(self.region)]

    def select(self, label: int) -> Tracks:
        """The tracks of one region's POIs, as a run of that region alone would give them."""
        if self.region is None:
            if label != 1:
                raise ValueError(f"no region {label}: the run has one region (1)")
            return self
        labels = self.labels()
        if label not in labels:
            raise ValueError(f"no region {label}: the run's regions are {labels}")
        k = labels.index(label)
        columns = np.flatnonzero(self.region == label)

        def column(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else np.asarray(values)[:, k]

        return replace(self, dx=ColumnView(self.dx, columns), dy=ColumnView(self.dy, columns),
                       residual=column(self.residual), x_px=self.x_px[columns], y_px=self.y_px[columns],
                       offset_dx=self.offset_dx[columns], offset_dy=self.offset_dy[columns],
                       camera_dx=column(self.camera_dx), camera_dy=column(self.camera_dy),
                       sigma_dx=column(self.sigma_dx), sigma_dy=column(self.sigma_dy), region=None)


@dataclass
class Measurement:
    """Filtered, averaged displacement with quality flags."""

    tracks: Tracks
    filtered: FilterResult
    valid: np.ndarray  # (F,) bool
    poi_kept_frac: np.ndarray  # (F,) see :func:`consistent_fraction`
    flow_spread_px: np.ndarray  # (F,) robust spread of the kept POIs' displacement
    residual_threshold: float
    consistency_band_px: float = float("nan")
    sigma_dx: np.ndarray | None = None  # (F,) px, standard uncertainty of dx
    sigma_dy: np.ndarray | None = None


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


def _mean_abs(error: np.ndarray) -> float:
    """Mean |error| over its finite values (NaN where none is): a photometric residual."""
    diff = np.abs(error)
    diff = diff[np.isfinite(diff)]
    return float(diff.mean()) if diff.size else float("nan")


def _residual(reference_values: np.ndarray, current: np.ndarray, x: np.ndarray, y: np.ndarray,
              dx: np.ndarray, dy: np.ndarray) -> float:
    return _mean_abs(_sample(current, x + dx, y + dy) - reference_values)


def _frames(source: FrameSource, start: int, stop: int | None,
            undistort: Undistort) -> Iterator[tuple[int, float, np.ndarray]]:
    for index, time_s, grey in source.frames(start, stop):
        yield index, time_s, (undistort(grey) if undistort is not None else grey)


def _stop(max_frames: int | None, frames: tuple[int, int | None] | None) -> tuple[int, int | None]:
    start, stop = frames if frames is not None else (0, None)
    if max_frames is not None:
        stop = max_frames if stop is None else min(stop, max_frames)
    return start, stop


def read_reference(source: FrameSource, reference_frame: int, undistort: Undistort = None,
                   average: int = 1) -> np.ndarray:
    """Grey (undistorted) ROI of frame ``reference_frame``, or the mean of ``average``
    frames from it (rounded to the frames' dtype).

    Why average: a phone video starts with a key frame (I-frame); the codec rebuilds
    low-texture surfaces a little differently in the predicted frames that follow, and a
    reference-frame method reads that as a sub-pixel shift (0.1-0.7 px on the simulated
    wall and beam). The mean of the frames while the structure is at rest is a
    reference like the frames it is compared with, and less noisy.
    """
    if reference_frame < 0:
        raise InputError(f"--reference-frame {reference_frame} is negative: pass a frame index >= 0")
    if average < 1:
        raise InputError(f"--reference-average {average} must be >= 1")
    total, count, dtype = None, 0, None
    for _, _, grey in _frames(source, reference_frame, reference_frame + average, undistort):
        total = grey.astype(np.float64) if total is None else total + grey
        count, dtype = count + 1, grey.dtype
    if count == 0:
        raise InputError(f"--reference-frame {reference_frame} is beyond the {source.frames_read} "
                         "decodable frames: pick an earlier frame")
    if count < average:
        raise InputError(f"--reference-average {average} needs frames {reference_frame}.."
                         f"{reference_frame + average - 1}, the video ends after {count} of them: "
                         "average fewer frames")
    if average == 1:
        return total.astype(dtype)
    mean = total / count
    return np.rint(mean).astype(dtype) if np.issubdtype(dtype, np.integer) else mean.astype(dtype)


def _progress(source: FrameSource, start: int, stop: int | None, show: bool) -> tqdm:
    total = source.header_frames or None
    if stop is not None:
        total = min(total, stop) if total else stop
    if total is not None:
        total = max(total - start, 0)
    return tqdm(total=total, unit="frame", file=sys.stderr, disable=not show, leave=False)


def image_digest(image: np.ndarray) -> str:
    """Short hash of an image's pixels (tells whether two runs share a reference frame)."""
    return hashlib.sha256(np.ascontiguousarray(image).tobytes()).hexdigest()[:16]


# Counters a chaining method keeps (see track_dense), reported with the timings.
CHAIN_COUNTS = ("full_frames", "warm_frames")


def _timings(t0: float, t1: float, t2: float, n_frames: int) -> dict[str, float]:
    # frames_s times the frame loop only: reading the reference and building the
    # methods (setup_s) are not frame processing.
    return {"setup_s": t1 - t0, "frames_s": t2 - t1, "frames_per_s": n_frames / max(t2 - t1, 1e-9)}


def _no_frames(source: FrameSource, start: int, stop: int | None) -> InputError:
    if start > 0 or stop is not None:
        return InputError(f"no frame to measure in frames {start}:{'' if stop is None else stop}: "
                          f"the video has {source.frames_read} decodable frames; pick a range inside it")
    return InputError("no frame to measure: the video is empty")


class _LucasKanadeSigma:
    """Standard uncertainty of a mean displacement over the POIs from the photometric residual.

    The least-squares translation of the POIs has covariance ``s^2 (sum g g^T)^-1``
    (``g`` the reference's gradients, ``s^2`` the residual variance), for independent
    pixels; the residuals of a smoothed flow are correlated over neighbouring POIs, so it
    is scaled by their design effect along rows and columns (``1 + 2 sum rho``).
    """

    def __init__(self, reference: np.ndarray, poi_xy: np.ndarray) -> None:
        grey = reference.astype(np.float32)
        gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        cols, rows = poi_xy[:, 0], poi_xy[:, 1]
        g = np.stack([gx[rows, cols], gy[rows, cols]], axis=1).astype(np.float64)
        self._tensor = g.T @ g
        self._x0, self._y0 = int(cols.min()), int(rows.min())
        self._shape = (int(rows.max()) - self._y0 + 1, int(cols.max()) - self._x0 + 1)
        self._rows, self._cols = rows - self._y0, cols - self._x0

    def sigma(self, residual: np.ndarray) -> tuple[float, float]:
        ok = np.isfinite(residual)
        if ok.sum() < 3 or not np.all(np.isfinite(self._tensor)):
            return float("nan"), float("nan")
        r = np.where(ok, residual, 0.0) - residual[ok].mean()
        var = float(np.mean(r[ok] ** 2))
        image = np.full(self._shape, np.nan)
        image[self._rows, self._cols] = np.where(ok, r, np.nan)
        effect = _design_effect(image, var, axis=1) * _design_effect(image, var, axis=0)
        try:
            cov = np.linalg.inv(self._tensor) * var * effect
        except np.linalg.LinAlgError:
            return float("nan"), float("nan")
        return float(np.sqrt(max(cov[0, 0], 0.0))), float(np.sqrt(max(cov[1, 1], 0.0)))


def _design_effect(image: np.ndarray, var: float, *, axis: int, max_lag: int = 32) -> float:
    """``1 + 2 sum rho(lag)`` of an image with NaN holes along one axis, while rho > 0."""
    total = 1.0
    if var <= 0:
        return total
    for lag in range(1, min(max_lag, image.shape[axis] - 1) + 1):
        a = image[:, :-lag] if axis == 1 else image[:-lag]
        b = image[:, lag:] if axis == 1 else image[lag:]
        both = np.isfinite(a) & np.isfinite(b)
        if both.sum() < 10:
            break
        rho = float(np.mean(a[both] * b[both])) / var
        if rho <= 0:
            break
        total += 2.0 * rho
    return total


def track_dense(source: FrameSource, factory: Callable[[], Any], poi_xy: np.ndarray, *,
                reference_frame: int = 0, reference_average: int = 1, jobs: int = 1,
                max_frames: int | None = None,
                frames: tuple[int, int | None] | None = None, undistort: Undistort = None,
                progress: bool = False, store_dir: str | Path | None = None,
                background: Background | None = None, mask: np.ndarray | None = None) -> Tracks:
    """Run a dense method of ``factory()`` on every frame against the reference frame.

    Parameters
    ----------
    source : FrameSource
    factory : callable
        Builds a method instance; ``jobs`` of them are built before the timed frame loop
        and handed out from a pool, one chain of frames (one frame for a method that does
        not chain) at a time, so that no two threads share one (OpenCV flow objects are
        not thread-safe). OpenCV and our numba kernels release the GIL while they compute.
    poi_xy : ndarray, shape (P, 2), int
        POI ``(x, y)`` in ROI pixels.
    reference_frame : int
        Index of the fixed reference frame; it is read from the video even when
        it lies outside ``frames``.
    reference_average : int
        The reference is the mean of this many frames from ``reference_frame``
        (see :func:`read_reference`); its offset (eq. 10) is then the method's
        output for the reference against itself.
    frames : (start, stop), optional
        Measure frames ``start <= index < stop`` only (``stop`` None: to the end).
    max_frames : int, optional
        Stop before frame index ``max_frames``.
    store_dir : path, optional
        Folder of the disk-backed per-POI store (default: the system's temporary folder).
    background : Background, optional
        Static points: the camera motion fitted to their flow is subtracted from
        the POIs' (``Tracks.camera_dx`` records it; the residual stays that of the
        image motion itself).
    mask : ndarray (H, W) bool or int, optional
        The POI mask (default: the POIs' pixels), given to each method's ``bind``. An int
        mask of labels 1..N (0: no POI) with two or more labels at the POIs measures each
        label's POIs as a region of its own (residual, uncertainty and camera motion per
        region; ``Tracks.region``), all from one flow computation per frame.
    """
    if jobs < 1:
        raise InputError(f"--jobs {jobs} must be >= 1")
    start, stop = _stop(max_frames, frames)
    t0 = time.perf_counter()
    reference = read_reference(source, reference_frame, undistort, reference_average)
    columns, rows_ = poi_xy[:, 0], poi_xy[:, 1]
    xs = columns.astype(np.float32)
    ys = rows_.astype(np.float32)
    ref_values = reference[rows_, columns].astype(np.float32)
    if mask is None:
        mask = np.zeros(reference.shape, bool)
        mask[rows_, columns] = True
    region_of = np.asarray(mask)[rows_, columns].astype(np.int64)
    labels = np.unique(region_of)
    if labels.size > 1 and labels[0] <= 0:
        raise ValueError(f"{int(np.sum(region_of <= 0))} POIs lie outside the labelled mask's regions")
    groups = [np.flatnonzero(region_of == label) for label in labels]
    read = None
    if background is not None:
        read = np.zeros(reference.shape, bool)
        read[background.rows, background.columns] = True
    idle: queue.SimpleQueue = queue.SimpleQueue()
    methods = [factory() for _ in range(jobs)]
    for method in methods:
        if hasattr(method, "bind"):
            method.bind(reference, mask, read=read)
        idle.put(method)
    lks = [_LucasKanadeSigma(reference, poi_xy[group]) for group in groups]
    # A method that solves frames from one another (``chain_length`` > 1) gets the frames of
    # one chain, ``(index - reference_frame) // chain_length``, in order on one instance, from
    # a restart: the chains are fixed by the frame index alone, so any --frames part or --jobs
    # count gives the very numbers of one run (a part that starts inside a chain first solves
    # the chain's earlier frames without keeping them). The reference frame begins a chain.
    chain = max(1, int(getattr(methods[0], "chain_length", 0) or 0))

    poi_points = poi_xy.astype(np.float64)
    centroids = np.array([poi_points[group].mean(axis=0) for group in groups])

    def compensate(flow: np.ndarray, dx: np.ndarray, dy: np.ndarray):
        """POI flow minus the camera's motion, and that motion at each region's centroid."""
        if background is None:
            return dx, dy, np.full((len(groups), 2), np.nan)
        bx = flow[background.rows, background.columns, 0]
        by = flow[background.rows, background.columns, 1]
        mx, my = background.motion_at(bx, by, np.vstack([poi_points, centroids]))
        n = len(poi_points)
        return ((dx - mx[:n]).astype(np.float32), (dy - my[:n]).astype(np.float32),
                np.column_stack([mx[n:], my[n:]]).astype(np.float64))

    def measure_frame(method: Any, current: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray,
                                                                 np.ndarray, np.ndarray]:
        """The POIs' displacement, and per region the mean photometric residual, the camera's
        motion and the standard uncertainty of the mean displacement."""
        flow = method.calc(reference, current)
        dx = flow[rows_, columns, 0].astype(np.float32)
        dy = flow[rows_, columns, 1].astype(np.float32)
        error = _sample(current, xs + dx, ys + dy) - ref_values
        own = getattr(method, "last_sigmas_px", None) or {}
        residual = np.array([_mean_abs(error[group]) for group in groups])
        sigma = np.array([own[int(label)] if int(label) in own else lk.sigma(error[group])
                          for label, group, lk in zip(labels, groups, lks, strict=True)], np.float64)
        cdx, cdy, camera = compensate(flow, dx, dy)
        return cdx, cdy, residual, camera, sigma

    def measure_chain(items: list[tuple[int, float, np.ndarray, bool]]) -> list[tuple[int, float, tuple]]:
        """Results of the kept frames of one chain, solved in order on one method instance."""
        method = idle.get()
        try:
            if hasattr(method, "restart"):
                method.restart()
            results = []
            for index, time_s, grey, keep in items:
                result = measure_frame(method, grey)  # a warm-up frame too: the chain needs it
                if keep:
                    results.append((index, time_s, result))
            return results
        finally:
            idle.put(method)

    def chain_of(index: int) -> int:
        return (index - reference_frame) // chain

    def chains() -> Iterator[list[tuple[int, float, np.ndarray, bool]]]:
        first = max(0, reference_frame + chain_of(start) * chain)  # the chain's first frame
        group: list[tuple[int, float, np.ndarray, bool]] = []
        for index, time_s, grey in _frames(source, first, stop, undistort):
            if group and chain_of(index) != chain_of(group[-1][0]):
                yield group
                group = []
            group.append((index, time_s, grey, index >= start))
        if group:
            yield group

    in_range = start <= reference_frame and (stop is None or reference_frame < stop)
    offset = None
    if not in_range or reference_average > 1:
        # The range lacks the reference frame (or the reference is no frame of the video but
        # a mean of frames): measure it against itself, as the frame's own row would have
        # been (the first of its chain), so the offset removed is the same in a whole run and
        # in its parts.
        own_dx, own_dy = measure_chain([(reference_frame, 0.0, reference, True)])[0][2][:2]
        offset = (own_dx.astype(np.float64), own_dy.astype(np.float64))

    store = PoiStore(len(poi_xy), directory=store_dir)
    frame_list: list[int] = []
    times: list[float] = []
    residuals: list[float] = []
    cameras: list[tuple[float, float]] = []
    sigmas: list[tuple[float, float]] = []

    def collect(results: list[tuple[int, float, tuple]]) -> None:
        for index, time_s, result in results:
            frame_list.append(index)
            times.append(time_s)
            store.append(result[0], result[1])
            residuals.append(result[2])
            cameras.append(result[3])
            sigmas.append(result[4])
            bar.update(1)

    t1 = time.perf_counter()
    bar = _progress(source, start, stop, progress)
    threads_before = cv2.getNumThreads()
    try:
        if jobs == 1:
            for group in chains():
                collect(measure_chain(group))
        else:
            # One OpenCV thread per job avoids oversubscribing the cores; a bounded queue (of
            # frames, or of chains of frames) keeps memory bounded and results in frame order.
            cv2.setNumThreads(1)
            bound = 2 * jobs if chain == 1 else jobs + 1
            with ThreadPoolExecutor(max_workers=jobs) as pool:
                pending: deque = deque()
                try:
                    for group in chains():
                        pending.append(pool.submit(measure_chain, group))
                        if len(pending) >= bound:
                            collect(pending.popleft().result())
                    while pending:
                        collect(pending.popleft().result())
                except BaseException:
                    pool.shutdown(wait=True, cancel_futures=True)
                    raise
    finally:
        cv2.setNumThreads(threads_before)
        bar.close()
    t2 = time.perf_counter()
    if not frame_list:
        raise _no_frames(source, start, stop)
    dx, dy = store.arrays()
    frame_index = np.asarray(frame_list)
    if offset is None:
        row = int(np.flatnonzero(frame_index == reference_frame)[0])
        offset = (reference_offset(dx, row), reference_offset(dy, row))
    # (F, R) per-frame values of R regions; (F,) for one region.
    per_region = (lambda values: np.asarray(values, np.float64)) if len(groups) > 1 \
        else (lambda values: np.asarray(values, np.float64)[:, 0])
    camera = np.asarray(cameras, np.float64) if background is not None else None
    sigma = np.asarray(sigmas, np.float64)
    timings = _timings(t0, t1, t2, len(frame_list))
    # Where the time went, for a method that tracks frames from their predecessor: frames it
    # measured in full and frames it tracked (warm-up frames of a part included).
    for key in CHAIN_COUNTS:
        if hasattr(methods[0], key):
            timings[key] = float(sum(getattr(m, key) for m in methods))
    return Tracks(frame_index, np.asarray(times), dx, dy, per_region(residuals), xs, ys,
                  reference_frame, offset[0], offset[1], timings,
                  source.truncated, source.header_frames, image_digest(reference),
                  camera_dx=None if camera is None else per_region(camera[..., 0]),
                  camera_dy=None if camera is None else per_region(camera[..., 1]),
                  sigma_dx=per_region(sigma[..., 0]), sigma_dy=per_region(sigma[..., 1]),
                  region=region_of if len(groups) > 1 else None)


def track_sparse(source: FrameSource, method: Any, mask: np.ndarray | None, *,
                 reference_frame: int = 0, reference_average: int = 1, max_frames: int | None = None,
                 undistort: Undistort = None,
                 progress: bool = False, store_dir: str | Path | None = None) -> Tracks:
    """Run a sparse method: detect features in the reference, follow them frame by frame.

    Frames before the reference frame cannot be reached by a forward tracker; they are
    reported as unknown (NaN). A sparse run cannot be split into frame ranges: its
    features are followed from frame to frame.
    """
    t0 = time.perf_counter()
    reference = read_reference(source, reference_frame, undistort, reference_average)
    points = method.start(reference, mask)
    if len(points) == 0:
        raise InputError("no corner feature found in the ROI of the reference frame: "
                         "the sparse method cannot track; use a dense method or a larger --roi")
    xs, ys = points[:, 0], points[:, 1]
    ref_values = _sample(reference, xs, ys)
    store = PoiStore(len(points), directory=store_dir)
    frame_list, times, residuals = [], [], []
    start, stop = _stop(max_frames, None)
    t1 = time.perf_counter()
    bar = _progress(source, start, stop, progress)
    try:
        for index, time_s, grey in _frames(source, start, stop, undistort):
            if index < reference_frame:
                d = np.full((len(points), 2), np.nan, np.float32)
                res = float("nan")
            else:
                d = method.step(reference if index == reference_frame else grey)
                res = _residual(ref_values, grey, xs, ys, d[:, 0], d[:, 1])
            frame_list.append(index)
            times.append(time_s)
            store.append(d[:, 0], d[:, 1])
            residuals.append(res)
            bar.update(1)
    finally:
        bar.close()
    t2 = time.perf_counter()
    if not frame_list:
        raise _no_frames(source, start, stop)
    dx, dy = store.arrays()
    row = frame_list.index(reference_frame) if reference_frame in frame_list else 0
    return Tracks(np.asarray(frame_list), np.asarray(times), dx, dy, np.asarray(residuals),
                  xs.astype(np.float32), ys.astype(np.float32), reference_frame,
                  reference_offset(dx, row), reference_offset(dy, row), _timings(t0, t1, t2, len(frame_list)),
                  source.truncated, source.header_frames, image_digest(reference))


# Quality thresholds of :func:`measure`, the defaults of the flags it calls.
# A frame's photometric residual (mean |grey difference| at the POIs) counts as a blocked
# view only far out in the tail of the clip's own residuals: RESIDUAL_K_MAD robust sigmas
# above their median (noise and codec flicker stay well inside), RESIDUAL_RATIO times the
# median (a steady clip's tiny MAD alone would flag ordinary variation) and RESIDUAL_FLOOR
# grey levels (below that it is sensor noise whatever the baseline).
RESIDUAL_K_MAD = 8.0
RESIDUAL_RATIO = 2.5
RESIDUAL_FLOOR = 3.0
# The kept POIs scatter as if the flow failed (an occluder as bright as the structure):
# SPREAD_RATIO times their median spread, and at least SPREAD_FLOOR_PX px, so that POIs
# agreeing to hundredths of a pixel are not flagged for a tenth.
SPREAD_RATIO = 4.0
SPREAD_FLOOR_PX = 1.5
# The band within which a POI agrees with its frame's median (poi_kept_frac): BAND_RATIO
# times the median spread of the valid frames, at least BAND_FLOOR_PX px, widened to
# BAND_RELATIVE of the median displacement so that a member that rotates or bends within
# the mask keeps its POIs at large amplitude.
BAND_RATIO = 3.0
BAND_FLOOR_PX = 0.5
BAND_RELATIVE = 0.25


def flag_invalid(residual: np.ndarray, *, k_mad: float = RESIDUAL_K_MAD, ratio: float = RESIDUAL_RATIO,
                 floor: float = RESIDUAL_FLOOR) -> tuple[np.ndarray, float]:
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
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(finite - median)))
    threshold = max(median + k_mad * sigma, ratio * median, floor)
    return np.isfinite(residual) & (residual <= threshold), threshold


class _NanQuiet:
    """Frames where every POI is NaN give NaN statistics, without RuntimeWarnings."""

    def __enter__(self) -> None:
        self._errstate = np.errstate(all="ignore")
        self._errstate.__enter__()
        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: object) -> None:
        self._warnings.__exit__(*exc)
        self._errstate.__exit__(*exc)


def poi_spread(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Per frame, the robust spread (px) of the POI displacements: 1.4826 x MAD, x and y combined.

    POIs on one structural member move almost alike; an occluder, a lost view
    or a failed flow scatters them.
    """
    spread = np.full(dx.shape[0], np.nan)
    if dx.shape[1] == 0:
        return spread
    with _NanQuiet():
        mad_x = np.nanmedian(np.abs(dx - np.nanmedian(dx, axis=1, keepdims=True)), axis=1)
        mad_y = np.nanmedian(np.abs(dy - np.nanmedian(dy, axis=1, keepdims=True)), axis=1)
    return MAD_TO_SIGMA * np.hypot(mad_x, mad_y)


def consistent_fraction(dx: np.ndarray, dy: np.ndarray, *, band_px: float,
                        relative: float = BAND_RELATIVE) -> np.ndarray:
    """Per frame, the fraction of POIs whose displacement is finite and agrees with the frame's median.

    A POI agrees when its 2-D distance from the frame's median displacement is
    at most ``max(band_px, relative * |median|)``: the relative term lets a
    structure that rotates or bends within the mask keep its POIs at large
    amplitude, while a blocked view or a failed flow scatters them out.
    """
    if dx.shape[1] == 0:
        return np.zeros(dx.shape[0])
    with _NanQuiet():
        median_x = np.nanmedian(dx, axis=1, keepdims=True)
        median_y = np.nanmedian(dy, axis=1, keepdims=True)
        distance = np.hypot(dx - median_x, dy - median_y)
        band = np.maximum(band_px, relative * np.hypot(median_x, median_y))
        agree = np.isfinite(distance) & (distance <= band)
    return agree.sum(axis=1) / dx.shape[1]


def flag_incoherent(spread: np.ndarray, *, ratio: float = SPREAD_RATIO,
                    floor_px: float = SPREAD_FLOOR_PX) -> np.ndarray:
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


def _per_frame(tracks: Tracks, columns: np.ndarray | None,
               statistic: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """``statistic(dx_block, dy_block)`` of every frame, offsets removed, read in blocks."""
    out = np.full(len(tracks.frame), np.nan)
    for rows, bx, by in row_blocks(tracks.dx, tracks.dy, tracks.offset_dx, tracks.offset_dy, columns):
        out[rows] = statistic(bx, by)
    return out


def measure(tracks: Tracks, *, filter_enabled: bool = True, average: str = "mean",
            threshold_ratio: float = THRESHOLD_RATIO, threshold_px: float | None = None,
            mcr_threshold: float = MCR_THRESHOLD, residual_ratio: float = RESIDUAL_RATIO,
            residual_k_mad: float = RESIDUAL_K_MAD, residual_floor: float = RESIDUAL_FLOOR,
            spread_ratio: float = SPREAD_RATIO, spread_floor_px: float = SPREAD_FLOOR_PX,
            check_coherence: bool = True, max_rounds: int = 3, band_ratio: float = BAND_RATIO,
            band_floor_px: float = BAND_FLOOR_PX, band_relative: float = BAND_RELATIVE) -> Measurement:
    """Quality flags, eq. (10)-(12) filtering and averaging of a run's tracks.

    A frame is invalid when its photometric residual is far above its baseline
    (:func:`flag_invalid`), when no POI was measured, or, with
    ``check_coherence``, when the POIs that survive the filters scatter far more
    than usual (:func:`flag_incoherent`). The coherence check must only look at
    the surviving POIs (background POIs in the mask stay put while the
    structure moves, which is no sign of a blocked view), and the filters must
    only use valid frames, so the two alternate until the flags settle (at most
    ``max_rounds`` rounds).

    ``poi_kept_frac`` is, per frame, the :func:`consistent_fraction` of the
    surviving POIs with a band of ``max(band_ratio * median spread,
    band_floor_px)``.
    """
    photometric, threshold = flag_invalid(tracks.residual, k_mad=residual_k_mad, ratio=residual_ratio,
                                          floor=residual_floor)
    measured = _per_frame(tracks, None, lambda bx, by: np.isfinite(bx).any(axis=1)) > 0
    base = photometric & measured
    offset = (tracks.offset_dx, tracks.offset_dy)

    def run_filters(valid: np.ndarray) -> FilterResult:
        return filter_and_average(tracks.dx, tracks.dy, valid=valid, offset=offset,
                                  threshold_ratio=threshold_ratio, threshold_px=threshold_px,
                                  mcr_threshold=mcr_threshold, average=average, enabled=filter_enabled)

    valid = base.copy()
    filtered = run_filters(valid)
    spread = _per_frame(tracks, filtered.kept, poi_spread)
    for _ in range(max_rounds if check_coherence else 0):
        flagged = base & ~flag_incoherent(spread, ratio=spread_ratio, floor_px=spread_floor_px)
        if np.array_equal(flagged, valid):
            break
        valid = flagged
        filtered = run_filters(valid)
        spread = _per_frame(tracks, filtered.kept, poi_spread)
    typical = spread[valid & np.isfinite(spread)]
    band = max(band_ratio * float(np.median(typical)) if typical.size else 0.0, band_floor_px)
    kept_frac = _per_frame(tracks, filtered.kept, lambda bx, by: consistent_fraction(
        bx, by, band_px=band, relative=band_relative))
    if tracks.sigma_dx is not None and tracks.sigma_dy is not None:
        sigma_dx, sigma_dy = np.asarray(tracks.sigma_dx, float), np.asarray(tracks.sigma_dy, float)
    else:
        # Features followed on their own (KLT): the standard error of their mean.
        sigma_dx = _per_frame(tracks, filtered.kept, lambda bx, by: _standard_error(bx))
        sigma_dy = _per_frame(tracks, filtered.kept, lambda bx, by: _standard_error(by))
    return Measurement(tracks, filtered, valid, kept_frac, spread, threshold, band, sigma_dx, sigma_dy)


def _standard_error(block: np.ndarray) -> np.ndarray:
    """Per row, 1.4826 MAD / sqrt(n) of the finite values (NaN with fewer than 2)."""
    with _NanQuiet():
        n = np.isfinite(block).sum(axis=1)
        mad = np.nanmedian(np.abs(block - np.nanmedian(block, axis=1, keepdims=True)), axis=1)
        return np.where(n >= 2, MAD_TO_SIGMA * mad / np.sqrt(np.maximum(n, 1)), np.nan)


def iter_rows(result: Measurement, mm_per_px: float, region: int | None = None) -> Iterable[dict[str, Any]]:
    """CSV rows; invalid frames report NaN displacement instead of a fake motion. ``region``:
    the label written in a ``region`` column (a run of several regions)."""
    tr = result.tracks
    labelled = {} if region is None else {"region": int(region)}
    for i in range(len(tr.frame)):
        ok = bool(result.valid[i])
        dx = float(result.filtered.dx[i]) if ok else float("nan")
        dy = float(result.filtered.dy[i]) if ok else float("nan")
        sx = float(result.sigma_dx[i]) if ok and result.sigma_dx is not None else float("nan")
        sy = float(result.sigma_dy[i]) if ok and result.sigma_dy is not None else float("nan")
        yield {"frame": int(tr.frame[i]), "time_s": float(tr.time_s[i]), **labelled, "dx_px": dx, "dy_px": dy,
               "dx_mm": dx * mm_per_px, "dy_mm": dy * mm_per_px, "valid": int(ok),
               "sigma_dx_px": sx, "sigma_dy_px": sy, "sigma_px": float(np.hypot(sx, sy)),
               "poi_kept_frac": float(result.poi_kept_frac[i]), "residual": float(tr.residual[i]),
               "flow_spread_px": float(result.flow_spread_px[i]),
               "camera_dx_px": float(tr.camera_dx[i]) if tr.camera_dx is not None else float("nan"),
               "camera_dy_px": float(tr.camera_dy[i]) if tr.camera_dy is not None else float("nan")}


RAW_FORMAT = "refflow-raw-tracks/1"


def save_raw_tracks(path: str | Path, tracks: Tracks, meta: dict[str, Any]) -> None:
    """Write the unfiltered tracks of a run or a range of frames (``track --raw-tracks``).

    ``meta`` must hold an ``identity`` dict (method, parameters, reference,
    ROI, calibration, POIs ...) that parts of one run share; :func:`load_raw_tracks`
    checks it. The per-POI matrices are streamed into the file (uncompressed).
    """
    camera = ({} if tracks.camera_dx is None
              else {"camera_dx_px": tracks.camera_dx, "camera_dy_px": tracks.camera_dy})
    if tracks.sigma_dx is not None:
        camera.update({"sigma_dx_px": tracks.sigma_dx, "sigma_dy_px": tracks.sigma_dy})
    if tracks.region is not None:
        camera["region"] = tracks.region
    write_npz(path, {"format": np.array(RAW_FORMAT), "meta": np.array(json.dumps(meta, sort_keys=True)),
                     "frame": tracks.frame, "time_s": tracks.time_s, "residual": tracks.residual,
                     "x_px": tracks.x_px, "y_px": tracks.y_px, "offset_dx_px": tracks.offset_dx,
                     "offset_dy_px": tracks.offset_dy, **camera, "dx_px": tracks.dx, "dy_px": tracks.dy})


@dataclass
class _Part:
    path: Path
    meta: dict[str, Any]
    small: dict[str, np.ndarray]


def _open_part(path: Path) -> _Part:
    if not path.is_file():
        raise InputError(f"part {str(path)!r} does not exist: pass the files `refflow track --raw-tracks` wrote")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "format" not in data.files or str(data["format"]) != RAW_FORMAT:
                raise InputError(f"{str(path)!r} is not a raw-tracks file of `refflow track --raw-tracks` "
                                 f"({RAW_FORMAT})")
            small = {k: data[k] for k in data.files if k not in ("dx_px", "dy_px", "meta", "format")}
            meta = json.loads(str(data["meta"]))
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(f"{str(path)!r} is not a readable .npz raw-tracks file ({err})") from None
    return _Part(path, meta, small)


def _rows_of(path: Path, name: str, n_points: int) -> Iterator[np.ndarray]:
    """Blocks of rows of an ``(F, n_points)`` float32 member, read without loading it whole."""
    with zipfile.ZipFile(path) as archive, archive.open(f"{name}.npy") as member:
        version = np.lib.format.read_magic(member)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(member)
        if fortran or dtype != np.float32 or len(shape) != 2 or shape[1] != n_points:
            raise InputError(f"{path}: {name} is not a float32 (frames, {n_points}) matrix")
        for rows in block_rows(shape[0], n_points):
            count = rows.stop - rows.start
            yield np.frombuffer(member.read(count * n_points * 4), np.float32).reshape(count, n_points)


def load_raw_tracks(paths: Iterable[str | Path], *,
                    store_dir: str | Path | None = None) -> tuple[Tracks, list[dict[str, Any]]]:
    """Concatenate raw-tracks parts of one run into :class:`Tracks` (in frame order).

    The parts must share their ``identity`` (same video, reference frame,
    ROI, calibration, POIs, method and parameters) and cover contiguous,
    non-overlapping frame ranges. Returns the tracks and the parts' ``meta``
    in frame order. Memory stays bounded: rows go through a :class:`PoiStore`.
    """
    parts = [_open_part(Path(p)) for p in paths]
    if not parts:
        raise InputError("no part given: pass the .npz files of `refflow track --raw-tracks`")
    first = parts[0]
    for part in parts[1:]:
        for key in sorted(set(first.meta["identity"]) | set(part.meta["identity"])):
            mine, theirs = first.meta["identity"].get(key), part.meta["identity"].get(key)
            if mine != theirs:
                raise InputError(f"{part.path.name} and {first.path.name} differ in {key} ({theirs!r} vs "
                                 f"{mine!r}): merge only parts of one run (same video, reference, ROI, "
                                 "POIs, method and parameters)")
        if not (np.array_equal(part.small["x_px"], first.small["x_px"])
                and np.array_equal(part.small["y_px"], first.small["y_px"])
                and np.array_equal(part.small.get("region", []), first.small.get("region", []))):
            raise InputError(f"{part.path.name} and {first.path.name} track different POIs: "
                             "use the same mask, --grid-step and --roi for every part")
    parts.sort(key=lambda part: int(part.small["frame"][0]) if part.small["frame"].size else -1)
    for before, after in zip(parts, parts[1:], strict=False):
        end, begin = int(before.small["frame"][-1]) + 1, int(after.small["frame"][0])
        if begin < end:
            raise InputError(f"{after.path.name} (from frame {begin}) overlaps {before.path.name} "
                             f"(to frame {end - 1}): give non-overlapping --frames ranges")
        if begin > end:
            raise InputError(f"frames {end}:{begin} are missing between {before.path.name} and "
                             f"{after.path.name}: track that range too (--frames {end}:{begin})")
    n_points = len(first.small["x_px"])
    store = PoiStore(n_points, directory=store_dir)
    for part in parts:
        for block_x, block_y in zip(_rows_of(part.path, "dx_px", n_points),
                                    _rows_of(part.path, "dy_px", n_points), strict=True):
            store.extend(block_x, block_y)
    dx, dy = store.arrays()
    reference_frame = int(first.meta["identity"]["reference_frame"])
    # The reference frame's own row gives the offset where a part holds it (as in a whole run).
    holder = next((p for p in parts if reference_frame in p.small["frame"]), parts[0])
    per_frame = ("frame", "time_s", "residual") + (("camera_dx_px", "camera_dy_px")
                                                   if "camera_dx_px" in first.small else ()) \
        + (("sigma_dx_px", "sigma_dy_px") if all("sigma_dx_px" in p.small for p in parts) else ())
    concat = {key: np.concatenate([p.small[key] for p in parts]) for key in per_frame}
    timings = {key: sum(p.meta.get("timings", {}).get(key, 0.0) for p in parts)
               for key in ("setup_s", "frames_s") + tuple(k for k in CHAIN_COUNTS if k in first.meta.get("timings", {}))}
    timings["frames_per_s"] = len(concat["frame"]) / max(timings["frames_s"], 1e-9)
    tracks = Tracks(concat["frame"], concat["time_s"], dx, dy, concat["residual"],
                    first.small["x_px"], first.small["y_px"], reference_frame,
                    holder.small["offset_dx_px"].astype(np.float64), holder.small["offset_dy_px"].astype(np.float64),
                    timings, any(p.meta["input"]["truncated"] for p in parts),
                    int(first.meta["input"]["header_frames"]), first.meta["identity"]["reference_digest"],
                    camera_dx=concat.get("camera_dx_px"), camera_dy=concat.get("camera_dy_px"),
                    sigma_dx=concat.get("sigma_dx_px"), sigma_dy=concat.get("sigma_dy_px"),
                    region=first.small.get("region"))
    return tracks, [p.meta for p in parts]
