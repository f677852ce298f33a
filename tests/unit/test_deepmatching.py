"""DeepMatching accuracy on a large-displacement pair with known flow."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import flow.methods.deepflow as deepflow_module
from flow.deepmatching import MatchParams, deep_matching, densify, pixel_descriptors

sys.path.insert(0, str(Path(__file__).parent))  # shared synthetic pairs
from _deepflow_synth import epe, rigid_flow, textured, to_u8, visible, warp_forward  # noqa: E402


@pytest.fixture(scope="module")
def large_pair():
    height, width = 128, 256
    truth = rigid_flow(height, width, 5.0, 40.0, 0.0)
    reference = textured(height, width, seed=3)
    current = warp_forward(reference, truth)
    return to_u8(reference), to_u8(current), truth


def test_descriptors_have_eight_rectified_orientations():
    image = textured(32, 48, seed=1)
    desc = pixel_descriptors(image, MatchParams())
    assert desc.shape == (32, 48, 8) and desc.dtype == np.float32
    assert (desc >= 0).all()


def test_matches_within_two_pixels(large_pair):
    reference, current, truth = large_pair
    grid = deep_matching(reference, current, MatchParams(ngh_rad=64))
    matches = grid.as_array()
    height, width = reference.shape
    xi = np.clip(np.rint(matches[:, 0]).astype(int), 0, width - 1)
    yi = np.clip(np.rint(matches[:, 1]).astype(int), 0, height - 1)
    err = np.hypot(
        matches[:, 2] - (matches[:, 0] + truth[yi, xi, 0]),
        matches[:, 3] - (matches[:, 1] + truth[yi, xi, 1]),
    )
    within = float((err <= 2.0).mean())
    print(
        f"{len(matches)} verified matches of {grid.valid.size} patches; {100 * within:.1f} % within 2 px"
    )
    assert len(matches) >= 0.5 * grid.valid.size
    assert within >= 0.90
    assert ((grid.score >= 0) & (grid.score <= 1)).all()


def test_reciprocal_check_removes_matches(large_pair):
    reference, current, _ = large_pair
    both = deep_matching(reference, current, MatchParams(ngh_rad=64))
    forward = deep_matching(reference, current, MatchParams(ngh_rad=64, reciprocal=False))
    assert both.valid.sum() <= forward.valid.sum()


def test_dense_interpolation(large_pair):
    reference, current, truth = large_pair
    flow = deepflow_module.DeepMatchingDense(ngh_rad=64).calc(reference, current)
    value = epe(flow, truth, visible(truth), margin=4)
    print(f"deepmatching (linear interpolation) EPE {value:.3f} px")
    assert flow.shape == reference.shape + (2,)
    assert value < 1.0
    grid = deep_matching(reference, current, MatchParams(ngh_rad=64))
    _, weight = densify(grid, reference.shape, nearest=True)
    assert weight.shape == reference.shape and weight.max() <= 1.0


def test_bad_parameters():
    image = np.zeros((64, 64), np.uint8)
    with pytest.raises(ValueError, match="downscale"):
        deep_matching(image, image, MatchParams(downscale=0))
    with pytest.raises(ValueError, match="interpolation"):
        deepflow_module.DeepMatchingDense(interpolation="cubic")
