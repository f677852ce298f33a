"""A deforming region's small motion read at its scale (flow.methods.deepflow.localfit).

The dense DeepFlow field reads a small deformation short, whatever its wavelength (its
smoothness outweighs a weak data term): the DIC Challenge's Sample 14, a 0.1 px sine, read
with a gain of 0.80-0.975. One windowed least-squares step from the dense field takes that
shortfall off at wavelengths beyond the window.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

import flow.methods.deepflow.localfit as localfit
import flow.methods.deepflow.method as deepflow_module
from flow.methods.deepflow.localfit import refine_locally

sys.path.insert(0, str(Path(__file__).parent))
import _sine_field as sine  # noqa: E402

PERIOD_PX = 80.0


def _sine_pair(amplitude: float):
    x = np.arange(sine.WIDTH, dtype=np.float64)
    shift = amplitude * np.sin(2 * np.pi * x / PERIOD_PX)
    reference = sine.speckle(0.0)
    poi = np.zeros(reference.shape, bool)
    poi[12:84, 12:148] = True
    return reference, sine.speckle(shift), poi, shift


def _columns(flow: np.ndarray, poi: np.ndarray) -> np.ndarray:
    return np.nanmean(np.where(poi, flow[..., 0], np.nan)[:, 12:148], axis=0)


def _gain(measured: np.ndarray, truth: np.ndarray) -> float:
    return float(measured @ truth / (truth @ truth))


def test_a_small_deformation_is_read_at_its_scale_by_the_default() -> None:
    """A 0.1 px sine of an 80 px period on a speckle: the dense field reads it with a gain of
    0.95 (0.948), the default (dense field and one windowed step) within 3 % (0.982), and its
    column means closer to the truth."""
    reference, current, poi, shift = _sine_pair(0.1)
    truth = shift[12:148]
    method = deepflow_module.DeepFlow()
    method.bind(reference, poi)
    read = _columns(method.calc(reference, current), poi)
    assert method.counts["why_dense_deforms"] == 1
    dense = deepflow_module.DeepFlow(member=False, texture=False)
    dense.bind(reference, poi)
    dense_read = _columns(dense.calc(reference, current), poi)
    assert _gain(dense_read, truth) < 0.96  # the shortfall the step is for
    assert abs(_gain(read, truth) - 1) < 0.03
    assert np.sqrt(np.mean((read - truth) ** 2)) < 0.8 * np.sqrt(np.mean((dense_read - truth) ** 2))


def _noisy_sine(amplitude: float, period_px: float, noise: float, *, width: int = 480, height: int = 160):
    """A speckle and its copy deformed by a sine along x, each with its own sensor noise (grey
    levels), and the POIs: all but a 12 px border."""
    rng = np.random.default_rng(3)
    shift = amplitude * np.sin(2 * np.pi * np.arange(width) / period_px)
    frames = [np.clip(sine.speckle(s, width=width, height=height) + rng.normal(0, noise, (height, width)), 0, 255)
              .astype(np.uint8) for s in (0.0, shift)]
    poi = np.zeros((height, width), bool)
    poi[12:-12, 12:-12] = True
    return frames, poi, shift[12:-12]


def _read_columns(frames, poi) -> tuple[np.ndarray, dict]:
    method = deepflow_module.DeepFlow()
    method.bind(frames[0], poi)
    flow = method.calc(*frames)
    assert method.counts["why_dense_deforms"] == 1
    windows = {k: v for k, v in method.counts.items() if k.startswith("field_window_") and v}
    return np.nanmean(np.where(poi, flow[..., 0], np.nan)[:, 12:-12], axis=0), windows


def test_a_deformation_of_long_wavelength_is_read_through_a_wider_window(monkeypatch) -> None:
    """A 0.2 and a 0.3 px sine of a 400 px period under 2 grey levels of noise, and a 0.1 px one
    under 3: the default reads them through a wider window than the base's 8 px (24-32 px
    here), and their column means closer than the base window alone (0.0064 -> 0.0051 px,
    0.0066 -> 0.0054, 0.0085 -> 0.0063), within 1 % of the gain, and at the region's ends (the
    windows cut by its edge, where the base field is kept) no worse."""
    for amplitude, noise in ((0.2, 2.0), (0.3, 2.0), (0.1, 3.0)):
        frames, poi, truth = _noisy_sine(amplitude, 400.0, noise)
        read, windows = _read_columns(frames, poi)
        monkeypatch.setattr(localfit, "WIDER_WINDOWS_PX", ())
        base, base_windows = _read_columns(frames, poi)
        monkeypatch.undo()
        assert base_windows == {"field_window_8px": 1} and len(windows) == 1
        assert windows.keys() <= {"field_window_24px", "field_window_32px"}

        def rmse(columns, part=slice(None), truth=truth):
            return float(np.sqrt(np.mean((columns[part] - truth[part]) ** 2)))

        assert rmse(read) < 0.85 * rmse(base), (amplitude, rmse(read), rmse(base))
        assert abs(_gain(read, truth) - _gain(base, truth)) < 0.01
        for end in (slice(0, 40), slice(-40, None)):
            assert rmse(read, end) < 1.1 * rmse(base, end), (amplitude, rmse(read, end), rmse(base, end))


def test_a_deformation_of_short_wavelength_keeps_the_base_window(monkeypatch) -> None:
    """A 0.2 px sine of a 60 px period (a 16 px window reads it 10 % short): the base window is
    kept, and the reading is the base window's, bit for bit."""
    frames, poi, _ = _noisy_sine(0.2, 60.0, 2.0)
    read, windows = _read_columns(frames, poi)
    monkeypatch.setattr(localfit, "WIDER_WINDOWS_PX", ())
    base, _ = _read_columns(frames, poi)
    assert windows == {"field_window_8px": 1}
    np.testing.assert_array_equal(read, base)


