"""Outlier filtering and averaging of per-POI displacement tracks (paper section 3.7).

``D`` is the ``(F, P)`` matrix of displacements of ``P`` POIs over ``F``
frames (one per image axis). The paper's steps:

1. offset removal: every POI track starts at zero at the reference frame;
2. eq. (10): keep POI ``m`` if ``max_t |d_m(t)| >= threshold``, the threshold
   being a fraction of the median over POIs of that maximum, so stationary
   background points drop out;
3. eq. (11): correlation coefficients ``R_ij`` between the kept tracks; keep
   POIs whose mean cross-correlation ``mcr_m`` exceeds a threshold;
4. eq. (12): average the surviving tracks frame by frame.

Both filters need the whole series, so they run once at the end of a run.
Frames flagged invalid (occlusion) are excluded from the statistics, so a
blocked view cannot poison the correlation; NaN entries (lost features) are
ignored.

The matrices may be disk-backed (``flow.measure.storage.DiskMatrix``), far larger than memory (a long
clip with thousands of POIs): every step reads them in blocks of frames
(:func:`row_blocks`) and keeps only per-POI and per-frame vectors, so memory
stays bounded by :data:`CHUNK_BYTES` whatever the clip length.

References
----------
Paper section 3.7, eq. (10)-(12).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

#: Bytes of float64 working arrays one block of frames may occupy.
CHUNK_BYTES = 32 << 20
#: Eq. (10) default: a POI whose peak |d| is below this fraction of the median over POIs
#: of that peak counts as background (the paper thresholds "with its median value"; half of
#: it keeps the parts of a member that move less than the typical POI).
THRESHOLD_RATIO = 0.5
#: Eq. (11) default: a POI whose mean correlation with the other POIs is below this moves
#: on its own (an outlier), not with the structure.
MCR_THRESHOLD = 0.5


@dataclass
class FilterResult:
    """Outcome of :func:`filter_and_average`."""

    dx: np.ndarray  # (F,) averaged displacement, px
    dy: np.ndarray
    kept: np.ndarray  # (P,) bool: POI survived the filters
    kept_threshold: np.ndarray  # (P,) bool: survived eq. (10)
    mcr: np.ndarray  # (P,) mean cross-correlation (NaN where not computed)
    threshold_px: float
    notes: list[str] = field(default_factory=list)


def block_rows(n_frames: int, n_points: int, *, copies: int = 8) -> Iterator[slice]:
    """Slices of frames whose ``copies`` float64 ``(rows, n_points)`` arrays fit :data:`CHUNK_BYTES`."""
    height = max(1, CHUNK_BYTES // max(1, n_points * 8 * copies))
    for start in range(0, n_frames, height):
        yield slice(start, min(start + height, n_frames))


def row_blocks(dx: np.ndarray, dy: np.ndarray, offset_x: np.ndarray | None = None,
               offset_y: np.ndarray | None = None,
               columns: np.ndarray | None = None) -> Iterator[tuple[slice, np.ndarray, np.ndarray]]:
    """``(rows, dx_block, dy_block)``: float64 blocks of frames, offsets removed, optional POI subset."""
    n_frames, n_points = dx.shape
    for rows in block_rows(n_frames, n_points):  # whole rows are read, whatever the subset
        bx = np.asarray(dx[rows], np.float64)
        by = np.asarray(dy[rows], np.float64)
        if offset_x is not None:
            bx = bx - offset_x
            by = by - offset_y
        if columns is not None:
            bx, by = bx[:, columns], by[:, columns]
        yield rows, bx, by


def reference_offset(d: np.ndarray, reference_row: int = 0) -> np.ndarray:
    """Each POI's value at ``reference_row``; where that is NaN, its first finite value (else 0)."""
    n_frames, n_points = d.shape
    if n_frames == 0:
        return np.zeros(n_points)
    offset = np.asarray(d[reference_row], np.float64).copy()
    todo = np.flatnonzero(~np.isfinite(offset))
    # A POI without a value at the reference frame (a feature found late) takes its first one.
    for rows in block_rows(n_frames, n_points):
        if todo.size == 0:
            break
        block = np.asarray(d[rows], np.float64)[:, todo]
        finite = np.isfinite(block)
        hit = finite.any(axis=0)
        offset[todo[hit]] = block[finite.argmax(axis=0)[hit], np.flatnonzero(hit)]
        todo = todo[~hit]
    offset[todo] = 0.0
    return offset


