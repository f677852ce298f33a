"""Unit tests of analysis: sync, metrics, spectra, occlusion and modal ID on planted signals."""

from __future__ import annotations

import numpy as np
import pytest

from analysis.metrics import occlusion_metrics, rmse
from analysis.modal import cantilever_shape, compare_with_model, identify, mac
from analysis.spectra import alias_frequency, welch_psd
from analysis.sync import align, estimate_offset, lowpass, xcorr_lag
from refflow.spectra import pick_peaks


def _beam_like(t):
    return (np.exp(-0.1 * t) * np.sin(2 * np.pi * 4.8 * t) + 0.3 * np.sin(2 * np.pi * 1.3 * t + 1)
            + 0.2 * np.sin(2 * np.pi * 11.0 * t))


def test_rmse_identical_is_zero_and_offset_is_offset():
    x = np.sin(np.linspace(0, 20, 500))
    assert rmse(x, x) == 0.0
    assert rmse(x + 0.123, x) == pytest.approx(0.123, abs=1e-12)


@pytest.mark.parametrize("lag_s", [0.0123, -0.0371, 0.0004])
def test_offset_estimate_within_005_reference_samples(lag_s):
    ref_t = np.arange(0.0, 20.0, 1e-3)  # 1 kHz
    frame_t = np.arange(0.0, 19.0, 1 / 60)
    est, corr = estimate_offset(ref_t, _beam_like(ref_t), frame_t, _beam_like(frame_t + lag_s),
                                center_s=lag_s + 0.04, highpass_hz=0.5)
    assert abs(est - lag_s) < 0.05e-3, (est - lag_s) / 1e-3
    assert corr > 0.999


@pytest.mark.parametrize("shift", [3.37, -0.41, 12.8])
def test_xcorr_lag_subsample(shift):
    n = np.arange(4000)
    g = lambda k: np.sin(2 * np.pi * k / 97.3) + 0.5 * np.sin(2 * np.pi * k / 31.7 + 0.3)  # noqa: E731
    assert abs(xcorr_lag(g(n), g(n - shift)) - shift) < 0.05


def test_align_excludes_invalid_frames_and_recovers_signal():
    ref_t = np.arange(0.0, 20.0, 1e-3)
    frame_t = np.arange(0.0, 19.0, 1 / 60)
    meas = _beam_like(frame_t + 0.02)
    valid = np.ones(frame_t.size, int)
    valid[300:360] = 0
    meas[300:360] = 50.0  # garbage that must not pull the lag
    al = align(ref_t, _beam_like(ref_t), frame_t, meas, valid=valid, center_s=0.0)
    assert abs(al.lag_s - 0.02) < 0.05e-3
    # the 30 Hz zero-phase low-pass leaves 11 Hz and 4.8 Hz content untouched
    ok = valid == 1
    assert rmse(al.ref_mm[ok], meas[ok]) < 2e-3


def test_lowpass_removes_mode3_without_delay():
    t = np.arange(0.0, 10.0, 1e-3)
    x = np.sin(2 * np.pi * 4.8 * t) + np.sin(2 * np.pi * 71.5 * t)
    y = lowpass(x, 1000.0)
    core = slice(1000, -1000)
    assert rmse(y[core], np.sin(2 * np.pi * 4.8 * t[core])) < 0.01


def test_welch_integrates_to_variance():
    rng = np.random.default_rng(0)
    x = 2.0 * rng.normal(size=2 ** 17) + 0.5 * np.sin(np.arange(2 ** 17) * 0.3)
    f, p = welch_psd(x, 1000.0, nperseg=1024)
    assert np.sum(p) * (f[1] - f[0]) == pytest.approx(np.var(x), rel=0.01)


