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

References
----------
Paper section 3.7, eq. (10)-(12).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


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


def remove_offset(d: np.ndarray, reference_row: int = 0) -> np.ndarray:
    """Subtract each POI's value at the reference frame (NaN-safe: first finite value)."""
    d = np.asarray(d, np.float64)
    if d.shape[0] == 0:
        return d
    offset = d[reference_row].copy()
    missing = ~np.isfinite(offset)
    if missing.any():
        # A POI without a value at the reference frame takes its first finite value.
        finite = np.isfinite(d[:, missing])
        first = np.where(finite.any(0), finite.argmax(0), 0)
        offset[missing] = d[first, np.flatnonzero(missing)]
    return d - np.where(np.isfinite(offset), offset, 0.0)


def mean_cross_correlation(tracks: np.ndarray) -> np.ndarray:
    """Eq. (11): mean over ``j != m`` of the correlation of track ``m`` with track ``j``.

    ``tracks`` is ``(T, P)`` (axes may be stacked along T). Uses
    ``mean_j R_mj = z_m . (sum_j z_j - z_m) / (T (P-1))`` with z-scored tracks, so the
    ``P x P`` matrix is never built (thousands of POIs stay cheap). NaNs count as the
    track's mean (zero after z-scoring).
    """
    tracks = np.asarray(tracks, np.float64)
    n_samples, n_points = tracks.shape
    if n_points < 2 or n_samples < 2:
        return np.ones(n_points)
    mean = np.nanmean(tracks, axis=0)
    centred = np.where(np.isfinite(tracks), tracks - mean, 0.0)
    std = np.sqrt(np.mean(centred**2, axis=0))
    z = np.divide(centred, std, out=np.zeros_like(centred), where=std > 0)
    total = z.sum(axis=1)
    return (z * (total[:, None] - z)).sum(axis=0) / (n_samples * (n_points - 1))


def filter_and_average(dx: np.ndarray, dy: np.ndarray, *, valid: np.ndarray | None = None,
                       reference_row: int = 0, threshold_ratio: float = 0.5,
                       threshold_px: float | None = None, mcr_threshold: float = 0.5,
                       average: str = "mean", enabled: bool = True) -> FilterResult:
    """Filter POI tracks with eq. (10)-(11) and average them with eq. (12).

    Parameters
    ----------
    dx, dy : ndarray, shape (F, P)
        Per-POI displacement tracks in pixels; NaN where unknown.
    valid : ndarray of bool, shape (F,), optional
        Frames usable for the statistics (occluded frames False).
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
    dx = remove_offset(dx, reference_row)
    dy = remove_offset(dy, reference_row)
    n_frames, n_points = dx.shape
    valid = np.ones(n_frames, bool) if valid is None else np.asarray(valid, bool)
    notes: list[str] = []
    kept = np.ones(n_points, bool)
    kept_threshold = kept.copy()
    mcr = np.full(n_points, np.nan)
    threshold = 0.0
    if enabled and n_points > 1 and valid.sum() >= 3:
        magnitude = np.hypot(dx[valid], dy[valid])
        with np.errstate(all="ignore"):
            peak = np.nanmax(np.where(np.isfinite(magnitude), magnitude, -np.inf), axis=0)
        peak[~np.isfinite(peak)] = 0.0
        threshold = float(threshold_px) if threshold_px is not None else threshold_ratio * float(np.median(peak))
        kept_threshold = peak >= threshold
        if not kept_threshold.any():
            notes.append("eq. (10) removed every POI; kept all")
            kept_threshold[:] = True
        idx = np.flatnonzero(kept_threshold)
        # Stack both axes so the correlation follows the 2-D motion; the axis with more
        # motion dominates naturally because tracks are centred but not per-axis scaled.
        stacked = np.vstack([dx[valid][:, idx], dy[valid][:, idx]])
        mcr[idx] = mean_cross_correlation(stacked)
        kept = np.zeros(n_points, bool)
        kept[idx] = mcr[idx] >= mcr_threshold
        if not kept.any():
            notes.append(f"eq. (11) removed every POI (max mcr {np.nanmax(mcr):.2f}); kept eq. (10) survivors")
            kept = kept_threshold.copy()
    reducer = np.nanmean if average == "mean" else np.nanmedian
    with np.errstate(all="ignore"), _quiet():
        out_x = reducer(dx[:, kept], axis=1) if kept.any() else np.full(n_frames, np.nan)
        out_y = reducer(dy[:, kept], axis=1) if kept.any() else np.full(n_frames, np.nan)
    return FilterResult(out_x, out_y, kept, kept_threshold, mcr, threshold, notes)


class _quiet:
    """Silence 'Mean of empty slice' for frames where every POI is NaN."""

    def __enter__(self) -> None:
        import warnings

        self._ctx = warnings.catch_warnings()
        self._ctx.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: object) -> None:
        self._ctx.__exit__(*exc)
