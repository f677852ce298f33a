"""Output-only modal identification: natural frequencies, damping ratios, mode shapes.

Peaks are found by frequency-domain decomposition (first singular value of
the cross-spectral matrix, FDD [1]_); frequencies, damping ratios and shapes
come from covariance-driven stochastic subspace identification (SSI-cov
[2]_) over a range of model orders, taking the median of the poles that fall
near each FDD peak (a one-line stabilisation criterion). Works on free decay
and on ambient response alike, since both give output correlations of the
form ``C A^k G``.

Shared by the measurement tool (``refflow modal`` on a user's own
measurement, :mod:`flow.modal`) and the workbench (``analysis.modal``
compares the result with the simulated beam's model). It sees only the
response it is given: no model, no ground truth.

References
----------
.. [1] Brincker, R., Zhang, L., Andersen, P. (2001) "Modal identification of
   output-only systems using frequency domain decomposition", Smart Mater.
   Struct. 10, 441-445.
.. [2] Peeters, B., De Roeck, G. (1999) "Reference-based stochastic subspace
   identification for output-only modal analysis", Mech. Syst. Signal
   Process. 13(6), 855-878.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy import signal


def mac(a: np.ndarray, b: np.ndarray) -> float:
    """Modal assurance criterion of two (possibly complex) shape vectors."""
    a = np.asarray(a).ravel()
    b = np.asarray(b).ravel()
    num = abs(np.vdot(a, b)) ** 2
    den = float(np.real(np.vdot(a, a)) * np.real(np.vdot(b, b)))
    return float(num / den) if den > 0 else float("nan")


def _real_shape(phi: np.ndarray) -> np.ndarray:
    """Rotate a complex shape onto the real axis and normalise (largest |.| = +1)."""
    phi = np.asarray(phi, complex)
    k = int(np.argmax(np.abs(phi)))
    real = np.real(phi * np.exp(-1j * np.angle(phi[k])))
    return real / real[k]


def _decimate(y: np.ndarray, rate_hz: float, band_hz: float) -> tuple[np.ndarray, float]:
    q = int(rate_hz // (2.5 * 2 * band_hz))
    out = y
    while q > 1:
        step = min(q, 10)
        out = signal.decimate(out, step, ftype="fir", axis=1, zero_phase=True)
        rate_hz /= step
        q //= step
    return out, rate_hz


def fdd_peaks(y: np.ndarray, rate_hz: float, *, n_modes: int, band_hz: tuple[float, float],
              segment_s: float = 20.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """First singular value of the CSD matrix and its strongest ``n_modes`` peaks.

    Returns ``(freq_hz, s1, peak_freqs_hz)`` with peaks sorted by frequency.
    """
    n_ch, n = y.shape
    nperseg = int(min(n, round(segment_s * rate_hz)))
    freq, _ = signal.welch(y[0], fs=rate_hz, nperseg=nperseg)
    g = np.empty((freq.size, n_ch, n_ch), complex)
    for a in range(n_ch):
        for b in range(a, n_ch):
            _, pab = signal.csd(y[a], y[b], fs=rate_hz, nperseg=nperseg)
            g[:, a, b] = pab
            g[:, b, a] = np.conj(pab)
    s1 = np.linalg.svd(g, compute_uv=False)[:, 0]
    in_band = (freq >= band_hz[0]) & (freq <= band_hz[1])
    if not in_band.any():
        raise ValueError(f"no spectral lines in band {band_hz} Hz at {rate_hz} Hz sampling")
    log_s1 = np.log10(np.maximum(s1, s1[in_band].max() * 1e-15))
    log_s1[~in_band] = log_s1[in_band].min()
    # rank by prominence in decades, not by height: a lightly damped mode is a
    # sharp, tall-over-its-valleys peak even when far weaker than mode 1, while
    # leakage bumps beside mode 1 are high but not prominent
    idx, props = signal.find_peaks(log_s1, prominence=0.3)
    order = np.argsort(-props["prominences"])
    df = freq[1] - freq[0]
    chosen: list[float] = []
    for i in idx[order]:
        a, b, c = log_s1[i - 1], log_s1[i], log_s1[i + 1]
        denom = a - 2 * b + c
        f_peak = float(freq[i] + (0.5 * (a - c) / denom if denom < 0 else 0.0) * df)
        if all(abs(f_peak - f) > max(0.15 * f, 5 * df) for f in chosen):
            chosen.append(f_peak)
        if len(chosen) == n_modes:
            break
    return freq, s1, np.sort(chosen)


def _toeplitz_svd(y: np.ndarray, block_rows: int) -> tuple[np.ndarray, np.ndarray]:
    """SVD of the block Toeplitz matrix of output correlations (shared by all orders)."""
    n_ch, n = y.shape
    i = block_rows
    # every lag sums over the same m samples: then R_k = C A^k (sum x x^T) C^T
    # holds exactly for a free decay whether or not it has died out by the end
    # (1/n biases damping up on a ringing record, 1/(n-k) down on a decayed one)
    m = n - 2 * i
    if m < 2 * i:
        raise ValueError(f"record of {n} samples is too short for {i} block rows")
    r = [y[:, k:k + m] @ y[:, :m].T / m for k in range(2 * i)]
    toeplitz = np.block([[r[i + a - b] for b in range(i)] for a in range(i)])
    u, s, _ = np.linalg.svd(toeplitz)
    return u, s


def ssi_cov_poles(y: np.ndarray, rate_hz: float, *, order: int, block_rows: int,
                  svd: tuple[np.ndarray, np.ndarray] | None = None) -> dict[str, np.ndarray]:
    """Poles of one SSI-cov model: ``freq_hz``, ``damping_ratio``, complex ``shapes`` (n_ch, m)."""
    n_ch = y.shape[0]
    u, s = svd if svd is not None else _toeplitz_svd(y, block_rows)
    obs = u[:, :order] * np.sqrt(s[:order])
    c = obs[:n_ch]
    a = np.linalg.lstsq(obs[:-n_ch], obs[n_ch:], rcond=None)[0]
    lam, vec = np.linalg.eig(a)
    keep = np.imag(lam) > 0
    lam, vec = lam[keep], vec[:, keep]
    s_cont = np.log(lam) * rate_hz
    wn = np.abs(s_cont)
    return {"freq_hz": wn / (2 * np.pi), "damping_ratio": -np.real(s_cont) / wn, "shapes": c @ vec}


def still_samples(y: np.ndarray, *, frac: float = 0.01) -> int:
    """Samples at the start where the structure is held still (e.g. before a pluck release).

    A held static shape is no part of the free response; left in, its step
    adds broadband power and spurious FDD peaks.
    """
    dev = np.abs(y - y[:, :1])
    limit = frac * np.maximum(np.ptp(y, axis=1, keepdims=True), 1e-300)
    moving = np.flatnonzero(np.any(dev > limit, axis=0))
    return int(max(moving[0] - 1, 0)) if moving.size else 0


def identify(y: np.ndarray, rate_hz: float, *, n_modes: int = 2, band_hz: tuple[float, float] | None = None,
             orders: range | None = None, block_rows: int | None = None,
             tol_frac: float = 0.05) -> list[dict[str, Any]]:
    """Identify the ``n_modes`` strongest modes from multi-channel response ``y`` (n_ch, n).

    Returns one dict per mode (sorted by frequency): ``freq_hz``,
    ``damping_ratio``, ``shape`` (real, largest component +1), ``fdd_freq_hz``,
    ``fdd_shape``, ``poles_used``. Fewer than ``n_modes`` where the FDD curve
    has fewer prominent peaks in the band.
    """
    return identify_with_diagnostics(y, rate_hz, n_modes=n_modes, band_hz=band_hz, orders=orders,
                                     block_rows=block_rows, tol_frac=tol_frac)[0]


def identify_with_diagnostics(y: np.ndarray, rate_hz: float, *, n_modes: int = 2,
                              band_hz: tuple[float, float] | None = None, orders: range | None = None,
                              block_rows: int | None = None, tol_frac: float = 0.05,
                              ) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """:func:`identify`, and what it decided from: ``(modes, diagnostics)``.

    ``diagnostics`` (for a stabilisation diagram): ``rate_hz`` (after the
    decimation to the band), ``band_hz``, ``still_samples`` (the held start
    left out), ``freq_hz`` and ``s1`` (the FDD curve: first singular value of
    the cross-spectral matrix, units^2/Hz), ``peak_hz`` (its picked peaks),
    ``block_rows``, ``orders`` and ``poles`` (one :func:`ssi_cov_poles` dict
    per order), ``tol_frac`` (poles within this fraction of a peak count).
    """
    y = np.asarray(y, float)
    if y.ndim != 2 or y.shape[0] < 1 or not np.all(np.isfinite(y)):
        raise ValueError(f"y must be a finite (channels, samples) array, got shape {y.shape}")
    held = still_samples(y)
    y = y[:, held:]
    y = y - y.mean(axis=1, keepdims=True)
    if band_hz is None:
        band_hz = (0.5, 0.4 * rate_hz)
    yd, fs = _decimate(y, rate_hz, band_hz[1])
    freq, s1, peak_hz = fdd_peaks(yd, fs, n_modes=n_modes, band_hz=band_hz)
    # FDD shapes: first singular vector of the CSD matrix at each peak
    n_ch = yd.shape[0]
    nperseg = int(min(yd.shape[1], round(20.0 * fs)))
    g = np.empty((freq.size, n_ch, n_ch), complex)
    for a_ in range(n_ch):
        for b_ in range(n_ch):
            _, g[:, a_, b_] = signal.csd(yd[a_], yd[b_], fs=fs, nperseg=nperseg)
    if block_rows is None:
        # cover a couple of periods of the lowest mode, keep the matrix small
        block_rows = int(np.clip(2 * fs / max(peak_hz[0], 1e-3) / max(n_ch, 1), 10, 80)) if peak_hz.size else 40
        # a short record of a slow mode: as many block rows as the record holds (>= 4 per row)
        block_rows = max(1, min(block_rows, yd.shape[1] // 4))
    if orders is None:
        orders = range(2 * n_modes, min(2 * n_modes + 40, block_rows * n_ch), 2)
    svd = _toeplitz_svd(yd, block_rows)
    poles = [ssi_cov_poles(yd, fs, order=o, block_rows=block_rows, svd=svd) for o in orders]
    modes = []
    for fp in peak_hz:
        fs_, zs, shapes = [], [], []
        for pol in poles:
            near = np.flatnonzero((np.abs(pol["freq_hz"] - fp) <= tol_frac * fp)
                                  & (pol["damping_ratio"] > 0) & (pol["damping_ratio"] < 0.3))
            if near.size:
                j = near[np.argmin(np.abs(pol["freq_hz"][near] - fp))]
                fs_.append(pol["freq_hz"][j])
                zs.append(pol["damping_ratio"][j])
                shapes.append(_real_shape(pol["shapes"][:, j]))
        k = int(np.argmin(np.abs(freq - fp)))
        fdd_shape = _real_shape(np.linalg.svd(g[k])[0][:, 0])
        if fs_:
            mid = int(np.argsort(fs_)[len(fs_) // 2])
            modes.append({"freq_hz": float(np.median(fs_)), "damping_ratio": float(np.median(zs)),
                          "shape": shapes[mid].tolist(), "fdd_freq_hz": float(fp),
                          "fdd_shape": fdd_shape.tolist(), "poles_used": len(fs_)})
        else:
            modes.append({"freq_hz": float(fp), "damping_ratio": float("nan"), "shape": fdd_shape.tolist(),
                          "fdd_freq_hz": float(fp), "fdd_shape": fdd_shape.tolist(), "poles_used": 0})
    diagnostics = {"rate_hz": fs, "band_hz": tuple(band_hz), "still_samples": held, "freq_hz": freq, "s1": s1,
                   "peak_hz": peak_hz, "block_rows": block_rows, "orders": list(orders), "poles": poles,
                   "tol_frac": tol_frac}
    return modes, diagnostics


def stabilisation(poles: list[dict[str, np.ndarray]], *, freq_tol: float = 0.01, damping_tol: float = 0.05,
                  mac_min: float = 0.98) -> list[np.ndarray]:
    """Stability class of each pole against the poles of the model order before it.

    Returns, per model order, an int array over that order's poles: 0 new (no pole of the
    previous order within ``freq_tol`` of its frequency), 1 stable in frequency, 2 stable in
    frequency, damping (within ``damping_tol`` of it, relative) and shape (MAC >= ``mac_min``)
    -- the usual criteria of a stabilisation diagram (1 %, 5 %, 0.98). The first order's poles
    are all new.
    """
    classes = []
    previous: dict[str, np.ndarray] | None = None
    for pol in poles:
        cls = np.zeros(pol["freq_hz"].size, int)
        if previous is not None and previous["freq_hz"].size:
            for j, (f, z) in enumerate(zip(pol["freq_hz"], pol["damping_ratio"], strict=True)):
                k = int(np.argmin(np.abs(previous["freq_hz"] - f)))
                if abs(previous["freq_hz"][k] - f) > freq_tol * f:
                    continue
                cls[j] = 1
                z_prev = previous["damping_ratio"][k]
                if (abs(z_prev - z) <= damping_tol * abs(z)
                        and mac(pol["shapes"][:, j], previous["shapes"][:, k]) >= mac_min):
                    cls[j] = 2
        classes.append(cls)
        previous = pol
    return classes