def test_peak_picking_within_resolution():
    t = np.arange(0.0, 30.0, 1 / 60)
    x = np.sin(2 * np.pi * 4.83 * t) + 0.3 * np.sin(2 * np.pi * 11.5 * t) + 0.1 * np.sin(2 * np.pi * 24.4 * t)
    f, p = welch_psd(x, 60.0, segment_s=10.0)
    df = f[1] - f[0]
    found = sorted(pk["freq_hz"] for pk in pick_peaks(f, p, count=3))
    assert np.allclose(found, [4.83, 11.5, 24.4], atol=df)


def test_alias_prediction():
    assert alias_frequency(71.5, 60.0) == pytest.approx(11.5)
    assert alias_frequency(24.4, 60.0) == pytest.approx(24.4)
    assert np.allclose(alias_frequency(np.array([130.0, 60.0, 45.0]), 60.0), [10.0, 0.0, 15.0])


def test_occlusion_metrics_planted():
    fps = 60.0
    t = np.arange(0, 10 * fps) / fps
    occluded = ((t >= 4.0) & (t < 5.0)).astype(int)
    err = np.zeros(t.size)
    err[occluded == 1] = 2.0
    err[(t >= 5.0) & (t < 5.5)] = 0.3  # offset that dies out after 0.5 s
    valid = np.ones(t.size, int)
    occ_idx = np.flatnonzero(occluded)
    valid[occ_idx[::2]] = 0  # half the occluded frames flagged
    out = occlusion_metrics(t, err, valid, occluded, post_s=1.0, hold_s=0.5, threshold_mm=0.1)
    assert out["occlusion_start_s"] == pytest.approx(4.0)
    assert out["occlusion_end_s"] == pytest.approx(5.0)
    assert out["occlusion_frames"] == 60
    assert out["occlusion_rmse_mm"] == pytest.approx(2.0)
    assert out["occluded_flagged_invalid_frac"] == pytest.approx(0.5)
    assert out["post_occlusion_offset_mm"] == pytest.approx(0.15)
    assert out["post_occlusion_rmse_mm"] == pytest.approx(np.sqrt(0.5 * 0.09))
    assert out["recovery_time_s"] == pytest.approx(0.5)
    assert out["pre_occlusion_rmse_mm"] == 0.0


def test_occlusion_never_recovers_is_nan():
    t = np.arange(600) / 60.0
    occ = ((t >= 4) & (t < 5)).astype(int)
    err = np.where(t >= 4, 1.0, 0.0)
    out = occlusion_metrics(t, err, np.ones(t.size), occ, threshold_mm=0.1)
    assert np.isnan(out["recovery_time_s"])
    assert out["post_occlusion_offset_mm"] == pytest.approx(1.0)


def test_modal_identification_two_damped_modes():
    fs = 1000.0
    t = np.arange(0.0, 30.0, 1 / fs)
    heights = np.array([250.0, 500.0, 750.0, 1000.0])
    planted = [(4.8, 0.01, 1.0), (24.4, 0.005, 0.3)]
    y = np.zeros((heights.size, t.size))
    for m, (f, z, a) in enumerate(planted, start=1):
        wd = 2 * np.pi * f * np.sqrt(1 - z * z)
        y += np.outer(cantilever_shape(heights / 1000, m), a * np.exp(-z * 2 * np.pi * f * t) * np.cos(wd * t + m))
    y += 1e-3 * np.random.default_rng(3).normal(size=y.shape)
    modes = identify(y, fs, n_modes=2)
    res = compare_with_model(modes, heights, np.array([4.8, 24.4, 71.5]), beam_length_mm=1000.0,
                             model_zeta=[0.01, 0.005, 0.005])
    for i in (1, 2):
        assert abs(res[f"mode{i}_freq_error_pct"]) < 0.5
        assert res[f"mode{i}_mac"] > 0.99
        assert abs(res[f"mode{i}_damping_error_pct"]) < 10.0


