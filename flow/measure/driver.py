"""The reference-frame driver (paper section 3.5) and its sparse counterpart: the frame loops.

Dense methods: every frame is compared with the one fixed reference frame, so
frames are independent (``jobs`` threads work on them at once), a run can be
split into frame ranges measured separately and merged, and tracking resumes
by itself after an occlusion. Sparse methods (KLT) follow their own features
through the sequence in order.

Memory stays constant whatever the clip length: frames are streamed, and the
per-POI tracks (``frames x POIs``, which eq. 10-12 need whole) go to a
disk-backed :class:`~flow.measure.storage.PoiStore` and are read back in blocks of frames.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import queue
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any, NamedTuple

import cv2
import numpy as np
from tqdm import tqdm

from flow.io.errors import InputError
from flow.io.frames import FrameSource
from flow.measure.background import Background
from flow.measure.filtering import reference_offset
from flow.measure.photometric import LucasKanadeSigma, mean_abs, photometric_residual, sample
from flow.measure.storage import PoiStore
from flow.measure.tracks import Tracks
from flow.measure.window import crop_window

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


def _one_frame(start: int, stop: int | None, n_frames: int) -> None:
    """A whole input of one frame, the reference only: refused rather than written as a row of
    zeros. A ``--frames`` part of one frame is a part of a run, measured as any other."""
    if n_frames == 1 and start == 0 and stop is None:
        raise InputError("the input holds one frame, the reference: a displacement needs at least one more; "
                         "pass the whole video or image folder")


def _pixels(shape: tuple[int, ...], rows: np.ndarray, columns: np.ndarray) -> np.ndarray:
    """A bool image of ``shape``, True at the given pixels."""
    image = np.zeros(shape, bool)
    image[rows, columns] = True
    return image


@dataclass(frozen=True)
class _Regions:
    """The POIs' regions: each POI's label, the labels ascending, each label's POIs and centroid."""

    region_of: np.ndarray  # (P,) int64
    labels: np.ndarray  # (R,)
    groups: list[np.ndarray]  # R arrays of POI indices
    centroids: np.ndarray  # (R, 2) x, y in ROI pixels


def _regions(poi_xy: np.ndarray, mask: np.ndarray) -> _Regions:
    """The regions of ``mask`` at the POIs: labels 1..N of an int mask; a bool mask is one region."""
    region_of = np.asarray(mask)[poi_xy[:, 1], poi_xy[:, 0]].astype(np.int64)
    labels = np.unique(region_of)
    if labels.size > 1 and labels[0] <= 0:
        raise ValueError(f"{int(np.sum(region_of <= 0))} POIs lie outside the labelled mask's regions")
    groups = [np.flatnonzero(region_of == label) for label in labels]
    poi_points = poi_xy.astype(np.float64)
    centroids = np.array([poi_points[group].mean(axis=0) for group in groups])
    return _Regions(region_of, labels, groups, centroids)


def _per_region(values: Any, n_regions: int) -> np.ndarray:
    """Per-frame values of R regions as (F, R); (F,) for one region."""
    values = np.asarray(values, np.float64)
    return values if n_regions > 1 else values[:, 0]


class _MethodPool:
    """``jobs`` method instances bound to the reference, lent out one chain of frames (one frame
    for a method that does not chain) at a time, so that no two threads share one (OpenCV flow
    objects are not thread-safe)."""

    def __init__(self, factory: Callable[[], Any], jobs: int) -> None:
        self._idle: queue.SimpleQueue = queue.SimpleQueue()
        self.methods = [factory() for _ in range(jobs)]
        self.chain = 1
        # Set when the run stops (Ctrl-C, SIGTERM): a method that checks it (a dense method's
        # ``stop``) abandons the frame it is measuring at its next stage, the jobs end within
        # a fraction of a frame.
        self.stop = threading.Event()
        for method in self.methods:
            if hasattr(method, "check_stop"):
                method.stop = self.stop

    def bind(self, reference: np.ndarray, mask: np.ndarray, read: np.ndarray | None) -> None:
        """Bind every instance to the reference and make them available."""
        for method in self.methods:
            if hasattr(method, "bind"):
                method.bind(reference, mask, read=read)
            self._idle.put(method)
        # A method that solves frames from one another (``chain_length`` > 1) gets the frames of
        # one chain, ``(index - reference_frame) // chain_length``, in order on one instance, from
        # a restart: the chains are fixed by the frame index alone, so any --frames part or --jobs
        # count gives the very numbers of one run (a part that starts inside a chain first solves
        # the chain's earlier frames without keeping them). The reference frame begins a chain.
        self.chain = max(1, int(getattr(self.methods[0], "chain_length", 0) or 0))

    @contextlib.contextmanager
    def lend(self) -> Iterator[Any]:
        """An idle method instance, given back when the block ends."""
        method = self._idle.get()
        try:
            yield method
        finally:
            self._idle.put(method)

    def chain_counts(self) -> dict[str, float]:
        """Where the time went, for a method that keeps ``counts`` (a dict: frames it measured in
        full and frames it tracked, ...; warm-up frames of a part included), summed over the
        instances; a length (a key ending in ``_px``: each instance measures it alike) is the
        largest of theirs."""
        counts = [getattr(m, "counts", None) or {} for m in self.methods]
        return {key: float(max(c.get(key, 0) for c in counts) if key.endswith("_px") else
                           sum(c.get(key, 0) for c in counts)) for key in counts[0]}


