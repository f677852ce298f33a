"""Synthetic stage files in the documented formats, for tests and demos.

A cantilever with known modes is sampled by a 1 kHz "laser sensor" and by a
camera whose clock lags the sensor by ``lag_s``; two fake trackers add known
errors (a good one, and a KLT-like one with scale error, drift and an
occlusion offset). Nothing here is imported by the pipeline itself.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .modal import cantilever_shape

MODEL_HZ = (4.8, 24.4, 71.5)
MODEL_ZETA = (0.01, 0.005, 0.004)


def beam_response(time_s: np.ndarray, z_mm: np.ndarray, *, beam_length_mm: float = 1000.0,
                  amplitudes_mm=(2.2, 0.25, 0.05), hold_s: float = 0.5, seed: int = 0) -> np.ndarray:
    """Pluck: held still for ``hold_s``, then free decay of three modes plus a
    little ambient motion; shape (len(z), len(t))."""
    rng = np.random.default_rng(seed)
    time_s = np.maximum(np.asarray(time_s, float) - hold_s, 0.0)
    out = np.zeros((len(z_mm), len(time_s)))
    for m, (f, zeta, amp) in enumerate(zip(MODEL_HZ, MODEL_ZETA, amplitudes_mm, strict=True), start=1):
        wd = 2 * np.pi * f * np.sqrt(1 - zeta ** 2)
        q = amp * np.exp(-zeta * 2 * np.pi * f * time_s) * np.cos(wd * time_s + rng.uniform(0, 2 * np.pi))
        q += 0.05 * amp * np.sin(wd * time_s + rng.uniform(0, 2 * np.pi))  # ambient part
        out += np.outer(cantilever_shape(np.asarray(z_mm) / beam_length_mm, m), q)
    return out


def _write_csv(path: Path, header: list[str], columns: list[np.ndarray], fmt: list[str]) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, np.column_stack(columns), delimiter=",", header=",".join(header),
               comments="", fmt=fmt)


def make_scenario(root: str | Path, *, duration_s: float = 20.0, fps: float = 60.0,
                  mm_per_px: float = 1 / 2.8, lag_s: float = 0.0123, sensor_height_mm: float = 800.0,
                  extra_heights_mm=(250, 500, 750, 1000), occlusion_s: tuple[float, float] | None = (8.0, 9.0),
                  klt_offset_mm: float = 0.4, amplitudes_mm=(2.2, 0.25, 0.05),
                  seed: int = 0) -> dict[str, Path]:
    """Write sim/, render/ and track/{proposed,klt}.csv under ``root``; return the paths.

    ``amplitudes_mm``: the three modes' amplitudes at the pluck (the reference is low-passed
    at 30 Hz, so a perfect camera reads mode 2 stronger than it)."""
    root = Path(root)
    rng = np.random.default_rng(seed + 1)
    t_sensor = np.arange(0.0, duration_s + 1e-9, 1e-3)
    heights = [sensor_height_mm, *extra_heights_mm]
    x = beam_response(t_sensor, np.array(heights, float), amplitudes_mm=amplitudes_mm, seed=seed)
    names = ["time_s", "dx_mm"] + [f"dx_mm_z{int(h):04d}" for h in extra_heights_mm]
    sensor = root / "sim" / "sensor.csv"
    _write_csv(sensor, names, [t_sensor, *(x[i] + 0.002 * rng.normal(size=t_sensor.size) for i in range(len(heights)))],
               ["%.6f"] + ["%.6f"] * len(heights))
    sim_json = root / "sim" / "sim.json"
    # the pluck's release, as sim/beam.py records its excitation
    release = {"type": "pluck", "params": [["start_s", 0.5]]}
    sim_json.write_text(json.dumps({"model_hz": list(MODEL_HZ), "damping": {"ratios": list(MODEL_ZETA)},
                                    "beam": {"length_mm": 1000.0}, "sensor": {"height_mm": sensor_height_mm},
                                    "parameters": {"excitation": [release]}}))

    t_cam = np.arange(0.0, duration_s - 1.0, 1.0 / fps)
    frames = np.arange(t_cam.size)
    truth_mm = beam_response(t_cam + lag_s, np.array([sensor_height_mm]), amplitudes_mm=amplitudes_mm, seed=seed)[0]
    occluded = np.zeros(t_cam.size, int)
    if occlusion_s is not None:
        occluded[(t_cam >= occlusion_s[0]) & (t_cam < occlusion_s[1])] = 1
    zeros = np.zeros(t_cam.size)
    truth = root / "render" / "truth.csv"
    _write_csv(truth, ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded"],
               [frames, t_cam, truth_mm / mm_per_px, zeros, truth_mm, zeros, occluded],
               ["%d", "%.6f", "%.5f", "%.5f", "%.6f", "%.6f", "%d"])
    render_json = root / "render" / "render.json"
    # the nominal offset is off by 30 ms, so the estimate has to do real work
    render_json.write_text(json.dumps({"mm_per_px": mm_per_px, "fps": fps, "camera_start_offset_s": lag_s + 0.03}))

    occ = occluded == 1
    proposed = truth_mm + 0.03 * rng.normal(size=t_cam.size)
    proposed[t_cam < 0.25] = truth_mm[t_cam < 0.25]  # a still structure, a steady datum
    proposed[occ] += 0.1 * rng.normal(size=occ.sum())
    valid_p = np.ones(t_cam.size, int)
    klt = 0.83 * truth_mm + 0.01 * t_cam + 0.05 * rng.normal(size=t_cam.size)
    klt[t_cam < 0.25] = 0.83 * truth_mm[t_cam < 0.25]
    if occ.any():
        end = np.flatnonzero(occ)[-1] + 1
        klt[occ] = 3.0 + 0.5 * rng.normal(size=occ.sum())
        klt[end:] += klt_offset_mm
    valid_k = np.ones(t_cam.size, int)
    valid_k[1::50] = 0
    tracks = {}
    for name, dx, valid in (("proposed", proposed, valid_p), ("klt", klt, valid_k)):
        # like a real tracker: displacement from frame 0, where it is exact
        dx = dx - dx[0]
        dx[0] = 0.0
        dx[valid == 0] = np.nan
        path = root / "track" / f"{name}.csv"
        _write_csv(path, ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid", "poi_kept_frac"],
                   [frames, t_cam, dx / mm_per_px, zeros, dx, zeros, valid, np.ones(t_cam.size)],
                   ["%d", "%.6f", "%.5f", "%.5f", "%.6f", "%.6f", "%d", "%.3f"])
        tracks[name] = path
    return {"sensor": sensor, "sim_json": sim_json, "truth": truth, "render_json": render_json,
            "proposed": tracks["proposed"], "klt": tracks["klt"]}