def test_mac_and_cantilever_shapes():
    z = np.linspace(0.1, 1.0, 6)
    s1, s2 = cantilever_shape(z, 1), cantilever_shape(z, 2)
    assert mac(s1, 3 * s1) == pytest.approx(1.0)
    assert mac(s1, s2) < 0.3
    assert s1[-1] == pytest.approx(1.0)


from hypothesis import given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402


@settings(max_examples=30, deadline=None)
@given(offset=st.floats(-5, 5), n=st.integers(2, 200))
def test_rmse_of_constant_offset_property(offset, n):
    x = np.linspace(-1, 1, n)
    assert rmse(x + offset, x) == pytest.approx(abs(offset), abs=1e-9)


def _video_modal(heights, modes, region_order):
    """A `refflow modal` JSON of one run of len(heights) regions, its points listed in ``region_order``."""
    idx = [k - 1 for k in region_order]
    return {"points": [{"name": f"regions region {k}", "region": k} for k in region_order],
            "modes": [{"mode": i, "freq_hz": f, "damping_ratio": z, "shape": list(np.asarray(s)[idx]),
                       "fdd_shape": list(np.asarray(s)[idx])} for i, (f, z, s) in enumerate(modes, start=1)]}


def test_video_modes_against_model_and_laser_on_planted_numbers():
    from analysis.modal import compare_video_modes, video_modes_by_height
    from analysis.report import modal_markdown

    heights = np.array([250.0, 500.0, 750.0, 1000.0])
    model_hz = np.array([4.1, 25.7, 72.0])
    s1, s2 = (cantilever_shape(heights / 1000, m) for m in (1, 2))
    sensor = {"heights_mm": heights.tolist(), "mode1_freq_hz": 4.1, "mode1_shape": s1.tolist(),
              "mode1_damping_ratio": 0.005, "mode2_freq_hz": 25.7, "mode2_shape": s2.tolist(),
              "mode2_damping_ratio": 0.005}

    def compare(modes):
        # regions listed out of order: the shapes must be put back in height order
        video = _video_modal(heights, modes, [3, 1, 4, 2])
        return compare_video_modes(video_modes_by_height(video, 4), heights, model_hz, beam_length_mm=1000.0,
                                   model_zeta=[0.005] * 3, sensor=sensor)

    good = compare([(4.1 * 1.002, 0.006, -2 * s1), (25.7, 0.005, 0.5 * s2)])
    assert good["n_modes"] == 2
    assert good["mode1_freq_error_pct"] == pytest.approx(0.2, abs=1e-9)
    assert good["mode1_damping_error_pct"] == pytest.approx(20.0)
    for i in (1, 2):
        assert good[f"mode{i}_model_index"] == i and good[f"mode{i}_sensor_index"] == i
        assert good[f"mode{i}_mac"] > 0.999 and good[f"mode{i}_mac_vs_sensor"] > 0.999
    # the wrong answers: a frequency 5 % low, the two shapes swapped
    bad = compare([(4.1 * 0.95, 0.005, s2), (25.7, 0.005, s1)])
    assert bad["mode1_freq_error_pct"] == pytest.approx(-5.0)
    assert bad["mode1_freq_vs_sensor_pct"] == pytest.approx(-5.0)
    for i in (1, 2):
        assert bad[f"mode{i}_mac"] < 0.9 and bad[f"mode{i}_mac_vs_sensor"] < 0.9
    text = modal_markdown([{**good, "scenario": "modal"}])
    assert "## modal: modes from the video (250, 500, 750, 1000 mm" in text
    assert "| 1 (model mode 1) | 4.1082 | 4.1 | 0.2 |" in text


def test_video_modes_need_one_region_per_height():
    from analysis.modal import video_modes_by_height

    video = _video_modal(np.arange(3), [(4.0, 0.01, [0.1, 0.5, 1.0])], [1, 2, 3])
    with pytest.raises(ValueError, match="3 points, expected one region per sensor height \\(4\\)"):
        video_modes_by_height(video, 4)
