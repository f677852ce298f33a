"""Align the 1 kHz reference with frame-rate measurements.

Conventions
-----------
* Both signals carry the sign of world x (``docs/formats.md``); no sign is
  flipped silently. If the best correlation is negative the result says so
  (``sign_flip_suspected``) instead of flipping.
* ``lag_s`` is defined so that the measurement at camera time ``t`` matches
  the reference at sensor time ``t + lag_s``.
* Frames flagged ``valid=0`` (or with NaN displacement) take no part in the
  lag fit.

The reference is low-passed with a zero-phase 3rd-order Butterworth filter
at 30 Hz (``sosfiltfilt``), as in the paper (section 4.3), before the
comparison: this removes modes the camera cannot resolve and adds no delay.

References
----------
.. [1] Won, J. et al. (2019) "Non-target structural displacement measurement
   using reference frame-based Deepflow", Sensors 19(9), 2992, section 4.3.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import interpolate, optimize, signal


def lowpass(x: np.ndarray, rate_hz: float, *, cutoff_hz: float = 30.0, order: int = 3) -> np.ndarray:
    """Zero-phase Butterworth low-pass (``sosfiltfilt``)."""
    if not 0 < cutoff_hz < rate_hz / 2:
        raise ValueError(f"cutoff_hz={cutoff_hz} must lie in (0, {rate_hz / 2}) for rate {rate_hz} Hz")
    sos = signal.butter(order, cutoff_hz, btype="low", fs=rate_hz, output="sos")
    return signal.sosfiltfilt(sos, np.asarray(x, dtype=float))


def xcorr_lag(x: np.ndarray, y: np.ndarray, *, max_lag: float | None = None) -> float:
    """Sub-sample lag ``d`` (in samples) such that ``y[n] ~ x[n - d]``.

    The integer peak of the FFT cross-correlation is refined by maximising the
    band-limited (Fourier-interpolated) correlation over a continuous lag,
    started from a parabolic fit through the peak and its neighbours.
    """
    x = np.asarray(x, float) - np.mean(x)
    y = np.asarray(y, float) - np.mean(y)
    if x.shape != y.shape or x.ndim != 1:
        raise ValueError(f"x and y must be 1-D and the same length, got {x.shape} and {y.shape}")
    n = x.size
    nfft = 1 << int(np.ceil(np.log2(2 * n)))
    cross = np.conj(np.fft.rfft(x, nfft)) * np.fft.rfft(y, nfft)
    corr = np.fft.irfft(cross, nfft)
    lags = np.arange(nfft)
    lags[lags >= nfft // 2] -= nfft
    keep = np.abs(lags) < n if max_lag is None else np.abs(lags) <= max_lag
    k = int(np.flatnonzero(keep)[np.argmax(corr[keep])])
    c0, cm, cp = corr[k], corr[(k - 1) % nfft], corr[(k + 1) % nfft]
    denom = cm - 2 * c0 + cp
    start = lags[k] + (0.5 * (cm - cp) / denom if denom < 0 else 0.0)
    omega = 2 * np.pi * np.fft.rfftfreq(nfft)
    weights = np.full(omega.size, 2.0)
    weights[0] = 1.0
    if nfft % 2 == 0:
        weights[-1] = 1.0

    def negative_corr(lag: float) -> float:
        return -float(np.sum(weights * np.real(cross * np.exp(1j * omega * lag))))

    res = optimize.minimize_scalar(negative_corr, bounds=(start - 1.0, start + 1.0),
                                   method="bounded", options={"xatol": 1e-6})
    return float(res.x)


@dataclass
class Alignment:
    """Reference resampled at the measurement's frame times."""

    lag_s: float
    ref_mm: np.ndarray  # filtered reference at t_frame + lag_s
    corr: float  # correlation coefficient at the chosen lag (valid frames)
    sign_flip_suspected: bool
    used_frames: int


def _reference_spline(ref_t: np.ndarray, ref_mm: np.ndarray):
    return interpolate.make_interp_spline(ref_t, ref_mm, k=3)


