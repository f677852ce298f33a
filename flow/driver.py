"""The reference-frame driver (paper section 3.5) and its sparse counterpart: the frame loops.

Dense methods: every frame is compared with the one fixed reference frame, so
frames are independent (``jobs`` threads work on them at once), a run can be
split into frame ranges measured separately and merged, and tracking resumes
by itself after an occlusion. Sparse methods (KLT) follow their own features
through the sequence in order.

Memory stays constant whatever the clip length: frames are streamed, and the
per-POI tracks (``frames x POIs``, which eq. 10-12 need whole) go to a
disk-backed :class:`~flow.storage.PoiStore` and are read back in blocks of frames.
"""

from __future__ import annotations

import hashlib
import queue
import sys
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from tqdm import tqdm

from flow.background import Background
from flow.filtering import reference_offset
from flow.io import FrameSource, InputError
from flow.photometric import LucasKanadeSigma, mean_abs, photometric_residual, sample
from flow.storage import PoiStore
from flow.tracks import CHAIN_COUNTS, Tracks

Undistort = Callable[[np.ndarray], np.ndarray] | None


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


def _timings(t0: float, t1: float, t2: float, n_frames: int) -> dict[str, float]:
    # frames_s times the frame loop only: reading the reference and building the
    # methods (setup_s) are not frame processing.
    return {"setup_s": t1 - t0, "frames_s": t2 - t1, "frames_per_s": n_frames / max(t2 - t1, 1e-9)}


def _no_frames(source: FrameSource, start: int, stop: int | None) -> InputError:
    if start > 0 or stop is not None:
        return InputError(f"no frame to measure in frames {start}:{'' if stop is None else stop}: "
                          f"the video has {source.frames_read} decodable frames; pick a range inside it")
    return InputError("no frame to measure: the video is empty")




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
    lks = [LucasKanadeSigma(reference, poi_xy[group]) for group in groups]
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
        error = sample(current, xs + dx, ys + dy) - ref_values
        own = getattr(method, "last_sigmas_px", None) or {}
        residual = np.array([mean_abs(error[group]) for group in groups])
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
    ref_values = sample(reference, xs, ys)
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
                res = photometric_residual(ref_values, grey, xs, ys, d[:, 0], d[:, 1])
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
