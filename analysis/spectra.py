"""Power spectra and aliasing of modes above Nyquist (peak picking: :mod:`refflow.spectra`)."""

from __future__ import annotations

import numpy as np
from scipy import signal


def welch_psd(x: np.ndarray, rate_hz: float, *, segment_s: float | None = None,
              nperseg: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD (Hann, 50 % overlap, mean removed) in units^2/Hz.

    ``sum(psd) * df`` equals the variance of ``x`` (Parseval), so PSDs of
    signals at different rates are directly comparable.
    """
    x = np.asarray(x, float)
    if x.ndim != 1 or x.size < 4 or not np.all(np.isfinite(x)):
        raise ValueError(f"welch_psd needs a finite 1-D signal of >= 4 samples, got shape {x.shape}")
    if nperseg is None:
        nperseg = x.size if segment_s is None else int(round(segment_s * rate_hz))
    nperseg = int(min(max(nperseg, 4), x.size))
    freq, psd = signal.welch(x, fs=rate_hz, window="hann", nperseg=nperseg,
                             noverlap=nperseg // 2, detrend="constant", scaling="density")
    return freq, psd


def alias_frequency(freq_hz: float | np.ndarray, rate_hz: float) -> float | np.ndarray:
    """Apparent frequency of ``freq_hz`` sampled at ``rate_hz`` (folded into [0, rate/2]).

    >>> alias_frequency(71.5, 60.0)
    11.5
    """
    f = np.asarray(freq_hz, float)
    folded = np.abs(f - rate_hz * np.round(f / rate_hz))
    return float(folded) if folded.ndim == 0 else folded


def nearest_peak(peaks: list[dict[str, float]], target_hz: float, tol_hz: float) -> dict[str, float] | None:
    """The strongest peak within ``tol_hz`` of ``target_hz`` (or ``None``)."""
    near = [p for p in peaks if abs(p["freq_hz"] - target_hz) <= tol_hz]
    return max(near, key=lambda p: p["psd"]) if near else None


def band_power(freq: np.ndarray, psd: np.ndarray, lo_hz: float, hi_hz: float) -> float:
    """Integral of the PSD over ``lo_hz <= f <= hi_hz`` (units^2)."""
    freq = np.asarray(freq, float)
    sel = (freq >= lo_hz) & (freq <= hi_hz)
    df = freq[1] - freq[0] if freq.size > 1 else 0.0
    return float(np.sum(np.asarray(psd)[sel]) * df)
