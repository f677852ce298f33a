"""Multi-point modal identification of the workbench beam, compared with its model.

The identification itself (FDD peaks + SSI-cov over model orders: ``identify``,
``fdd_peaks``, ``ssi_cov_poles``, ``mac``, ``still_samples``) is shared with the
measurement tool and lives in :mod:`refflow.modal`; it is re-exported here for the
workbench's callers. What is the workbench's own stays here: the Euler-Bernoulli
cantilever shapes of the simulated beam, the model's damping from ``sim.json``, and
the comparison of identified modes with the model.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from refflow.modal import fdd_peaks, identify, mac, ssi_cov_poles, still_samples

__all__ = ["cantilever_shape", "compare_with_model", "fdd_peaks", "identify", "mac", "model_damping",
           "ssi_cov_poles", "still_samples"]

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