def test_where_the_wider_window_takes_no_step_the_base_reading_and_its_sigma_stay() -> None:
    """A block with a 10 px arm (a reviewer's case): a 32 px window holds too few of the arm's
    POIs to take a step there, and the arm keeps the 8 px reading and its sigma (every arm POI
    that had one: the wider window's missing sigma blended in had left 970 of 1400 without);
    the block deep inside is read through the wider window."""
    width, height = 360, 200
    rng = np.random.default_rng(0)
    shift = 0.2 * np.sin(2 * np.pi * np.arange(width) / 400)
    frames = [np.clip(sine.speckle(s, width=width, height=height) + rng.normal(0, 2, (height, width)), 0, 255)
              .astype(np.uint8) for s in (0.0, shift)]
    region = np.zeros((height, width), bool)
    region[20:180, 20:200] = True
    region[95:105, 200:340] = True
    rows, cols = np.nonzero(region)
    base = refine_locally(*frames, rows, cols, np.zeros(rows.size), np.zeros(rows.size), with_sigma=True)
    (u, v, sigma_u, sigma_v), window = localfit.refine_adaptively(*frames, rows, cols, base, with_sigma=True)
    assert window > localfit.WINDOW_PX
    arm = cols >= 200
    had = np.isfinite(base[2]) & arm
    assert had.sum() > 1000
    np.testing.assert_array_equal(u[had], base[0][had])
    np.testing.assert_array_equal(sigma_u[had], base[2][had])
    np.testing.assert_array_equal(sigma_v[had], base[3][had])
    deep = localfit._depth(rows, cols) >= 2 * window
    assert np.isfinite(sigma_u[deep]).all() and np.all(sigma_u[deep] < 0.8 * base[2][deep])


