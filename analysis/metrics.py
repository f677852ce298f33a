"""Accuracy metrics of one tracked series against the reference.

Every key carries its unit (``rmse_mm``, ``drift_mm_per_s``, ``..._pct``,
``..._hz``); ratios without a unit end in ``_ratio`` or ``_frac``.
Error is always ``measured - reference`` in world x (mm) or image x (px).

Maximum displacement (``max_disp_*``, Table 1) is read as the paper reads its Fig. 8: the
largest excursion after the release (the hold before a pluck excluded: every method is put
into the laser's datum there, so the hold itself says nothing), from the rest position that
each series shows after the release (its own mean there). A constant offset of a method
does not move it; a scale error does, one for one. ``p2p_first_cycles_*`` is the
peak-to-peak amplitude over the first ``p2p_cycles`` periods of mode 1 after the release.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from refflow.spectra import pick_peaks

from .modal import identify
from .readers import Sensor, model_modes_hz, release_time_s, track_mm
from .spectra import alias_frequency, band_power, nearest_peak, welch_psd
from .sync import align, datum_offset, estimate_offset, lowpass

# Fewer valid frames than this overlapping the reference: a run is reported as unmeasured
# (its valid share and no error metrics) instead of errors over a handful of frames.
MIN_COMPARED_FRAMES = 8

DEFAULTS: dict[str, Any] = {
    "lowpass_hz": 30.0,            # paper section 4.3
    "lowpass_order": 3,
    "datum_s": 0.25,               # median over the first 0.25 s, see sync.datum_offset
    "max_lag_s": 0.1,              # < half the mode-1 period, see sync.estimate_offset
    "sync_highpass_hz": 0.5,       # lag fit only: drift/offsets must not pull the lag
    "psd_segment_s": 10.0,         # 0.1 Hz resolution for the mode peaks
    "lowfreq_hz": 0.1,             # "0-0.1 Hz region" of Fig. 9 (drift)
    "post_occlusion_s": 1.0,       # window after the view returns
    "recovery_hold_s": 0.5,        # error must stay below threshold this long
    "recovery_threshold_mm": None,  # default: max(4 x pre-occlusion RMSE, 0.02 mm) pointwise,
                                    # max(pre-occlusion RMSE, 0.02 mm) on the hold-window mean
    "mode_count": 3,
    "p2p_cycles": 2,               # peak-to-peak amplitude over the first 2 periods of mode 1
}


def clean(value: Any) -> Any:
    """JSON-safe copy: NaN/inf become ``None``, NumPy scalars become Python."""
    if isinstance(value, dict):
        return {k: clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if isinstance(value, np.ndarray):
        return clean(value.tolist())
    if isinstance(value, (np.bool_, bool)):
        return bool(value)
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value


def rmse(a: np.ndarray, b: np.ndarray | float = 0.0) -> float:
    """Root-mean-square of ``a - b`` over finite entries (NaN if none)."""
    d = np.asarray(a, float) - b
    d = d[np.isfinite(d)]
    return float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")


def occlusion_spans(occluded: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, stop)]`` index ranges where ``occluded`` is non-zero (stop exclusive)."""
    occ = np.asarray(occluded) != 0
    edges = np.diff(np.concatenate([[0], occ.astype(int), [0]]))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def occlusion_metrics(time_s: np.ndarray, error_mm: np.ndarray, valid: np.ndarray,
                      occluded: np.ndarray, *, post_s: float = 1.0, hold_s: float = 0.5,
                      threshold_mm: float | None = None) -> dict[str, Any]:
    """Error during the (longest) occlusion and how the method comes back.

    ``error_mm`` may be NaN where the method gave no value. Frames flagged
    ``valid=0`` still count for the error *during* occlusion (if they carry a
    number) but not for recovery, which is judged on frames the method vouches for.

    ``recovery_time_s`` is the time from the end of the occlusion to the first
    frame from which, for ``hold_s``, every error stays within the pointwise
    threshold (default 4 x pre-occlusion RMSE, at least 0.02 mm) and the
    window's mean error is within the offset threshold (default 1 x
    pre-occlusion RMSE, at least 0.02 mm) of the pre-occlusion bias; ``None``
    (NaN) if that never happens before the record ends. ``threshold_mm`` sets
    both thresholds. The post-occlusion offset is the mean error in the
    ``post_s`` after the view returns minus the mean error before the
    occlusion (the step the occlusion left, paper Fig. 10);
    ``post_occlusion_error_mm`` is that mean error itself.
    """
    time_s = np.asarray(time_s, float)
    error_mm = np.asarray(error_mm, float)
    valid = np.asarray(valid) != 0
    spans = occlusion_spans(occluded)
    if not spans:
        return {"occlusion_spans": 0}
    first, stop = max(spans, key=lambda s: s[1] - s[0])
    inside = np.zeros(time_s.size, bool)
    inside[first:stop] = True
    t_start = float(time_s[first])
    t_end = float(time_s[stop]) if stop < time_s.size else float(time_s[-1])
    pre = valid & (time_s < t_start) & np.isfinite(error_mm)
    pre_rmse = rmse(error_mm[pre])
    pre_bias = float(np.mean(error_mm[pre])) if pre.any() else 0.0
    if threshold_mm is None:
        # 4 sigma: white noise alone crosses it once in ~16000 frames
        point_thr = max(4.0 * pre_rmse, 0.02) if math.isfinite(pre_rmse) else 0.02
        offset_thr = max(pre_rmse, 0.02) if math.isfinite(pre_rmse) else 0.02
    else:
        point_thr = offset_thr = float(threshold_mm)
    post = (time_s >= t_end) & (time_s < t_end + post_s) & ~inside
    post_ok = post & valid & np.isfinite(error_mm)
    during = inside & np.isfinite(error_mm)
    judged = valid & np.isfinite(error_mm)
    # recovered at the first frame from which, for hold_s, every error is
    # within the pointwise threshold AND the mean error is back at the
    # pre-occlusion bias: a method that returns with an offset has not recovered
    recovery = float("nan")
    for k in np.flatnonzero((time_s >= t_end) & ~inside):
        if time_s[k] + hold_s > time_s[-1] + 1e-9:
            break
        window = judged & (time_s >= time_s[k]) & (time_s < time_s[k] + hold_s)
        if not judged[k]:
            continue
        err_w = error_mm[window]
        if np.all(np.abs(err_w) <= point_thr) and abs(np.mean(err_w) - pre_bias) <= offset_thr:
            recovery = float(time_s[k] - t_end)
            break
    n_occ = int(stop - first)
    return {
        "occlusion_spans": len(spans),
        "occlusion_start_s": t_start,
        "occlusion_end_s": t_end,
        "occlusion_duration_s": t_end - t_start,
        "occlusion_frames": n_occ,
        "occlusion_rmse_mm": rmse(error_mm[during]),
        "occlusion_max_error_mm": float(np.max(np.abs(error_mm[during]))) if during.any() else float("nan"),
        "occluded_flagged_invalid_frac": float(np.mean(~valid[first:stop])),
        "pre_occlusion_rmse_mm": pre_rmse,
        # the jump the occlusion left: the mean error after it against the mean error before it
        # (a method's constant bias is in rmse/bias, not here)
        "post_occlusion_offset_mm": float(np.mean(error_mm[post_ok]) - pre_bias) if post_ok.any() else float("nan"),
        "post_occlusion_error_mm": float(np.mean(error_mm[post_ok])) if post_ok.any() else float("nan"),
        "post_occlusion_rmse_mm": rmse(error_mm[post_ok]),
        "recovery_threshold_mm": float(point_thr),
        "recovery_offset_threshold_mm": float(offset_thr),
        "recovery_time_s": recovery,
    }


