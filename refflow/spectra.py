"""Spectral peak picking, shared by ``flow`` (the dominant frequency of a measurement) and
``analysis`` (modes in the PSDs of the measurement and the reference)."""

from __future__ import annotations

import numpy as np

# scipy.signal (about a second to import) is imported where it is used: `refflow track` imports
# this module through flow.figures and never picks a peak.


def pick_peaks(freq: np.ndarray, spectrum: np.ndarray, *, count: int | None = None,
               min_hz: float = 0.0, rel_prominence: float = 1e-3) -> list[dict[str, float]]:
    """Local maxima of a spectrum at or above ``min_hz``, strongest first, refined by a parabola.

    The peak frequency is refined by a parabola through the log-spectrum at the
    peak bin and its neighbours (for a Hann window this is accurate to a small
    fraction of a bin). Only local maxima count: the edge of the band searched, or
    the Nyquist bin, where a spectrum merely falls or rises, is not a peak.

    Parameters
    ----------
    freq : (N,) array
        Evenly spaced frequencies, Hz.
    spectrum : (N,) array
        Power spectral density or amplitude spectrum on ``freq`` (non-negative).
    count : int, optional
        Keep the ``count`` strongest peaks (default: all).
    min_hz : float
        Ignore peaks below this frequency.
    rel_prominence : float
        Minimum prominence as a fraction of the spectrum's maximum (0: every local maximum).

    Returns
    -------
    list of dict
        ``freq_hz`` (refined) and ``psd`` (the spectrum's value at the peak bin) per peak.
    """
    freq = np.asarray(freq, float)
    spectrum = np.asarray(spectrum, float)
    if freq.shape != spectrum.shape or freq.ndim != 1:
        raise ValueError(f"freq {freq.shape} and spectrum {spectrum.shape} must be 1-D of one length")
    if freq.size < 3:
        return []
    from scipy import signal

    log_spectrum = np.log(np.maximum(spectrum, np.max(spectrum) * 1e-30 + 1e-300))
    idx, _ = signal.find_peaks(spectrum, prominence=rel_prominence * float(np.max(spectrum)))
    peaks = []
    df = freq[1] - freq[0]
    for i in idx:
        if freq[i] < min_hz:
            continue
        a, b, c = log_spectrum[i - 1], log_spectrum[i], log_spectrum[i + 1]
        denom = a - 2 * b + c
        delta = 0.5 * (a - c) / denom if denom < 0 else 0.0
        peaks.append({"freq_hz": float(freq[i] + delta * df), "psd": float(spectrum[i])})
    peaks.sort(key=lambda p: -p["psd"])
    return peaks[:count] if count is not None else peaks