def test_a_local_feature_on_a_smooth_deformation_keeps_the_base_window_about_it(monkeypatch) -> None:
    """A 0.3 px bump (Gaussian, 12 px) on a 0.3 px sine of 900 px period: the region is read
    through a wider window, which would read the bump's peak 0.32 px (truth 0.54; the 8 px
    window 0.52) and its neighbourhood 0.16 px RMS (8 px: 0.017); about the bump the 8 px field
    is kept: read as the 8 px window reads it, the region as a whole no worse."""
    import cv2

    width, height = 600, 300
    rng = np.random.default_rng(5)
    pattern = cv2.GaussianBlur(rng.normal(0, 1, (height + 40, width + 40)).astype(np.float32), (0, 0), 1.5)
    pattern = 128 + 50 * pattern / pattern.std()
    xs, ys = np.meshgrid(np.arange(width + 40, dtype=np.float32), np.arange(height + 40, dtype=np.float32))
    field = (0.3 * np.sin(2 * np.pi * xs / 900) + 0.3 * np.exp(-((xs - 320) ** 2 + (ys - 170) ** 2) / (2 * 12.0 ** 2)))
    field = field.astype(np.float32)
    frames = [np.clip(image + rng.normal(0, 2, image.shape), 0, 255)[20:-20, 20:-20].astype(np.uint8)
              for image in (pattern, cv2.remap(pattern, xs - field, ys, cv2.INTER_CUBIC))]
    truth = field[20:-20, 20:-20]
    poi = np.zeros((height, width), bool)
    poi[10:-10, 10:-10] = True
    near = np.hypot(*(np.mgrid[0:height, 0:width] - np.array([150, 300])[:, None, None])) < 12

    def read():
        method = deepflow_module.DeepFlow()
        method.bind(frames[0], poi)
        flow = method.calc(*frames)
        windows = {k for k, v in method.counts.items() if k.startswith("field_window_") and v}
        return flow[..., 0], windows

    adaptive, windows = read()
    monkeypatch.setattr(localfit, "WIDER_WINDOWS_PX", ())
    base, _ = read()
    assert windows & {"field_window_24px", "field_window_32px"}

    def rms(flow, where):
        return float(np.sqrt(np.mean((flow - truth)[where] ** 2)))

    assert rms(adaptive, near) < 1.1 * rms(base, near) and abs(adaptive[150, 300] - base[150, 300]) < 0.01
    assert rms(adaptive, poi) <= 1.02 * rms(base, poi)


def test_the_wider_windows_are_tried_widest_first_then_by_bisection(monkeypatch) -> None:
    """Which windows are read, for each answer of the attenuation test: one try where the
    widest is acceptable, three at most, and the widest acceptable one kept (the POIs 64 px
    deep and more read by it alone, see _inset)."""
    rows, cols = (a.ravel() for a in np.mgrid[0:160, 0:160])  # 64 px deep and more: the wider window's
    base = (np.zeros(rows.size), np.zeros(rows.size))
    for widest_ok, expected_tries in ((32.0, [32.0]), (24.0, [32.0, 16.0, 24.0]), (16.0, [32.0, 16.0, 24.0]),
                                      (12.0, [32.0, 16.0, 12.0]), (8.0, [32.0, 16.0, 12.0])):
        tried = []

        def fake_refine(reference, current, rows, cols, u, v, *, window_px, with_sigma, tried=tried):
            tried.append(window_px)
            return u + window_px, v, np.zeros_like(u), np.zeros_like(v)

        def fake_attenuation(rows, cols, field, smoother, widest_ok=widest_ok):
            return 1.0 if float(np.max(smoother[0])) <= widest_ok else 1.5

        monkeypatch.setattr(localfit, "refine_locally", fake_refine)
        monkeypatch.setattr(localfit, "attenuation", fake_attenuation)
        (u, _), window = localfit.refine_adaptively(None, None, rows, cols, base)
        assert tried == expected_tries and window == widest_ok
        assert np.max(u) == (widest_ok if widest_ok > 8 else 0.0)