class _FrameResult(NamedTuple):
    """One frame's measurement: the POIs' displacement (the camera's motion removed) and, per
    region, the mean photometric residual, the camera's motion at the region's centroid and
    the standard uncertainty of the mean displacement."""

    dx: np.ndarray  # (P,) float32, px
    dy: np.ndarray
    residual: np.ndarray  # (R,) grey levels
    camera: np.ndarray  # (R, 2) px, NaN without a background
    sigma: np.ndarray  # (R, 2) px
    # The mask pixels' (u, v) for --field, and their standard uncertainty (None: the method has none).
    field: tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None] | None = None
    hidden: bool | None = None  # the method saw nothing of the scene in the frame (see Tracks.hidden)
    holds_reference: np.ndarray | None = None  # (R,) bool, see Tracks.sigma_holds_reference


class _PoiReadout:
    """Reads a method's flow of one frame against the reference at the POIs (a :class:`_FrameResult`)."""

    def __init__(self, reference: np.ndarray, poi_xy: np.ndarray, regions: _Regions,
                 background: Background | None, field: Any = None) -> None:
        self.reference = reference
        self._field = field
        self._columns, self._rows = poi_xy[:, 0], poi_xy[:, 1]
        self.xs = self._columns.astype(np.float32)
        self.ys = self._rows.astype(np.float32)
        self._ref_values = reference[self._rows, self._columns].astype(np.float32)
        self._regions = regions
        self._lks = [LucasKanadeSigma(reference, poi_xy[group]) for group in regions.groups]
        self._background = background
        self._points = poi_xy.astype(np.float64)

    def measure(self, method: Any, current: np.ndarray) -> _FrameResult:
        flow = method.calc(self.reference, current)
        dx = flow[self._rows, self._columns, 0].astype(np.float32)
        dy = flow[self._rows, self._columns, 1].astype(np.float32)
        error = sample(current, self.xs + dx, self.ys + dy) - self._ref_values
        filled = getattr(method, "last_filled", None)  # POIs whose flow the method gave, not read
        if filled is not None and filled.shape == current.shape[:2]:
            error[filled[self._rows, self._columns]] = np.nan  # (mean_abs takes the finite ones)
        own = getattr(method, "last_sigmas_px", None) or {}
        labels, groups = self._regions.labels, self._regions.groups
        residual = np.array([mean_abs(error[group]) for group in groups])
        sigma = np.array([own[int(label)] if int(label) in own else lk.sigma(error[group])
                          for label, group, lk in zip(labels, groups, self._lks, strict=True)], np.float64)
        cdx, cdy, camera = self._compensate(flow, dx, dy)
        field = None if self._field is None else self._field.cut(flow, cdx, cdy,
                                                                  getattr(method, "last_field_sigma", None))
        hidden = getattr(method, "last_hidden", None)  # None: the method does not tell
        held = getattr(method, "last_sigmas_hold_reference", None) or set()
        holds = np.array([int(label) in own and int(label) in held for label in labels], bool)
        return _FrameResult(cdx, cdy, residual, camera, sigma, field, None if hidden is None else bool(hidden),
                            holds)

    def _compensate(self, flow: np.ndarray, dx: np.ndarray,
                    dy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """POI flow minus the camera's motion, and that motion at each region's centroid."""
        background = self._background
        if background is None:
            return dx, dy, np.full((len(self._regions.groups), 2), np.nan)
        bx = flow[background.rows, background.columns, 0]
        by = flow[background.rows, background.columns, 1]
        mx, my = background.motion_at(bx, by, np.vstack([self._points, self._regions.centroids]))
        n = len(self._points)
        return ((dx - mx[:n]).astype(np.float32), (dy - my[:n]).astype(np.float32),
                np.column_stack([mx[n:], my[n:]]).astype(np.float64))


# A frame of a chain: index, time, grey image, and whether it is kept (False: it only warms
# the chain up, before the frames asked for).
_ChainFrame = tuple[int, float, np.ndarray, bool]
_Solved = list[tuple[int, float, _FrameResult]]


def _work_area(method: Any, shape: tuple[int, ...], mask: np.ndarray,
               background: Background | None) -> tuple[slice, slice] | None:
    """The part of the frames a dense method can ever read: the POIs' bounding box plus the
    widest context the method may take (``max_window_margin``; None: the whole frame), so that
    frames are held, queued and measured at that size (a 4K frame of a small member costs what
    the member costs, and the numbers are those of an --roi holding the area). None: the whole
    frame (a method without a bound context, or background points, which lie anywhere)."""
    widest = getattr(method, "max_window_margin", None)
    margin = None if widest is None or background is not None else widest(shape)
    return None if margin is None else crop_window(shape[:2], np.asarray(mask) != 0, margin)


def _cutter(undistort: Undistort, area: tuple[slice, slice] | None) -> Undistort:
    """``undistort`` followed by the cut to ``area`` (a copy: the frame itself is let go)."""
    if area is None:
        return undistort
    if undistort is None:
        return lambda grey: np.ascontiguousarray(grey[area])
    return lambda grey: np.ascontiguousarray(undistort(grey)[area])


# A method's kernels that take longer than this to load are being compiled (the first run on a
# machine, or after an upgrade of numba): said on stderr, where the progress bar would sit at 0.
COMPILE_NOTICE_S = 1.5


def _warm_up(method: Any, progress: bool) -> None:
    """Compile (or load) the method's kernels before the first frame, saying so where it takes
    long, so that neither the progress bar nor Ctrl-C waits on a compiler in a worker thread."""
    warm = getattr(method, "warm_up", None)
    if warm is None:
        return
    notice = threading.Timer(COMPILE_NOTICE_S, lambda: print(
        f"refflow: compiling the {getattr(method, 'name', '') or 'method'}'s kernels (first run only, "
        "about 30 s on 2 cores; `make` does it at install)", file=sys.stderr, flush=True))
    notice.daemon = True
    if progress:
        notice.start()
    try:
        warm()
    finally:
        notice.cancel()


def _measure_chain(pool: _MethodPool, readout: _PoiReadout, items: list[_ChainFrame], *,
                   stop: threading.Event | None = None) -> _Solved:
    """Results of the kept frames of one chain, solved in order on one method instance; none
    once ``stop`` is set (an interrupted run stops after the frame each job is measuring, or
    within it where the method checks the pool's ``stop``)."""
    with pool.lend() as method:
        if hasattr(method, "restart"):
            method.restart()
        results = []
        for index, time_s, grey, keep in items:
            if stop is not None and stop.is_set():
                return []
            result = readout.measure(method, grey)  # a warm-up frame too: the chain needs it
            if keep:
                results.append((index, time_s, result))
        return results


def _chain_of(index: int, reference_frame: int, chain: int) -> int:
    """The chain of frame ``index``: chains of ``chain`` frames, the reference frame begins one."""
    return (index - reference_frame) // chain


def _chains(source: FrameSource, start: int, stop: int | None, undistort: Undistort, *,
            reference_frame: int, chain: int) -> Iterator[list[_ChainFrame]]:
    """Frames ``start:stop`` chain by chain; the first chain from its own first frame."""
    first = max(0, reference_frame + _chain_of(start, reference_frame, chain) * chain)
    group: list[_ChainFrame] = []
    for index, time_s, grey in _frames(source, first, stop, undistort):
        current = _chain_of(index, reference_frame, chain)
        if group and current != _chain_of(group[-1][0], reference_frame, chain):
            yield group
            group = []
        group.append((index, time_s, grey, index >= start))
    if group:
        yield group


def _run_chains(chains: Iterator[list[_ChainFrame]], measure_chain: Callable[..., _Solved],
                collect: Callable[[_Solved], None], *, jobs: int, chain: int,
                stop: threading.Event | None = None) -> None:
    """Solve every chain, ``jobs`` at a time, and ``collect`` their results in frame order.
    Interrupted (Ctrl-C), ``stop`` is set: the jobs stop at their method's next check of it
    (see :class:`_MethodPool`), or after their current frame, never after their chain."""
    threads_before = cv2.getNumThreads()
    try:
        if jobs == 1:
            for group in chains:
                collect(measure_chain(group))
        else:
            # One OpenCV thread per job avoids oversubscribing the cores; a bounded queue (of
            # frames, or of chains of frames) keeps memory bounded and results in frame order.
            cv2.setNumThreads(1)
            bound = 2 * jobs if chain == 1 else jobs + 1
            stop = threading.Event() if stop is None else stop
            with ThreadPoolExecutor(max_workers=jobs) as executor:
                pending: deque = deque()
                try:
                    for group in chains:
                        pending.append(executor.submit(measure_chain, group, stop=stop))
                        if len(pending) >= bound:
                            collect(pending.popleft().result())
                    while pending:
                        collect(pending.popleft().result())
                except BaseException:
                    stop.set()
                    executor.shutdown(wait=True, cancel_futures=True)
                    raise
    finally:
        cv2.setNumThreads(threads_before)


class _Collected:
    """The kept frames' results in frame order: the POIs' rows in a disk store, the per-frame
    values in lists."""

    def __init__(self, n_points: int, store_dir: str | Path | None, field: Any = None) -> None:
        self.store = PoiStore(n_points, directory=store_dir)
        self.field = field
        self.frames: list[int] = []
        self.times: list[float] = []
        self.residuals: list[np.ndarray] = []
        self.cameras: list[np.ndarray] = []
        self.sigmas: list[np.ndarray] = []
        self.hidden: list[bool | None] = []
        self.holds_reference: list[np.ndarray] = []

    def add(self, results: _Solved, bar: tqdm) -> None:
        for index, time_s, result in results:
            self.frames.append(index)
            self.times.append(time_s)
            self.store.append(result.dx, result.dy)
            self.residuals.append(result.residual)
            self.cameras.append(result.camera)
            self.sigmas.append(result.sigma)
            self.hidden.append(result.hidden)
            self.holds_reference.append(result.holds_reference)
            if self.field is not None:
                self.field.append(index, *result.field)
            bar.update(1)


def _to_work_area(source: FrameSource, method: Any, reference: np.ndarray, mask: np.ndarray, poi_xy: np.ndarray,
                  background: Background | None, undistort: Undistort) -> tuple[Any, ...]:
    """The reference, mask and POIs cut to the method's work area (see :func:`_work_area`), the
    area's origin in the ROI, the undistortion that cuts its output to the area, and the area
    the source cuts each frame to (None: not cut there)."""
    area = _work_area(method, reference.shape, mask, background)
    origin = np.zeros(2, poi_xy.dtype)
    # Without undistortion (which needs the whole frame) the source cuts each frame before
    # its colour conversion; with it, the undistorted frame is cut.
    at_source = area if undistort is None and hasattr(source, "cut") else None
    if area is not None:
        origin = np.array([area[1].start, area[0].start], poi_xy.dtype)
        reference, mask, poi_xy = np.ascontiguousarray(reference[area]), mask[area], poi_xy - origin
        if at_source is None:
            undistort = _cutter(undistort, area)
    return reference, mask, poi_xy, origin, undistort, at_source


def track_dense(source: FrameSource, factory: Callable[[], Any], poi_xy: np.ndarray, *,
                reference_frame: int = 0, reference_average: int = 1, jobs: int = 1,
                max_frames: int | None = None,
                frames: tuple[int, int | None] | None = None, undistort: Undistort = None,
                progress: bool = False, store_dir: str | Path | None = None,
                background: Background | None = None, mask: np.ndarray | None = None,
                field: Any = None) -> Tracks:
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
    field : flow.field.stream.FieldStream, optional
        Receives every kept frame's displacement at the mask pixels, in frame order
        (``--field``), and the reference's own where the range lacks the reference frame.
    """
    if jobs < 1:
        raise InputError(f"--jobs {jobs} must be >= 1")
    start, stop = _stop(max_frames, frames)
    t0 = time.perf_counter()
    reference = read_reference(source, reference_frame, undistort, reference_average)
    if mask is None:
        mask = _pixels(reference.shape, poi_xy[:, 1], poi_xy[:, 0])
    regions = _regions(poi_xy, mask)
    read = None if background is None else _pixels(reference.shape, background.rows, background.columns)
    pool = _MethodPool(factory, jobs)
    _warm_up(pool.methods[0], progress)
    digest = image_digest(reference)
    if field is not None:
        field.set_image(reference)
    reference, mask, poi_xy, origin, undistort, at_source = _to_work_area(
        source, pool.methods[0], reference, mask, poi_xy, background, undistort)
    if field is not None:
        field.flow_origin = (int(origin[0]), int(origin[1]))
        for method in pool.methods:
            method.want_field_sigma = True  # the pixels' own uncertainty, where the method has one
    pool.bind(reference, mask, read)
    readout = _PoiReadout(reference, poi_xy, regions, background, field)
    measure_chain = functools.partial(_measure_chain, pool, readout)
    in_range = start <= reference_frame and (stop is None or reference_frame < stop)
    offset = None
    if not in_range or reference_average > 1:
        # The range lacks the reference frame (or the reference is no frame of the video but
        # a mean of frames): measure it against itself, as the frame's own row would have
        # been (the first of its chain), so the offset removed is the same in a whole run and
        # in its parts.
        own = measure_chain([(reference_frame, 0.0, reference, True)])[0][2]
        offset = (own.dx.astype(np.float64), own.dy.astype(np.float64))
        if field is not None:
            field.set_reference(*own.field[:2])

    collected = _Collected(len(poi_xy), store_dir, field)
    t1 = time.perf_counter()
    cut = source.cut(at_source) if at_source is not None else contextlib.nullcontext()
    with _progress(source, start, stop, progress) as bar, cut:
        chains = _chains(source, start, stop, undistort, reference_frame=reference_frame, chain=pool.chain)
        _run_chains(chains, measure_chain, functools.partial(collected.add, bar=bar), jobs=jobs, chain=pool.chain,
                    stop=pool.stop)
    t2 = time.perf_counter()
    if not collected.frames:
        raise _no_frames(source, start, stop)
    _one_frame(start, stop, len(collected.frames))
    xy = (readout.xs + np.float32(origin[0]), readout.ys + np.float32(origin[1]))
    return _assemble(collected, source, regions, xy, reference_frame, offset, digest,
                     {**_timings(t0, t1, t2, len(collected.frames)), **pool.chain_counts()},
                     with_camera=background is not None, reference_average=reference_average)


def _assemble(collected: _Collected, source: FrameSource, regions: _Regions, xy: tuple[np.ndarray, np.ndarray],
              reference_frame: int, offset: tuple[np.ndarray, np.ndarray] | None, digest: str,
              timings: dict[str, float], *, with_camera: bool, reference_average: int) -> Tracks:
    """A dense run's :class:`Tracks` from its collected frames (the reference's offset, eq. 10,
    from the reference frame's own row where ``offset`` is None)."""
    dx, dy = collected.store.arrays()
    frame_index = np.asarray(collected.frames)
    if offset is None:
        row = int(np.flatnonzero(frame_index == reference_frame)[0])
        offset = (reference_offset(dx, row), reference_offset(dy, row))
    n_regions = len(regions.groups)
    camera = np.asarray(collected.cameras, np.float64) if with_camera else None
    sigma = np.asarray(collected.sigmas, np.float64)
    holds = np.asarray(collected.holds_reference, bool).reshape(len(frame_index), n_regions)
    return Tracks(frame=frame_index, time_s=np.asarray(collected.times), dx=dx, dy=dy,
                  residual=_per_region(collected.residuals, n_regions), x_px=xy[0], y_px=xy[1],
                  reference_frame=reference_frame, reference_average=reference_average,
                  offset_dx=offset[0], offset_dy=offset[1],
                  timings_s=timings, truncated=source.truncated, header_frames=source.header_frames,
                  reference_digest=digest,
                  camera_dx=None if camera is None else _per_region(camera[..., 0], n_regions),
                  camera_dy=None if camera is None else _per_region(camera[..., 1], n_regions),
                  sigma_dx=_per_region(sigma[..., 0], n_regions), sigma_dy=_per_region(sigma[..., 1], n_regions),
                  sigma_holds_reference=holds if n_regions > 1 else holds[:, 0],
                  region=regions.region_of if n_regions > 1 else None,
                  hidden=None if None in collected.hidden else np.asarray(collected.hidden, bool))


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
    _one_frame(start, stop, len(frame_list))
    dx, dy = store.arrays()
    row = frame_list.index(reference_frame) if reference_frame in frame_list else 0
    return Tracks(frame=np.asarray(frame_list), time_s=np.asarray(times), dx=dx, dy=dy,
                  residual=np.asarray(residuals), x_px=xs.astype(np.float32), y_px=ys.astype(np.float32),
                  reference_frame=reference_frame, reference_average=reference_average,
                  offset_dx=reference_offset(dx, row),
                  offset_dy=reference_offset(dy, row), timings_s=_timings(t0, t1, t2, len(frame_list)),
                  truncated=source.truncated, header_frames=source.header_frames,
                  reference_digest=image_digest(reference))
