"""The shared spectral peak picker (refflow.spectra.pick_peaks) on planted tones, and its two
users: flow's dominant frequency and analysis's mode picking."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from refflow.spectra import pick_peaks

RATE_HZ = 60.0


def _two_tones(strong_hz: float, weak_hz: float, *, duration_s: float = 20.0) -> np.ndarray:
    t = np.arange(0.0, duration_s, 1 / RATE_HZ)
    return 1.0 * np.sin(2 * np.pi * strong_hz * t + 0.3) + 0.4 * np.sin(2 * np.pi * weak_hz * t + 1.1)


def _psd(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    return signal.periodogram(x, fs=RATE_HZ, window="hann")


@pytest.mark.parametrize(("strong_hz", "weak_hz"), [(3.1, 7.3), (7.3, 3.1)])
def test_the_stronger_tone_comes_first(strong_hz, weak_hz):
    freq, psd = _psd(_two_tones(strong_hz, weak_hz))
    df = freq[1] - freq[0]
    peaks = pick_peaks(freq, psd, count=2)
    assert [p["freq_hz"] for p in peaks] == pytest.approx([strong_hz, weak_hz], abs=0.1 * df)
    assert peaks[0]["psd"] > peaks[1]["psd"]
    assert pick_peaks(freq, psd, count=1)[0]["freq_hz"] == pytest.approx(strong_hz, abs=0.1 * df)


def test_a_scaled_frequency_axis_moves_the_answer():
    """The answer is read off the axis it is given: 0.95 x the axis, 0.95 x the peak (-5 %)."""
    freq, psd = _psd(_two_tones(3.1, 7.3))
    right = pick_peaks(freq, psd, count=1)[0]["freq_hz"]
    scaled = pick_peaks(0.95 * freq, psd, count=1)[0]["freq_hz"]
    assert scaled == pytest.approx(0.95 * right, rel=1e-9)
    assert (scaled - 3.1) / 3.1 == pytest.approx(-0.05, abs=0.002)
    assert scaled != pytest.approx(3.1, abs=0.1)


def test_min_hz_leaves_the_next_peak_not_the_band_edge():
    """Above min_hz the strong low tone only falls away: the answer is the weak tone, not the
    first bin searched."""
    freq, psd = _psd(_two_tones(1.0, 7.3))
    peaks = pick_peaks(freq, psd, count=1, min_hz=2.0, rel_prominence=0.0)
    assert peaks[0]["freq_hz"] == pytest.approx(7.3, abs=0.01)


def test_no_peak_in_a_flat_spectrum_and_bad_shapes_refused():
    assert pick_peaks(np.arange(10.0), np.zeros(10), rel_prominence=0.0) == []
    assert pick_peaks(np.arange(2.0), np.ones(2)) == []
    with pytest.raises(ValueError, match="must be 1-D of one length"):
        pick_peaks(np.arange(10.0), np.ones(9))


def test_flow_dominant_frequency_uses_it():
    from flow.figures import dominant_frequency

    t = np.arange(0.0, 20.0, 1 / RATE_HZ)
    values = _two_tones(3.1, 7.3)
    hz, freqs, amplitude = dominant_frequency(t, values)
    assert hz == pytest.approx(3.1, abs=0.01)
    assert hz == pick_peaks(freqs, amplitude, count=1, min_hz=1 / 20.0, rel_prominence=0.0)[0]["freq_hz"]
    # Just above --min-hz the 1 Hz tone's main lobe only falls away: the 7.3 Hz tone is the
    # dominant one there (before the picker was shared, the first bin searched was taken, and
    # its parabola put the answer at 1.007 Hz, below min_hz).
    hz, _, _ = dominant_frequency(t, _two_tones(1.0, 7.3), min_hz=1.04)
    assert hz == pytest.approx(7.3, abs=0.01)
    # A still series has no dominant frequency (it was the first bin searched, 1 / record).
    hz, _, _ = dominant_frequency(t, np.zeros_like(t))
    assert hz is None