def test_one_step_takes_off_most_of_a_long_wavelengths_shortfall() -> None:
    """Started from 0.7 of a 0.3 px sine (a field read 30 % short), one step reads it within
    10 % (the window's response at an 80 px period is 0.82); started from the truth it stays
    within 0.01 px; POIs whose frame position falls outside the frame keep their start."""
    reference, current, poi, shift = _sine_pair(0.3)
    rows, cols = np.nonzero(poi)
    truth = shift[cols]
    u, v = refine_locally(reference, current, rows, cols, 0.7 * truth, np.zeros_like(truth))
    assert abs(_gain(u, truth) - 1) < 0.1 and np.abs(v).max() < 0.1
    u, _ = refine_locally(reference, current, rows, cols, truth, np.zeros_like(truth))
    assert np.sqrt(np.mean((u - truth) ** 2)) < 0.01
    far = np.full_like(truth, 1e4)
    u, v = refine_locally(reference, current, rows, cols, far, np.zeros_like(truth))
    np.testing.assert_array_equal(u, far)


def _uniform_pair(shift: float, *, width: int = 240, height: int = 160):
    """A speckle moved ``shift`` px along x (exact), in a frame larger than the POIs' box (rows
    50-109, columns 80-159), so that the box and the frame's crop are cut out of it."""
    reference = sine.speckle(0.0, width=width, height=height)
    current = sine.speckle(np.full(width, shift), width=width, height=height)
    rows, cols = (a.ravel() for a in np.mgrid[50:110, 80:160])
    return reference, current, rows, cols


def test_the_step_reads_a_region_inside_a_larger_frame_under_changed_light() -> None:
    """A 0.3 px shift started 0.2 px short: read within 0.01 px RMS, v within 0.01 px, with the
    frame as it is, 10 grey levels brighter, 5 % brighter and on a 0-20 grey ramp (the window's
    offset and gain; without them a 5 % gain left 0.036 px RMS, 10 grey levels 0.057)."""
    reference, current, rows, cols = _uniform_pair(0.3)
    ramp = np.linspace(0, 20, current.shape[1])[None, :]
    for frame in (current.astype(np.float64), current + 10.0, current * 1.05, current + ramp):
        lit = np.clip(frame, 0, 255).astype(np.uint8)
        u, v = refine_locally(reference, lit, rows, cols, np.full(rows.size, 0.1), np.zeros(rows.size))
        assert np.sqrt(np.mean((u - 0.3) ** 2)) < 0.01 and np.sqrt(np.mean(v ** 2)) < 0.01


def test_windows_without_texture_in_both_directions_keep_the_dense_field() -> None:
    """Vertical stripes (texture along x only) and a flat patch with 2 grey levels of noise: the
    step cannot tell the motion there, and the start is returned unchanged; a NaN start stays
    NaN and leaves the other POIs their step."""
    rng = np.random.default_rng(3)
    height, width = 120, 160
    x = np.arange(width, dtype=np.float64)
    stripes = 128 + 60 * np.sin(2 * np.pi * x / 9.0)[None, :] * np.ones((height, 1))
    flat = np.full((height, width), 128.0)
    rows, cols = (a.ravel() for a in np.mgrid[30:90, 40:120])
    start_u, start_v = np.full(rows.size, 0.2), np.zeros(rows.size)
    for image in (stripes, flat):
        reference = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        current = np.clip(image + rng.normal(0, 2.0, image.shape), 0, 255).astype(np.uint8)
        u, v = refine_locally(reference, current, rows, cols, start_u, start_v)
        np.testing.assert_array_equal(u, start_u)
        np.testing.assert_array_equal(v, start_v)
    reference, current, rows, cols = _uniform_pair(0.3)
    start = np.full(rows.size, 0.1)
    start[0] = np.nan
    u, _ = refine_locally(reference, current, rows, cols, start, np.zeros(rows.size))
    assert np.isnan(u[0]) and np.all(np.isfinite(u[1:])) and abs(np.median(u[1:]) - 0.3) < 0.01