def estimate_offset(ref_t: np.ndarray, ref_mm: np.ndarray, meas_t: np.ndarray, meas_mm: np.ndarray,
                    *, valid: np.ndarray | None = None, max_lag_s: float = 0.1,
                    center_s: float = 0.0, highpass_hz: float | None = None) -> tuple[float, float]:
    """Clock offset ``lag_s`` between a dense reference and sparse measurements.

    The search covers ``center_s +- max_lag_s``. Keep ``max_lag_s`` below half
    the period of the dominant mode (0.104 s at 4.8 Hz): a decaying single
    mode looks alike one period later, so a wider window can lock onto the
    wrong cycle; centre the window on a nominal offset (e.g. the camera's
    recorded start time) instead of widening it.

    Coarse: correlation coefficient on a grid of lags one reference sample
    apart (the reference is evaluated at ``meas_t + lag`` by a cubic spline),
    parabolic interpolation of the peak. Fine: minimise the mean-removed
    squared error over a continuous lag near that peak.

    With ``highpass_hz`` both series are high-passed (zero-phase, 2nd order)
    *at the frame rate, after resampling*, so the filter acts identically on
    both; drift and post-occlusion offsets of a poor tracker - slow, large
    errors - then cannot pull the lag. Invalid frames are bridged linearly
    for that filter and left out of the fit.

    Returns
    -------
    lag_s, corr : float
        Offset in seconds and the correlation coefficient there.
    """
    ref_t = np.asarray(ref_t, float)
    meas_t = np.asarray(meas_t, float)
    meas_mm = np.asarray(meas_mm, float)
    use = np.isfinite(meas_mm) if valid is None else (np.asarray(valid) != 0) & np.isfinite(meas_mm)
    if use.sum() < 8:
        raise ValueError(f"only {int(use.sum())} valid frames: need at least 8 to estimate the offset")
    spline = _reference_spline(ref_t, ref_mm)
    dt = float(np.median(np.diff(ref_t)))
    # only frames whose reference exists at every candidate lag, so all lags
    # are scored on the same frames
    span = min(max_lag_s, 0.25 * (meas_t[use][-1] - meas_t[use][0]))
    inside = (meas_t + center_s - span >= ref_t[0]) & (meas_t + center_s + span <= ref_t[-1])
    if (use & inside).sum() < 8:
        raise ValueError(f"reference ({ref_t[0]:.3f}..{ref_t[-1]:.3f} s) does not cover the "
                         f"measurement ({meas_t[0]:.3f}..{meas_t[-1]:.3f} s) at lag "
                         f"{center_s:.3f} +- {span:.3f} s: check the clocks or max_lag_s")
    t = meas_t[inside]
    keep = use[inside]
    series = np.interp(t, t[keep], meas_mm[inside][keep])
    fps = 1.0 / float(np.median(np.diff(t)))
    sos = None
    if highpass_hz and highpass_hz < 0.25 * fps and t.size > 30:
        sos = signal.butter(2, highpass_hz, btype="high", fs=fps, output="sos")
        series = signal.sosfiltfilt(sos, series)
    y = series[keep] - series[keep].mean()
    y_norm = y / (np.linalg.norm(y) or 1.0)

    def ref_rows(lags: np.ndarray) -> np.ndarray:
        rows = spline(t[None, :] + lags[:, None])
        if sos is not None:
            rows = signal.sosfiltfilt(sos, rows, axis=1)
        rows = rows[:, keep]
        return rows - rows.mean(axis=1, keepdims=True)

    lo, hi = center_s - span, center_s + span
    grid = np.arange(np.ceil(lo / dt), np.floor(hi / dt) + 1) * dt
    corrs = np.empty(grid.size)
    block = 128  # bounded memory: block x frames
    for start in range(0, grid.size, block):
        rows = ref_rows(grid[start:start + block])
        corrs[start:start + block] = rows @ y_norm / np.maximum(np.linalg.norm(rows, axis=1), 1e-300)
    # the signed maximum: a sign error must show as a poor fit, not be hidden
    k = int(np.argmax(corrs))
    lag0 = grid[k]
    if 0 < k < grid.size - 1:
        cm, c0, cp = corrs[k - 1:k + 2]
        denom = cm - 2 * c0 + cp
        if denom < 0:
            lag0 += dt * 0.5 * (cm - cp) / denom

    def sse(lag: float) -> float:
        return float(np.sum((y - ref_rows(np.array([lag]))[0]) ** 2))

    res = optimize.minimize_scalar(sse, bounds=(max(lo, lag0 - dt), min(hi, lag0 + dt)),
                                   method="bounded", options={"xatol": 1e-7})
    lag = float(res.x)
    r = ref_rows(np.array([lag]))[0]
    return lag, float(np.dot(r, y_norm) / (np.linalg.norm(r) or 1.0))


