"""Accuracy of the clean-room DeepFlow against ground truth and OpenCV's DeepFlow."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import flow.methods.deepflow.method as deepflow_module
from flow.methods import registry
from flow.methods.deepflow import variational
from flow.methods.deepflow.regionfit import RegionMotion

sys.path.insert(0, str(Path(__file__).parent))  # shared synthetic pairs
from _deepflow_synth import (  # noqa: E402
    bar_frames,
    epe,
    grid,
    low_texture_pair,
    rigid_flow,
    textured,
    to_u8,
    visible,
    warp_forward,
)

H, W = 96, 128


def _opencv_deepflow(reference, current):
    return cv2.optflow.createOptFlow_DeepFlow().calc(reference, current, None)


def _synthetic_flows():
    gx, gy = grid(H, W)
    translation = np.dstack([np.full((H, W), 2.3), np.full((H, W), -1.4)]).astype(np.float32)
    rotation = rigid_flow(H, W, 3.0, 0.0, 0.0)
    deformation = np.dstack(
        [3 * np.sin(2 * np.pi * gy / H), 2 * np.cos(2 * np.pi * gx / W)]
    ).astype(np.float32)
    return {"translation": translation, "rotation": rotation, "deformation": deformation}


@pytest.mark.parametrize("case", ["translation", "rotation", "deformation"])
def test_variational_only_matches_opencv_deepflow(case):
    truth = _synthetic_flows()[case]
    reference = textured(H, W, seed=0)
    current = warp_forward(reference, truth)
    reference, current = to_u8(reference), to_u8(current)
    ours = deepflow_module.DeepFlow(beta=0.0).calc(reference, current)
    theirs = _opencv_deepflow(reference, current)
    epe_ours, epe_cv = epe(ours, truth), epe(theirs, truth)
    print(f"{case}: EPE ours {epe_ours:.4f} px, OpenCV DeepFlow {epe_cv:.4f} px")
    assert ours.shape == (H, W, 2) and ours.dtype == np.float32
    assert epe_ours <= 1.10 * epe_cv


def test_large_displacement_recovered_where_opencv_fails():
    height, width = 128, 256
    truth = rigid_flow(height, width, 5.0, 40.0, 0.0)
    reference = textured(height, width, seed=3)
    current = warp_forward(reference, truth)
    reference, current = to_u8(reference), to_u8(current)
    seen = visible(truth)
    ours = deepflow_module.DeepFlow(ngh_rad=64).calc(reference, current)
    theirs = _opencv_deepflow(reference, current)
    epe_ours = epe(ours, truth, seen, margin=1)
    epe_cv = epe(theirs, truth, seen, margin=1)
    print(
        f"large displacement: EPE ours {epe_ours:.3f} px, OpenCV DeepFlow {epe_cv:.3f} px "
        f"({epe_cv / epe_ours:.0f} times ours: it does not find the 40 px motion)"
    )
    assert epe_ours < 0.5
    assert epe_cv > 10 * epe_ours


@pytest.mark.parametrize("shift", [0.1, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 5.0])
def test_subpixel_translation_of_low_texture(shift):
    reference, current = low_texture_pair(shift, 0.5 * shift)
    flow = deepflow_module.DeepFlow().calc(reference, current)
    centre = flow[32:64, 48:80]
    err_x = float(centre[..., 0].mean() - shift)
    err_y = float(centre[..., 1].mean() - 0.5 * shift)
    print(f"shift {shift}: error dx {err_x:+.4f} px, dy {err_y:+.4f} px")
    assert abs(err_x) < 0.05 and abs(err_y) < 0.05


def test_low_texture_bar_slope_is_one():
    shifts = np.array([0.5, 1.0, 2.0, 3.0, 4.0, 6.0])
    reference, frames, poi = bar_frames(shifts)
    method = deepflow_module.DeepFlow()
    ours = [float(method.calc(reference, f)[..., 0][poi].mean()) for f in frames]
    theirs = [float(_opencv_deepflow(reference, f)[..., 0][poi].mean()) for f in frames]
    slope_ours = np.polyfit(shifts, ours, 1)[0]
    slope_cv = np.polyfit(shifts, theirs, 1)[0]
    print(f"bar slope ours {slope_ours:.4f}, OpenCV DeepFlow {slope_cv:.4f}")
    assert abs(slope_ours - 1.0) < 0.02


def _random_system(height, width, seed):
    """Packed SOR arrays of a diagonally dominant random system (see flow.methods.deepflow.variational)."""
    rng = np.random.default_rng(seed)
    shape = (height + 2, 2, variational._packed_width(width))
    links = [np.zeros(shape, np.float32) for _ in range(2)]
    for link in links:
        link[1:-1, :, 1 : (width + 1) // 2 + 1] = rng.uniform(
            0.0, 0.3, (height, 2, (width + 1) // 2)
        )
    coef = rng.uniform(-0.2, 0.2, (height + 2, 5, 2, shape[2])).astype(np.float32)
    coef[:, 3:] = rng.uniform(0.5, 1.0, (height + 2, 2, 2, shape[2]))
    return links[0], links[1], coef


def _plain_red_black(du, dv, east, south, coef, n_sor):
    """Sweep after sweep, all red rows then all black rows: the textbook order."""
    for _ in range(n_sor):
        for colour in (0, 1):
            for y in range(du.shape[0] - 2):
                variational._sor_row(du, dv, east, south, coef, colour, y, np.float32(1.6))


# The pipelined and plain orders do the same arithmetic; only the compiler's
# choice of fused multiply-adds may differ between the two call sites.
ROUNDING = 1e-6


def test_pipelined_sor_is_plain_red_black():
    east, south, coef = _random_system(37, 53, seed=1)
    start = np.random.default_rng(2).standard_normal((2,) + east.shape).astype(np.float32)
    expected = start.copy()
    _plain_red_black(expected[0], expected[1], east, south, coef, 25)
    assert np.abs(expected - start).max() > 0.1
    for chunk in (1, 4, 25):
        got = start.copy()
        variational._sor(got[0], got[1], east, south, coef, 25, 1.6, chunk)
        np.testing.assert_allclose(got, expected, rtol=0, atol=ROUNDING, err_msg=f"chunk {chunk}")


def test_fused_setup_and_sweeps_equal_the_stages_run_in_turn():
    height, width = 41, 57
    rng = np.random.default_rng(3)
    image = cv2.GaussianBlur(rng.standard_normal((height, width)).astype(np.float32), (0, 0), 2)
    flow = np.dstack([np.full((height, width), 0.4), np.full((height, width), -0.3)]).astype(
        np.float32
    )
    packed = (height + 2, 2, variational._packed_width(width))
    data = np.empty((height + 2, variational._N_DATA) + packed[1:], np.float32)
    level = np.empty((height + 2, variational._N_LEVEL) + packed[1:], np.float32)
    variational._prepare_level(
        image, np.roll(image, 1, axis=1), flow, (1.0, 1.0), 0.8 * flow, (1.0, 1.0),
        np.full((height, width), 4.0, np.float32), np.full((height, width), 0.5, np.float32),
        0.25, np.empty((13, height, width), np.float32), data, level, True,
    )  # fmt: skip
    results = []
    for fused in (True, False):
        du, dv, east, south, a = (np.zeros(packed, np.float32) for _ in range(5))
        total = np.empty((height + 2, 2) + packed[1:], np.float32)
        coef = np.empty((height + 2, variational._N_COEF) + packed[1:], np.float32)
        consts = (0.5, 5.0, 1e-6)
        for _ in range(3):
            if fused:
                variational._outer_iteration(
                    level, data, du, dv, total, a, east, south, coef, *consts, width, 25, 1.6, 7
                )
            else:
                variational._total_rows(level, du, dv, total, height, width, 0, height)
                variational._smoothness_rows(total, level, a, consts[2], width, 0, height)
                variational._link_rows(a, east, south, height, width, 0, height)
                variational._coef_rows(level, data, du, dv, east, south, coef, *consts, 0, height)
                _plain_red_black(du, dv, east, south, coef, 25)
        results.append(np.stack([du, dv]))
    assert np.abs(results[1]).max() > 0.01
    np.testing.assert_allclose(results[0], results[1], rtol=0, atol=ROUNDING)


def test_same_input_gives_the_same_bytes():
    reference, current = low_texture_pair(1.3, -0.4)
    first = deepflow_module.DeepFlow().calc(reference, current)
    again = deepflow_module.DeepFlow().calc(reference, current)
    assert first.tobytes() == again.tobytes()


def test_refine_refuses_mismatched_arrays():
    params = variational.VariationalParams()
    reference = np.zeros((40, 50), np.float32)
    with pytest.raises(ValueError, match=r"\(40, 60\).*\(40, 50\)"):
        variational.refine(reference, np.zeros((40, 60), np.float32), params)
    with pytest.raises(ValueError, match="uint16"):
        variational.refine(reference.astype(np.uint16), reference.astype(np.uint16), params)
    with pytest.raises(ValueError, match=r"\(20, 25, 2\).*\(40, 50\)"):
        variational.refine(reference, reference, params, match_flow=np.zeros((20, 25, 2), np.float32),
                           match_weight=np.zeros((40, 50), np.float32))
    with pytest.raises(ValueError, match=r"\(40, 51\).*\(40, 50\)"):
        variational.refine(reference, reference, params, match_flow=np.zeros((40, 50, 2), np.float32),
                           match_weight=np.zeros((40, 51), np.float32))


def test_registry_and_parameters():
    # Importing the module registers both names (flow.methods imports it too).
    assert {"deepflow", "deepmatching"} <= set(registry.available())
    method = deepflow_module.DeepFlow(preset="fast", alpha=1.5)
    params = method.params()
    assert params["alpha"] == 1.5 and params["eta"] == 0.8 and params["preset"] == "fast"
    assert params["beta"] == 32.0 and params["ngh_rad"] is None
    with pytest.raises(ValueError, match="unknown parameter"):
        deepflow_module.DeepFlow(alhpa=1.0)
    with pytest.raises(ValueError, match="unknown preset"):
        deepflow_module.DeepFlow(preset="nope")
    with pytest.raises(ValueError, match="equal size"):
        method.calc(np.zeros((32, 32), np.uint8), np.zeros((32, 40), np.uint8))


def test_motorcycle_large_displacement_within_reach():
    """Middlebury 2014 "Motorcycle" (7-60 px disparities) with the default parameters: the
    matching's reach scales with the image, so the motion is found (EPE was 18 px with a fixed
    32 px radius). The disparity is the left image's (left pixel x shows right pixel x - d:
    checked photometrically, |R(x - d) - L(x)| is 11 grey levels against 17 for the other
    reading), so the flow from the left image to the right is (-disparity, 0); occluded
    pixels count."""
    from skimage import data  # a test dependency (pyproject: [test])

    left, right, disparity = data.stereo_motorcycle()
    reference = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    current = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    flow = deepflow_module.DeepFlow().calc(reference, current)
    known = np.isfinite(disparity)
    epe = float(np.hypot(flow[..., 0] + np.where(known, disparity, 0.0), flow[..., 1])[known].mean())
    print(f"Motorcycle mean EPE {epe:.2f} px")
    assert epe <= 3.0


def test_member_motion_takes_the_along_member_motion_that_matches_the_pois():
    """The outline fixes the motion across a member; along it, where the mask's ends are no
    member ends, the fitted field can be wrong: the POIs then take the across-member motion
    with the along-member motion given (the dense flow's), and only where that matches them
    better (a wrong along-member motion given is refused)."""
    reference, (current,), poi = bar_frames([3.0], bar_std=12.0)
    reference, current = reference.astype(np.float32), current.astype(np.float32)
    region = deepflow_module._Region.of(reference, poi, 1, member=True, texture=False)
    prior = np.tile([3.0, 0.0], (len(region.prior_rows), 1))
    fit = region.member.fit(current, prior)
    assert fit.ok
    u, v, own, taken, _ = region.motion(reference, current, fit)
    assert taken is None and abs(np.mean(u) - 3.0) < 0.05 and abs(np.mean(v)) < 0.05

    t_dir = region.member.axes[:, 0]
    wrong = fit.params.copy()
    wrong[3] += 1.5  # the along-member translation, off by 1.5 px
    bad = deepflow_module.MemberFit(True, wrong, fit.cov, fit.n_used, fit.n_profiles, fit.scale)
    u, v, off, taken, _ = region.motion(reference, current, bad)
    assert taken is None and abs(np.mean(u * t_dir[0] + v * t_dir[1]) - 1.5) < 0.05 and off > own
    zero = np.zeros(len(region.rows))
    u, v, fixed, taken, _ = region.motion(reference, current, bad, zero)
    assert taken is not None and abs(np.mean(v)) < 0.05 and abs(np.mean(u) - 3.0) < 0.05
    assert fixed < off
    # A wrong along-member motion given does not replace a right field.
    u, v, kept, taken, _ = region.motion(reference, current, fit, np.full(len(region.rows), 2.0))
    assert taken is None and kept == own and abs(np.mean(v)) < 0.05


def test_a_texture_too_weak_to_be_taken_is_not_fitted(monkeypatch):
    """The painted bar's faint paint is never taken over its outline (see ``_choose``): its
    affine correlation is not even tried, on every full measurement (a quarter of their time)."""
    reference, frames, poi = bar_frames(np.array([1.0, 2.0]), bar_std=1.0)
    method = deepflow_module.DeepFlow()
    method.bind(reference, poi)
    region = method._regions[0]
    assert region.texture is not None and min(region.texture.gradient_rms) < deepflow_module.MIN_TEXTURE_GRADIENT
    calls = []
    failed = RegionMotion(np.zeros(6), False, (float("nan"), float("nan")), float("nan"), 0, 0.0)
    monkeypatch.setattr(type(region.texture), "fit", lambda self, *a, **k: calls.append(1) or failed)
    for frame in frames:
        flow = method.calc(reference, frame)
        assert np.isfinite(flow[..., 0][poi]).all()
    assert calls == [] and method.counts["full_frames"] == len(frames)
    # The same bar with a strong paint is fitted (the check can fail).
    reference, frames, poi = bar_frames(np.array([1.0]), bar_std=40.0)
    method = deepflow_module.DeepFlow()
    method.bind(reference, poi)
    method.calc(reference, frames[0])
    assert calls


def _fine_speckle(height, width, seed=5):
    # A periodic speckle with content up to half the sampling rate (white noise through a
    # 0.8 px Gaussian, in the Fourier domain), as DIC images have.
    rng = np.random.default_rng(seed)
    fy, fx = np.fft.fftfreq(height)[:, None], np.fft.fftfreq(width)[None, :]
    gain = np.exp(-2 * (np.pi * 0.8) ** 2 * (fx**2 + fy**2))
    noise = np.real(np.fft.ifft2(np.fft.fft2(rng.standard_normal((height, width))) * gain))
    return 40.0 * noise / noise.std() + 128.0


def _fourier_shift(image, dx):
    # ``image`` moved by dx px toward +x, exactly for a band-limited periodic image.
    fx = np.fft.fftfreq(image.shape[1])[None, :]
    return np.real(np.fft.ifft2(np.fft.fft2(image) * np.exp(-2j * np.pi * fx * dx)))


def test_bspline_warp_returns_the_image_at_whole_pixels_and_interpolates_a_shift():
    image = _fine_speckle(48, 64).astype(np.float32)
    coef = np.empty_like(image)
    variational._bspline_coefficients(image, coef)
    out, inside = np.empty_like(image), np.empty_like(image)
    variational._warp(coef, np.zeros((48, 64, 2), np.float32), out, inside, True)
    np.testing.assert_allclose(out, image, atol=1e-3)
    # Sampling at x + 0.3 must give the image moved by -0.3 px (away from the border).
    shift = np.dstack([np.full((48, 64), 0.3), np.zeros((48, 64))]).astype(np.float32)
    truth = _fourier_shift(image.astype(np.float64), -0.3)[8:-8, 8:-8]
    errors = {}
    for bspline in (True, False):
        variational._warp(coef if bspline else image, shift, out, inside, bspline)
        errors[bspline] = np.abs(out[8:-8, 8:-8] - truth).mean()
    # On this speckle (std 40 grey levels) the cubic convolution is off by 2.2 on average, the spline by half that.
    assert errors[True] < 0.6 * errors[False], errors


@pytest.mark.parametrize("dx", [0.1, 0.25])
def test_subpixel_shift_of_a_fine_speckle_is_read_without_interpolation_bias(dx):
    # With the cubic-convolution warp this read 24 % (0.1 px) and 12 % (0.25 px) long, DIC
    # Challenge Sample 14's speckle shifted 0.1 px 9 %; with the B-spline 3.4 % and 2.2 % here.
    reference = _fine_speckle(96, 160)
    current = _fourier_shift(reference, dx)
    flow = variational.refine(reference.astype(np.float32), current.astype(np.float32),
                              variational.VariationalParams())
    got = float(flow[16:-16, 16:-16, 0].mean())
    assert abs(got - dx) < 0.05 * dx, got
    assert abs(float(flow[16:-16, 16:-16, 1].mean())) < 0.002


@pytest.mark.parametrize("shape", [(2, 3), (4, 6), (9, 17), (40, 60)])
def test_bspline_coefficients_give_the_image_back_on_any_side(shape):
    # A line shorter than the prefilter's 16-sample start sums its whole mirrored period (a
    # truncated sum was off by up to 14 grey levels at a side of 2).
    image = (np.random.default_rng(1).random(shape) * 255).astype(np.float32)
    coef, out, inside = np.empty_like(image), np.empty_like(image), np.empty_like(image)
    variational._bspline_coefficients(image, coef)
    variational._warp(coef, np.zeros(shape + (2,), np.float32), out, inside, True)
    np.testing.assert_allclose(out, image, atol=1e-3)


def test_a_tracked_frame_tries_its_key_s_outline_model_and_its_neighbours_first() -> None:
    from flow.methods.deepflow.member import BLURS
    from flow.methods.deepflow.method import _first_models
    shift = len(BLURS)  # the whole-profile match
    assert _first_models(0) == (0, 1, shift)
    assert _first_models(2) == (0, 1, 2, 3, shift)
    assert _first_models(len(BLURS) - 1) == (0, len(BLURS) - 2, len(BLURS) - 1, shift)
    assert _first_models(shift) == (0, shift)


def test_a_large_windows_solver_scratch_is_not_kept_between_solves(monkeypatch):
    """The solver's scratch (about 240 bytes a pixel: 2 GB for a whole 4K frame) is kept
    between solves only up to WORKSPACE_KEEP_BYTES: beyond, it would add to the regions' fits
    that follow it. The flow is the same either way."""
    height, width = 96, 128
    reference = to_u8(textured(height, width, seed=4))
    current = to_u8(warp_forward(textured(height, width, seed=4), rigid_flow(height, width, 0.0, 1.3, -0.4)))
    kept = deepflow_module.DeepFlow()
    kept_flow = kept.calc(reference, current)
    assert 0 < kept._workspace.nbytes() <= deepflow_module.WORKSPACE_KEEP_BYTES
    monkeypatch.setattr(deepflow_module, "WORKSPACE_KEEP_BYTES", kept._workspace.nbytes() - 1)
    dropped = deepflow_module.DeepFlow()
    first = dropped.calc(reference, current)
    assert dropped._workspace.nbytes() == 0
    assert np.array_equal(first, kept_flow) and np.array_equal(dropped.calc(reference, current), kept_flow)