def test_each_corrected_pois_uncertainty_is_its_windows_noise() -> None:
    """A 0.3 px shift of a speckle with fresh sensor noise in both frames (3 seeds, 2 and 6 grey
    levels): the errors of the corrected POIs over their own sigma have an RMS near 1 (0.84 and
    0.80 here; 0.97-1.08 per pixel on the DIC Challenge's Sample 14) and 90-99.8 % lie within 2
    sigma; the sigma triples with the noise; without noise in the images it is
    far below the noisy frames' (it is the noise's, not the estimator's own bias: see the
    module's notes). Where the dense field stays (stripes), there is none."""
    reference, current, rows, cols = _uniform_pair(0.3)
    medians = {}
    for noise in (2.0, 6.0):
        z, sigmas = [], []
        for seed in range(3):
            rng = np.random.default_rng(seed)
            ref = np.clip(reference + rng.normal(0, noise, reference.shape), 0, 255).astype(np.uint8)
            cur = np.clip(current + rng.normal(0, noise, current.shape), 0, 255).astype(np.uint8)
            u, v, su, sv = refine_locally(ref, cur, rows, cols, np.full(rows.size, 0.32),
                                          np.full(rows.size, -0.02), with_sigma=True)
            assert np.isfinite(su).all() and np.isfinite(sv).all()
            z += [(u - 0.3) / su, v / sv]
            sigmas.append(su)
        z = np.concatenate(z)
        assert 0.7 < np.sqrt(np.mean(z ** 2)) < 1.35, noise
        assert 0.9 <= np.mean(np.abs(z) < 2) <= 0.998, noise
        medians[noise] = float(np.median(np.concatenate(sigmas)))
    assert 2.4 < medians[6.0] / medians[2.0] < 3.6
    _, _, clean, _ = refine_locally(reference, current, rows, cols, np.full(rows.size, 0.32),
                                    np.full(rows.size, -0.02), with_sigma=True)
    assert np.median(clean) < 0.3 * medians[2.0]
    x = np.arange(160, dtype=np.float64)
    stripes = (128 + 60 * np.sin(2 * np.pi * x / 9.0)[None, :] * np.ones((120, 1))).astype(np.uint8)
    srows, scols = (a.ravel() for a in np.mgrid[30:90, 40:120])
    _, _, su, sv = refine_locally(stripes, stripes, srows, scols, np.full(srows.size, 0.2),
                                  np.zeros(srows.size), with_sigma=True)
    assert np.isnan(su).all() and np.isnan(sv).all()


def test_a_tall_regions_pois_are_corrected_in_bands_as_if_at_once(monkeypatch) -> None:
    """The POIs are corrected in bands of BAND_ROWS rows of their box, each with the POIs its
    windows reach (a whole 4K frame's 8 M POIs held dozens of per-POI arrays at once: 2.5 GB,
    1.7 GB in bands): the readings are the one-band readings to the bit, in any order of the
    POIs, and their sigmas to float precision."""
    import flow.methods.deepflow.localfit as localfit

    reference, current, poi, shift = _sine_pair(0.1)
    rows, cols = np.nonzero(poi)
    order = np.random.default_rng(3).permutation(rows.size)
    rows, cols = rows[order], cols[order]
    start_u, start_v = 0.8 * shift[cols], np.zeros(rows.size)
    start_u[::53] = np.nan
    whole = refine_locally(reference, current, rows, cols, start_u, start_v, with_sigma=True)
    monkeypatch.setattr(localfit, "BAND_ROWS", 16)  # 72 rows of POIs: 7 bands of the box
    banded = refine_locally(reference, current, rows, cols, start_u, start_v, with_sigma=True)
    assert np.array_equal(whole[0], banded[0], equal_nan=True) and np.array_equal(whole[1], banded[1], equal_nan=True)
    assert np.allclose(whole[2], banded[2], rtol=1e-5, equal_nan=True)
    assert np.allclose(whole[3], banded[3], rtol=1e-5, equal_nan=True)
    moved = np.isfinite(whole[2])
    assert moved.mean() > 0.5 and np.all(whole[0][moved] != start_u[moved])  # a test that can fail
