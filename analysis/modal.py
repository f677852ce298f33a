"""Multi-point modal identification: natural frequencies, damping, mode shapes.

Peaks are found by frequency-domain decomposition (first singular value of
the cross-spectral matrix, FDD [1]_); frequencies, damping ratios and shapes
come from covariance-driven stochastic subspace identification (SSI-cov
[2]_) over a range of model orders, taking the median of the poles that fall
near each FDD peak (a one-line stabilisation criterion). Works on free decay
and on ambient response alike, since both give output correlations of the
form ``C A^k G``.

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

# beta_n L of a clamped-free Euler-Bernoulli beam
_BETA_L = (1.875104068711961, 4.694091132974175, 7.854757438237613, 10.99554073487547)


def cantilever_shape(z_over_l: np.ndarray, mode: int) -> np.ndarray:
    """Euler-Bernoulli clamped-free mode shape ``mode`` (1-based), tip = 1."""
    bl = _BETA_L[mode - 1]
    x = bl * np.asarray(z_over_l, float)
    sigma = (np.cosh(bl) + np.cos(bl)) / (np.sinh(bl) + np.sin(bl))
    phi = np.cosh(x) - np.cos(x) - sigma * (np.sinh(x) - np.sin(x))
    tip = np.cosh(bl) - np.cos(bl) - sigma * (np.sinh(bl) - np.sin(bl))
    return phi / tip


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
    ``fdd_shape``, ``poles_used``.
    """
    y = np.asarray(y, float)
    if y.ndim != 2 or y.shape[0] < 1 or not np.all(np.isfinite(y)):
        raise ValueError(f"y must be a finite (channels, samples) array, got shape {y.shape}")
    y = y[:, still_samples(y):]
    y = y - y.mean(axis=1, keepdims=True)
    if band_hz is None:
        band_hz = (0.5, 0.4 * rate_hz)
    yd, fs = _decimate(y, rate_hz, band_hz[1])
    freq, _, peak_hz = fdd_peaks(yd, fs, n_modes=n_modes, band_hz=band_hz)
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
    return modes


def model_damping(sim_json: dict[str, Any], n_modes: int) -> list[float | None]:
    """Model damping ratios from ``sim.json`` when it states them (several layouts tolerated)."""
    for key in ("damping_ratios", "model_damping_ratio", "damping_ratio", "zeta", "damping"):
        val = sim_json.get(key)
        if isinstance(val, dict):
            for sub in ("ratios", "zeta", "damping_ratio", "modal", "ratio"):
                if sub in val:
                    val = val[sub]
                    break
        if isinstance(val, (int, float)):
            return [float(val)] * n_modes
        if isinstance(val, (list, tuple)) and val and all(isinstance(v, (int, float)) for v in val):
            return [float(v) for v in val[:n_modes]] + [None] * max(0, n_modes - len(val))
    return [None] * n_modes


def compare_with_model(modes: list[dict[str, Any]], heights_mm: np.ndarray, model_hz: np.ndarray,
                       *, beam_length_mm: float, model_zeta: list[float | None] | None = None) -> dict[str, Any]:
    """Frequency/damping errors and MAC against the model.

    Model shapes are the Euler-Bernoulli cantilever shapes at the sensor
    heights (the simulated beam is a clamped-free beam; the MAC is insensitive
    to the small difference between its exact modes and these).
    """
    out: dict[str, Any] = {"heights_mm": np.asarray(heights_mm, float).tolist(), "beam_length_mm": beam_length_mm}
    zeta = model_zeta or [None] * len(modes)
    # match identified modes to model modes by nearest frequency
    for i, mode in enumerate(modes, start=1):
        j = int(np.argmin(np.abs(np.asarray(model_hz) - mode["freq_hz"])))
        f_model = float(model_hz[j])
        shape_model = cantilever_shape(np.asarray(heights_mm) / beam_length_mm, j + 1)
        z_model = zeta[j] if j < len(zeta) else None
        out[f"mode{i}_model_index"] = j + 1
        out[f"mode{i}_freq_hz"] = mode["freq_hz"]
        out[f"mode{i}_freq_model_hz"] = f_model
        out[f"mode{i}_freq_error_pct"] = 100.0 * (mode["freq_hz"] - f_model) / f_model
        out[f"mode{i}_damping_ratio"] = mode["damping_ratio"]
        out[f"mode{i}_damping_model_ratio"] = z_model
        out[f"mode{i}_damping_error_pct"] = (100.0 * (mode["damping_ratio"] - z_model) / z_model
                                             if z_model else None)
        out[f"mode{i}_mac"] = mac(mode["shape"], shape_model)
        out[f"mode{i}_mac_fdd"] = mac(mode["fdd_shape"], shape_model)
        out[f"mode{i}_shape"] = mode["shape"]
        out[f"mode{i}_shape_model"] = (shape_model / shape_model[np.argmax(np.abs(shape_model))]).tolist()
    return out
