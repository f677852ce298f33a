"""DeepMatching accuracy on a large-displacement pair with known flow."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import flow.methods.deepflow.deepmatching as dm
import flow.methods.deepflow.method as deepflow_module
from flow.methods.deepflow.deepmatching import MatchParams, deep_matching, densify

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
    desc = dm._descriptor_planes(image, MatchParams())
    assert desc.shape == (8, 32, 48) and desc.dtype == np.float32
    assert (desc >= 0).all()


def test_matches_within_two_pixels(large_pair):
    reference, current, truth = large_pair
    grid = deep_matching(reference, current, MatchParams(ngh_rad=64))
    ok = grid.valid
    height, width = reference.shape
    xi = np.clip(np.rint(grid.x[ok]).astype(int), 0, width - 1)
    yi = np.clip(np.rint(grid.y[ok]).astype(int), 0, height - 1)
    err = np.hypot(grid.dx[ok] - truth[yi, xi, 0], grid.dy[ok] - truth[yi, xi, 1])
    within = float((err <= 2.0).mean())
    print(
        f"{int(ok.sum())} verified matches of {ok.size} patches; {100 * within:.1f} % within 2 px"
    )
    assert ok.sum() >= 0.5 * ok.size
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


def test_shared_products_give_both_directions_correlations():
    rng = np.random.default_rng(4)
    f1 = rng.random((8, 22, 30), dtype=np.float32)
    f2 = rng.random((8, 22, 30), dtype=np.float32)
    f1[:, 8:12, 4:8] = 0.0  # a blank patch has no correlation
    n1, n2 = dm._patch_norms(f1), dm._patch_norms(f2)
    ny, nx, R = 5, 7, 3
    D = 2 * R + 1
    forward = np.zeros((ny, D, D, nx), np.float32)
    backward = np.zeros_like(forward)
    dm._atomic_both(f1, f2, n1, n2, R, 0, 4, forward, backward)
    dm._atomic_both(f1, f2, n1, n2, R, 4, D, forward, backward)

    def correlation(a, b, na, nb, i, j, dy, dx):
        y, x = 4 * i + dy, 4 * j + dx
        if not (0 <= y <= a.shape[1] - 4 and 0 <= x <= a.shape[2] - 4):
            return 0.0
        if na[4 * i, 4 * j] <= 1e-6 or nb[y, x] <= 1e-6:
            return 0.0
        dot = np.sum(a[:, 4 * i : 4 * i + 4, 4 * j : 4 * j + 4] * b[:, y : y + 4, x : x + 4])
        return dot / (na[4 * i, 4 * j] * nb[y, x])

    for i in range(ny):
        for j in range(nx):
            for k in range(D):
                for kx in range(D):
                    fw = correlation(f1, f2, n1, n2, i, j, k - R, kx - R)
                    bw = correlation(f2, f1, n2, n1, i, j, k - R, kx - R)
                    assert forward[i, k, kx, j] == pytest.approx(fw, abs=1e-5)
                    assert backward[i, k, kx, j] == pytest.approx(bw, abs=1e-5)


def test_fast_power_matches_pow():
    x = np.concatenate([np.linspace(0.0, 1.0, 10001), [1e-20, 3e-8]]).astype(np.float32)
    y = x.copy()
    dm._power(y, 1.4, np.empty(x.size, np.int32))
    truth = x.astype(np.float64) ** 1.4
    assert np.all(np.abs(y - truth) <= 2e-6 * truth + 1e-30)


def test_bad_parameters():
    image = np.zeros((64, 64), np.uint8)
    with pytest.raises(ValueError, match="downscale"):
        deep_matching(image, image, MatchParams(downscale=0))
    with pytest.raises(ValueError, match="interpolation"):
        deepflow_module.DeepMatchingDense(interpolation="cubic")


def test_mismatched_or_unsupported_images_raise_before_the_kernels():
    image = np.zeros((64, 64), np.uint8)
    with pytest.raises(ValueError, match=r"\(64, 48\).*\(64, 64\)"):
        deep_matching(image, np.zeros((64, 48), np.uint8))
    with pytest.raises(ValueError, match="ndim 3"):
        deep_matching(image, np.zeros((64, 64, 3), np.uint8))
    with pytest.raises(ValueError, match="float64"):
        deep_matching(image, np.zeros((64, 64)))
