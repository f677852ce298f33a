"""Accuracy of the clean-room DeepFlow against ground truth and OpenCV's DeepFlow."""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

import flow.methods.deepflow as deepflow_module
from flow import registry

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
    print(f"large displacement: EPE ours {epe_ours:.3f} px, OpenCV DeepFlow {epe_cv:.3f} px")
    assert epe_ours < 0.5
    assert epe_cv > 10 * epe_ours


@pytest.mark.parametrize("shift", [0.1, 0.5, 1.0, 2.0])
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


def test_registry_and_parameters():
    # Importing the module registers both names (flow.methods imports it too).
    assert {"deepflow", "deepmatching"} <= set(registry._REGISTRY)
    method = deepflow_module.DeepFlow(preset="fast", alpha=1.5)
    params = method.params()
    assert params["alpha"] == 1.5 and params["eta"] == 0.8 and params["preset"] == "fast"
    assert params["beta"] == 32.0 and params["ngh_rad"] == 32.0
    with pytest.raises(ValueError, match="unknown parameter"):
        deepflow_module.DeepFlow(alhpa=1.0)
    with pytest.raises(ValueError, match="unknown preset"):
        deepflow_module.DeepFlow(preset="nope")
    with pytest.raises(ValueError, match="equal size"):
        method.calc(np.zeros((32, 32), np.uint8), np.zeros((32, 40), np.uint8))