def align(ref_t: np.ndarray, ref_mm: np.ndarray, meas_t: np.ndarray, meas_mm: np.ndarray, *,
          valid: np.ndarray | None = None, cutoff_hz: float = 30.0, order: int = 3,
          max_lag_s: float = 0.1, lag_s: float | None = None, highpass_hz: float | None = 0.5,
          center_s: float = 0.0) -> Alignment:
    """Low-pass the reference, estimate the clock offset, resample at frame times.

    For the offset fit only, both series are high-passed at ``highpass_hz``
    (see :func:`estimate_offset`). Pass ``lag_s`` to skip the estimate.
    """
    ref_t = np.asarray(ref_t, float)
    rate = 1.0 / float(np.median(np.diff(ref_t)))
    filtered = lowpass(ref_mm, rate, cutoff_hz=cutoff_hz, order=order)
    meas_t = np.asarray(meas_t, float)
    valid_mask = np.ones(meas_t.size, bool) if valid is None else np.asarray(valid) != 0
    valid_mask &= np.isfinite(meas_mm)
    if lag_s is None:
        lag_s, _ = estimate_offset(ref_t, filtered, meas_t, meas_mm, valid=valid_mask,
                                   max_lag_s=max_lag_s, center_s=center_s, highpass_hz=highpass_hz)
    spline = _reference_spline(ref_t, filtered)
    shifted = meas_t + lag_s
    inside = (shifted >= ref_t[0]) & (shifted <= ref_t[-1])
    ref_at_frames = np.full(meas_t.size, np.nan)
    ref_at_frames[inside] = spline(shifted[inside])
    use = valid_mask & inside
    a, b = ref_at_frames[use], np.asarray(meas_mm, float)[use]
    corr = float(np.corrcoef(a, b)[0, 1]) if use.sum() > 2 and a.std() > 0 and b.std() > 0 else float("nan")
    return Alignment(lag_s=float(lag_s), ref_mm=ref_at_frames, corr=corr,
                     sign_flip_suspected=bool(corr < 0), used_frames=int(use.sum()))


def datum_offset(time_s: np.ndarray, ref_mm: np.ndarray, meas_mm: np.ndarray, valid: np.ndarray,
                 *, datum_s: float = 0.25) -> float:
    """Offset that puts a measurement into the reference's datum.

    Trackers report motion relative to their first (reference) frame, the
    laser relative to the beam at rest; a plucked beam is held deflected when
    the video starts, so the two differ by a constant. We take the median of
    ``ref - meas`` over the first ``datum_s`` seconds of valid frames (the
    hold before a pluck; ``datum_s=0``: the first valid frame only). The
    median resists noise; a tracker with a scale error shifts the datum if
    the structure moves in that window. Add the result to the measurement.
    Errors change by this one constant only; bias and drift are judged after it.
    """
    ok = (np.asarray(valid) != 0) & np.isfinite(ref_mm) & np.isfinite(meas_mm)
    if not ok.any():
        return 0.0
    t0 = time_s[ok][0]
    first = ok & (time_s <= t0 + datum_s)
    return float(np.median(ref_mm[first] - meas_mm[first]))