def _zscore(block: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    centred = np.where(np.isfinite(block), block - mean, 0.0)
    return np.divide(centred, std, out=np.zeros_like(centred), where=std > 0)


def _mcr_streaming(blocks: Callable[[], Iterator[np.ndarray]], n_points: int) -> np.ndarray:
    """Eq. (11) over sample blocks ``(t, P)`` that ``blocks()`` yields, in three passes.

    ``mean_j R_mj = z_m . (sum_j z_j - z_m) / (T (P-1))`` with z-scored tracks, so
    neither the ``P x P`` matrix nor the whole ``(T, P)`` matrix is ever in memory.
    NaNs count as the track's mean (zero after z-scoring).
    """
    count = np.zeros(n_points)
    total = np.zeros(n_points)
    squares = np.zeros(n_points)
    n_samples = 0
    for block in blocks():
        finite = np.isfinite(block)
        values = np.where(finite, block, 0.0)
        count += finite.sum(axis=0)
        total += values.sum(axis=0)
        squares += (values**2).sum(axis=0)
        n_samples += block.shape[0]
    if n_points < 2 or n_samples < 2:
        return np.ones(n_points)
    mean = np.divide(total, count, out=np.zeros(n_points), where=count > 0)
    # Sum over finite entries of (x - mean)^2, divided by all samples (NaNs sit at the mean).
    std = np.sqrt(np.maximum(squares - 2 * mean * total + count * mean**2, 0.0) / n_samples)
    sums = [_zscore(block, mean, std).sum(axis=1) for block in blocks()]
    mcr = np.zeros(n_points)
    for block, z_sum in zip(blocks(), sums, strict=True):
        z = _zscore(block, mean, std)
        mcr += (z * (z_sum[:, None] - z)).sum(axis=0)
    return mcr / (n_samples * (n_points - 1))


def filter_and_average(dx: np.ndarray, dy: np.ndarray, *, valid: np.ndarray | None = None,
                       reference_row: int = 0, offset: tuple[np.ndarray, np.ndarray] | None = None,
                       threshold_ratio: float = THRESHOLD_RATIO, threshold_px: float | None = None,
                       mcr_threshold: float = MCR_THRESHOLD, average: str = "mean",
                       enabled: bool = True) -> FilterResult:
    """Filter POI tracks with eq. (10)-(11) and average them with eq. (12).

    Parameters
    ----------
    dx, dy : ndarray, shape (F, P)
        Per-POI displacement tracks in pixels; NaN where unknown. May be
        on disk (anything indexable by blocks of rows): they are read in blocks of frames, never whole.
    valid : ndarray of bool, shape (F,), optional
        Frames usable for the statistics (occluded frames False).
    reference_row : int
        Row of the reference frame, whose values are the offsets removed.
    offset : (ndarray, ndarray) of shape (P,), optional
        Offsets to remove instead (when the reference frame is not among the rows).
    threshold_ratio : float
        Eq. (10) threshold as a fraction of the median over POIs of ``max_t |d_m|``
        (the paper thresholds "with its median value").
    threshold_px : float, optional
        Absolute eq. (10) threshold in pixels; overrides ``threshold_ratio``.
    mcr_threshold : float
        Eq. (11) threshold on the mean cross-correlation, in [-1, 1].
    average : {"mean", "median"}
        Eq. (12) average, or the robust median alternative.
    enabled : bool
        False skips eq. (10)-(11) (the KLT baseline averages without filtering).
    """
    if average not in ("mean", "median"):
        raise ValueError(f"average {average!r} unknown; use 'mean' or 'median'")
    n_frames, n_points = dx.shape
    if offset is None:
        offset_x, offset_y = reference_offset(dx, reference_row), reference_offset(dy, reference_row)
    else:
        offset_x, offset_y = (np.asarray(o, np.float64) for o in offset)
    valid = np.ones(n_frames, bool) if valid is None else np.asarray(valid, bool)
    notes: list[str] = []
    kept = np.ones(n_points, bool)
    kept_threshold = kept.copy()
    mcr = np.full(n_points, np.nan)
    threshold = 0.0
    if enabled and n_points > 1 and valid.sum() >= 3:
        peak = np.full(n_points, -np.inf)
        for rows, bx, by in row_blocks(dx, dy, offset_x, offset_y):
            magnitude = np.hypot(bx[valid[rows]], by[valid[rows]])
            if magnitude.size:
                peak = np.maximum(peak, np.where(np.isfinite(magnitude), magnitude, -np.inf).max(axis=0))
        peak[~np.isfinite(peak)] = 0.0
        threshold = float(threshold_px) if threshold_px is not None else threshold_ratio * float(np.median(peak))
        kept_threshold = peak >= threshold
        if not kept_threshold.any():
            notes.append("eq. (10) removed every POI; kept all")
            kept_threshold[:] = True
        idx = np.flatnonzero(kept_threshold)

        def samples() -> Iterator[np.ndarray]:
            # Both axes as samples of one track, so the correlation follows the 2-D motion; the
            # axis with more motion dominates naturally (tracks centred, not per-axis scaled).
            for axis in (0, 1):
                for rows, bx, by in row_blocks(dx, dy, offset_x, offset_y, columns=idx):
                    yield (bx, by)[axis][valid[rows]]

        mcr[idx] = _mcr_streaming(samples, len(idx))
        kept = np.zeros(n_points, bool)
        kept[idx] = mcr[idx] >= mcr_threshold
        if not kept.any():
            notes.append(f"eq. (11) removed every POI (max mcr {np.nanmax(mcr):.2f}); kept eq. (10) survivors")
            kept = kept_threshold.copy()
    out_x, out_y = average_tracks(dx, dy, kept, (offset_x, offset_y), average=average)
    return FilterResult(out_x, out_y, kept, kept_threshold, mcr, threshold, notes)


def average_tracks(dx: np.ndarray, dy: np.ndarray, kept: np.ndarray,
                   offset: tuple[np.ndarray, np.ndarray], *, average: str = "mean") -> tuple[np.ndarray, np.ndarray]:
    """Eq. (12): frame-by-frame mean (or median) of the kept POIs' offset-free tracks."""
    n_frames = dx.shape[0]
    out_x = np.full(n_frames, np.nan)
    out_y = np.full(n_frames, np.nan)
    if not kept.any():
        return out_x, out_y
    reducer = np.nanmean if average == "mean" else np.nanmedian
    with np.errstate(all="ignore"), warnings.catch_warnings():
        # Frames where every kept POI is NaN average to NaN: no 'Mean of empty slice' noise.
        warnings.simplefilter("ignore", RuntimeWarning)
        for rows, bx, by in row_blocks(dx, dy, *offset, columns=kept):
            out_x[rows] = reducer(bx, axis=1)
            out_y[rows] = reducer(by, axis=1)
    return out_x, out_y