def _fill_gaps(t: np.ndarray, x: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Linear interpolation over frames without a valid value (for spectra only)."""
    return np.interp(t, t[ok], x[ok])


def identify_mode1(meas_mm: np.ndarray, fps: float, model_hz: float) -> dict[str, float]:
    """Mode 1 identified from the measurement alone (SSI, finer than the PSD's bins).

    A short clip resolves the PSD only to ~1/T Hz; the parametric fit of
    :func:`analysis.modal.identify` recovers the frequency of a decaying mode
    to a small fraction of that, which is what a modal survey needs.
    """
    try:
        mode = identify(meas_mm[None, :], fps, n_modes=1, band_hz=(0.5, min(0.45 * fps, 2.0 * model_hz)))[0]
    except (ValueError, np.linalg.LinAlgError, IndexError):
        return {"mode1_identified_hz": float("nan"), "mode1_identified_error_pct": float("nan")}
    freq = float(mode["freq_hz"])
    return {"mode1_identified_hz": freq,
            "mode1_identified_error_pct": 100.0 * (freq - model_hz) / model_hz,
            "mode1_identified_damping_ratio": float(mode["damping_ratio"])}


def _pct(measured: float, reference: float) -> float:
    return 100.0 * (measured - reference) / reference if reference > 0 else float("nan")


def amplitude_metrics(time_s: np.ndarray, ref_mm: np.ndarray, meas_mm: np.ndarray, use: np.ndarray, *,
                      release_s: float, period_s: float, cycles: int = 2) -> dict[str, float]:
    """Maximum displacement and first cycles' peak-to-peak, measured and reference.

    ``time_s`` on the reference's clock; ``use``: the frames both series are compared on.
    Only frames from ``release_s`` on count; each series is taken about its own mean there
    (its rest position), so a constant offset of ``meas_mm`` changes nothing and a scale
    factor ``k`` gives an error of ``100 (k - 1)`` %.
    """
    after = use & (time_s >= release_s)
    nan = float("nan")
    if after.sum() < 8:
        return {"max_disp_meas_mm": nan, "max_disp_ref_mm": nan, "max_disp_error_pct": nan,
                "p2p_first_cycles_meas_mm": nan, "p2p_first_cycles_ref_mm": nan,
                "p2p_first_cycles_error_pct": nan, "release_s": float(release_s)}
    ref = ref_mm[after] - np.mean(ref_mm[after])
    meas = meas_mm[after] - np.mean(meas_mm[after])
    max_ref, max_meas = float(np.max(np.abs(ref))), float(np.max(np.abs(meas)))
    first = time_s[after] < time_s[after][0] + cycles * period_s
    p2p_ref, p2p_meas = float(np.ptp(ref[first])), float(np.ptp(meas[first]))
    return {"max_disp_meas_mm": max_meas, "max_disp_ref_mm": max_ref,
            "max_disp_error_pct": _pct(max_meas, max_ref),
            "p2p_first_cycles_meas_mm": p2p_meas, "p2p_first_cycles_ref_mm": p2p_ref,
            "p2p_first_cycles_error_pct": _pct(p2p_meas, p2p_ref), "release_s": float(release_s)}


def _truth_at_frames(track: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """truth.csv's ``occluded`` flag and ``dx_mm`` at the track's rows, matched by frame number
    (0 and NaN where the truth has no such frame)."""
    t = track["time_s"]
    occluded = np.zeros(t.size)
    truth_mm = np.full(t.size, np.nan)
    pos = {int(f): i for i, f in enumerate(truth["frame"])}
    rows = np.array([pos.get(int(f), -1) for f in track["frame"]])
    has = rows >= 0
    occluded[has] = truth["occluded"][rows[has]]
    truth_mm[has] = truth["dx_mm"][rows[has]]
    return occluded, truth_mm


def _amplitude_of_run(sensor: Sensor, filtered_1khz: np.ndarray, t: np.ndarray, lag_s: float,
                      ref_mm: np.ndarray, meas_mm: np.ndarray, both: np.ndarray, unocc: np.ndarray,
                      release_s: float, mode1_hz: float, cycles: int) -> dict[str, Any]:
    """:func:`amplitude_metrics` at the frame times, and the filtered laser's own maximum
    over the same span (``max_disp_ref_1khz_mm``)."""
    amplitude = amplitude_metrics(t + lag_s, ref_mm, meas_mm, unocc, release_s=release_s,
                                  period_s=1.0 / mode1_hz, cycles=cycles)
    span_t = t[both] + lag_s
    in_span = (sensor.time_s >= max(span_t[0], release_s)) & (sensor.time_s <= span_t[-1])
    laser = filtered_1khz[in_span]
    max_ref_1khz = float(np.max(np.abs(laser - np.mean(laser)))) if laser.size else float("nan")
    # max_disp_ref_mm: at the frame times, what a perfect camera could see;
    # max_disp_ref_1khz_mm: the filtered laser itself, same time span
    return {**amplitude, "max_disp_ref_1khz_mm": max_ref_1khz}


def _error_metrics(t: np.ndarray, err_mm: np.ndarray, err_px: np.ndarray, both: np.ndarray,
                   unocc: np.ndarray, max_ref: float) -> dict[str, Any]:
    """RMSE (mm, px, % of the maximum reference displacement), bias, spread, worst error and
    drift of ``measured - reference`` over the compared frames."""
    e = err_mm[both]
    slope = float(np.polyfit(t[both], e, 1)[0]) if both.sum() > 2 else float("nan")
    return {
        "rmse_mm": rmse(e),
        "rmse_px": rmse(err_px[both]),
        "rmse_pct_of_max_ref": 100.0 * rmse(e) / max_ref if max_ref > 0 else float("nan"),
        "rmse_unoccluded_mm": rmse(err_mm[unocc]),
        "bias_mm": float(np.mean(e)),
        "error_std_mm": float(np.std(e)),
        "max_error_mm": float(np.max(np.abs(e))),
        "drift_mm_per_s": slope,
    }


def _sync_truth_metrics(sensor: Sensor, filtered_1khz: np.ndarray, truth: dict[str, np.ndarray],
                        lag_s: float, max_lag_s: float, nominal_lag_s: float) -> dict[str, float]:
    """The true clock offset, from the frame-exact truth vs the same reference, and the
    error of the measured one (nothing where the truth cannot be aligned)."""
    if not (np.isfinite(truth["dx_mm"]).all() and np.std(truth["dx_mm"]) > 0):
        return {}
    try:
        lag_truth, _ = estimate_offset(sensor.time_s, filtered_1khz, truth["time_s"], truth["dx_mm"],
                                       valid=truth["occluded"] == 0, max_lag_s=max_lag_s,
                                       center_s=nominal_lag_s)
    except ValueError:
        return {}
    return {"sync_lag_truth_s": lag_truth, "sync_lag_error_ms": 1e3 * (lag_s - lag_truth)}


def _mode_peak_metrics(f: np.ndarray, p_meas: np.ndarray, sensor: Sensor, fps: float,
                       modes_hz: np.ndarray, segment_s: float) -> dict[str, Any]:
    """Per model mode: where its (aliased) peak is expected in the measurement's PSD, and the
    peaks found there and in the raw laser's PSD."""
    df = float(f[1] - f[0])
    peaks = pick_peaks(f, p_meas, min_hz=0.5 * df, rel_prominence=1e-6)
    fr, p_raw = welch_psd(sensor.dx_mm, sensor.rate_hz, segment_s=segment_s)
    ref_peaks = pick_peaks(fr, p_raw, min_hz=0.5 * df, rel_prominence=1e-6)
    out: dict[str, Any] = {"psd_resolution_hz": df}
    for i, fm in enumerate(modes_hz, start=1):
        expected = alias_frequency(fm, fps)
        tol = max(2 * df, 0.03 * expected)
        hit = nearest_peak(peaks, expected, tol)
        ref_hit = nearest_peak(ref_peaks, fm, max(2 * (fr[1] - fr[0]), 0.03 * fm))
        out[f"mode{i}_model_hz"] = float(fm)
        out[f"mode{i}_aliased"] = bool(fm > fps / 2)
        out[f"mode{i}_expected_hz"] = float(expected)
        out[f"mode{i}_meas_peak_hz"] = hit["freq_hz"] if hit else float("nan")
        out[f"mode{i}_ref_peak_hz"] = ref_hit["freq_hz"] if ref_hit else float("nan")
        out[f"mode{i}_meas_peak_error_hz"] = (hit["freq_hz"] - expected) if hit else float("nan")
    return out


def _lowfreq_metrics(meas_f: np.ndarray, ref_f: np.ndarray, fps: float, lowfreq_hz: float) -> dict[str, float]:
    """Drift: power below ``lowfreq_hz`` in the measurement and the reference (one segment:
    the longest, which the lowest band needs)."""
    fl, pl_meas = welch_psd(meas_f, fps)
    _, pl_ref = welch_psd(ref_f, fps)
    # a record shorter than 1 / lowfreq_hz cannot resolve 0.1 Hz: widen the
    # band to the first non-zero bin rather than report DC leakage alone
    lf = max(float(lowfreq_hz), float(fl[1] - fl[0]) * 1.0001)
    lm, lr = band_power(fl, pl_meas, 0.0, lf), band_power(fl, pl_ref, 0.0, lf)
    return {"lowfreq_band_hz": lf, "lowfreq_power_meas_mm2": lm, "lowfreq_power_ref_mm2": lr,
            "lowfreq_power_ratio": lm / lr if lr > 0 else float("nan"),
            "lowfreq_resolution_hz": float(fl[1] - fl[0])}


def _spectral_metrics(t: np.ndarray, meas_mm: np.ndarray, ref_mm: np.ndarray, valid: np.ndarray,
                      sensor: Sensor, fps: float, modes_hz: np.ndarray, p: dict[str, Any]) -> dict[str, Any]:
    """Mode peaks, mode 1's amplitude ratio and identified frequency, and drift power, from
    spectra of a gap-free series over the compared span."""
    span = np.flatnonzero(np.isfinite(ref_mm))
    sl = slice(span[0], span[-1] + 1)
    meas_f = _fill_gaps(t[sl], meas_mm[sl], valid[sl])
    ref_f = ref_mm[sl]
    f, p_meas = welch_psd(meas_f, fps, segment_s=p["psd_segment_s"])
    _, p_ref = welch_psd(ref_f, fps, segment_s=p["psd_segment_s"])
    out = _mode_peak_metrics(f, p_meas, sensor, fps, modes_hz, p["psd_segment_s"])
    df = float(f[1] - f[0])
    f1 = float(modes_hz[0])
    half = max(3 * df, 0.1 * f1)
    pm, pr = band_power(f, p_meas, f1 - half, f1 + half), band_power(f, p_ref, f1 - half, f1 + half)
    out["mode1_amplitude_ratio"] = math.sqrt(pm / pr) if pr > 0 else float("nan")
    out.update(identify_mode1(meas_f, fps, f1))
    out.update(_lowfreq_metrics(meas_f, ref_f, fps, p["lowfreq_hz"]))
    return out


def evaluate(sensor: Sensor, sim_json: dict[str, Any], truth: dict[str, np.ndarray],
             mm_per_px: float, fps: float, track: dict[str, np.ndarray],
             params: dict[str, Any] | None = None, *, nominal_lag_s: float = 0.0) -> dict[str, Any]:
    """All metrics of one method in one scenario (see module docstring for conventions).

    ``nominal_lag_s`` centres the clock-offset search (render.json's
    ``camera_start_offset_s``: sensor time = camera time + offset).
    """
    p = {**DEFAULTS, **(params or {})}
    modes_hz = model_modes_hz(sim_json)[: int(p["mode_count"])]
    t = track["time_s"]
    meas_mm, mm_from_px = track_mm(track, mm_per_px)
    valid = (track["valid"] != 0) & np.isfinite(meas_mm)
    occluded, truth_mm = _truth_at_frames(track, truth)
    usable = int((valid & (occluded == 0)).sum())
    if usable < MIN_COMPARED_FRAMES:
        # The method flagged (nearly) every frame: nothing to compare, and that is the result.
        return clean({"frames": int(t.size), "valid_frac": float(np.mean(valid)), "compared_frames": usable,
                      "unmeasured": f"only {usable} valid frames outside occlusions (at least "
                                    f"{MIN_COMPARED_FRAMES} are needed): no error metrics",
                      "params": {k: p[k] for k in DEFAULTS}})
    # occluded frames carry no information about the clock offset
    al = align(sensor.time_s, sensor.dx_mm, t, meas_mm, valid=valid & (occluded == 0), cutoff_hz=p["lowpass_hz"],
               order=int(p["lowpass_order"]), max_lag_s=p["max_lag_s"], highpass_hz=p["sync_highpass_hz"],
               center_s=nominal_lag_s)
    ref_mm = al.ref_mm
    both = valid & np.isfinite(ref_mm)
    if both.sum() < MIN_COMPARED_FRAMES:
        raise ValueError(f"only {int(both.sum())} valid frames overlap the reference")
    # trackers measure from their first frame, the laser from rest: one constant
    datum_mm = datum_offset(t, ref_mm, meas_mm, valid & (occluded == 0), datum_s=p["datum_s"])
    meas_mm = meas_mm + datum_mm
    err_mm = meas_mm - ref_mm
    err_px = (track["dx_px"] + datum_mm / mm_per_px) - ref_mm / mm_per_px
    unocc = both & (occluded == 0)
    filtered_1khz = lowpass(sensor.dx_mm, sensor.rate_hz, cutoff_hz=p["lowpass_hz"], order=int(p["lowpass_order"]))
    amplitude = _amplitude_of_run(sensor, filtered_1khz, t, al.lag_s, ref_mm, meas_mm, both, unocc,
                                  release_time_s(sim_json), float(modes_hz[0]), int(p["p2p_cycles"]))
    raw_mm, raw_px = meas_mm - datum_mm, track["dx_px"]
    scale_ok = valid & (np.abs(raw_px) > 1e-6)
    out: dict[str, Any] = {
        "frames": int(t.size), "valid_frac": float(np.mean(valid)), "compared_frames": int(both.sum()),
        "datum_offset_mm": datum_mm, "sync_lag_s": al.lag_s, "sync_lag_nominal_s": float(nominal_lag_s),
        "sync_corr": al.corr, "sign_flip_suspected": al.sign_flip_suspected, **amplitude,
        **_error_metrics(t, err_mm, err_px, both, unocc, amplitude["max_disp_ref_mm"]),
        # truth is from rest too, and frame-exact: no filter, no sync
        "rmse_vs_truth_mm": rmse(meas_mm[valid] - truth_mm[valid]),
        "mm_per_px_render": float(mm_per_px), "mm_from_render_scale": mm_from_px,
        "mm_per_px_track": float(np.median(raw_mm[scale_ok] / raw_px[scale_ok])) if scale_ok.sum() else float("nan"),
        **_sync_truth_metrics(sensor, filtered_1khz, truth, al.lag_s, p["max_lag_s"], nominal_lag_s),
        **_spectral_metrics(t, meas_mm, ref_mm, valid, sensor, fps, modes_hz, p),
    }
    out.update(occlusion_metrics(t, err_mm, valid, occluded, post_s=p["post_occlusion_s"],
                                 hold_s=p["recovery_hold_s"], threshold_mm=p["recovery_threshold_mm"]))
    out["params"] = {k: p[k] for k in DEFAULTS}
    return clean(out)
