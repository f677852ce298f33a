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

__all__ = ["cantilever_shape", "compare_video_modes", "compare_with_model", "fdd_peaks", "identify", "mac",
           "model_damping", "ssi_cov_poles", "still_samples", "video_modes_by_height"]

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


def video_modes_by_height(video: dict[str, Any], n_heights: int, source: str = "modal_video.json") -> list[dict[str, Any]]:
    """The modes of a ``refflow modal`` JSON of one run of ``n_heights`` regions, each shape
    reordered by region label (region ``k`` = the ``k``-th height, sorted)."""
    points = video.get("points")
    if not isinstance(points, list) or len(points) != n_heights:
        found = len(points) if isinstance(points, list) else "no"
        raise ValueError(f"{source}: {found} points, expected one region per sensor height ({n_heights})")
    labels = [point.get("region") for point in points]
    if sorted(labels, key=lambda v: (v is None, v)) != list(range(1, n_heights + 1)):
        raise ValueError(f"{source}: point regions {labels}, expected the labels 1..{n_heights} of one run")
    order = np.argsort(labels)
    modes = []
    for mode in video.get("modes") or []:
        zeta = mode.get("damping_ratio")
        modes.append({"freq_hz": float(mode["freq_hz"]),
                      "damping_ratio": float("nan") if zeta is None else float(zeta),
                      "shape": np.asarray(mode["shape"], float)[order],
                      "fdd_shape": np.asarray(mode["fdd_shape"], float)[order]})
    if not modes:
        raise ValueError(f"{source}: no modes identified (see its notes and stabilisation diagram)")
    return modes


def compare_video_modes(modes: list[dict[str, Any]], heights_mm: np.ndarray, model_hz: np.ndarray, *,
                        beam_length_mm: float, model_zeta: list[float | None] | None = None,
                        sensor: dict[str, Any] | None = None) -> dict[str, Any]:
    """Modes identified from the video against the model (:func:`compare_with_model`: frequency
    and damping errors, MAC against the Euler-Bernoulli shapes at ``heights_mm``) and, where
    ``sensor`` (the ``analysis modal`` JSON of the simulated laser at the same heights) is given,
    against the modes identified from the simulated sensor (nearest frequency): the video's
    share of the difference from the model."""
    heights = np.asarray(heights_mm, float)
    out = compare_with_model(modes, heights, np.asarray(model_hz, float), beam_length_mm=beam_length_mm,
                             model_zeta=model_zeta)
    out["n_modes"] = len(modes)
    if sensor is None:
        return out
    if not np.allclose(np.asarray(sensor.get("heights_mm", []), float), heights):
        raise ValueError(f"the sensor's modes are at heights {sensor.get('heights_mm')} mm, the video's at "
                         f"{heights.tolist()} mm: identify both at the same heights")
    sensor_hz = []
    while f"mode{len(sensor_hz) + 1}_freq_hz" in sensor:
        sensor_hz.append(float(sensor[f"mode{len(sensor_hz) + 1}_freq_hz"]))
    if not sensor_hz:
        return out
    for i, mode in enumerate(modes, start=1):
        j = int(np.argmin(np.abs(np.asarray(sensor_hz) - mode["freq_hz"]))) + 1
        f_sensor = sensor_hz[j - 1]
        out[f"mode{i}_sensor_index"] = j
        out[f"mode{i}_freq_sensor_hz"] = f_sensor
        out[f"mode{i}_freq_vs_sensor_pct"] = 100.0 * (mode["freq_hz"] - f_sensor) / f_sensor
        out[f"mode{i}_damping_sensor_ratio"] = sensor.get(f"mode{j}_damping_ratio")
        out[f"mode{i}_mac_vs_sensor"] = mac(mode["shape"], np.asarray(sensor[f"mode{j}_shape"], float))
    return out
