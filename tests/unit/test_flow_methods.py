"""Accuracy of the registry's methods on synthetic sequences with known motion."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

from flow.io.source import open_source
from flow.measure.driver import track_dense, track_sparse
from flow.measure.quality import measure
from flow.methods import registry
from flow.methods.base import CROP_MARGIN_PX
from flow.methods.klt import KLT

sys.path.insert(0, str(Path(__file__).parent))
from _fresh_python import run_fresh  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]

# The sub-pixel test below skips these two: `deepflow` has its own, stricter accuracy tests
# (tests/unit/test_deepflow.py), and `deepmatching` is an ablation whose matches sit on an
# integer grid of atomic patches (interpolated between them), so 0.05 px on a 0.1 px shift is
# not what it is built for; its accuracy is covered in tests/unit/test_deepmatching.py.
OTHER_TESTS = {"deepflow", "deepmatching"}
REFERENCE_FRAME_METHODS = [n for n, kind in registry.kinds().items() if kind == "dense"]
DENSE = [n for n in REFERENCE_FRAME_METHODS if n not in OTHER_TESTS]
# Parameters that keep the slow methods to a second or two on the 40-frame drift sequence
# (tvl1 at its defaults takes ~2 minutes there); accuracy stays well inside the bound.
FAST_PARAMS = {"deepflow": {"preset": "fast"}, "tvl1": {"warps": 2, "scales": 2, "epsilon": 0.02}}


def texture(width: int, height: int, dx: float = 0.0, dy: float = 0.0, *, seed: int = 0,
            max_freq: float = 0.12) -> np.ndarray:
    """Band-limited analytic texture seen shifted by (dx, dy): exact sub-pixel motion."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(float)
    x, y = x - dx, y - dy
    image = np.zeros((height, width))
    for _ in range(40):
        fx, fy = rng.uniform(-max_freq, max_freq, 2)
        image += rng.uniform(0.5, 1.0) * np.cos(2 * np.pi * (fx * x + fy * y) + rng.uniform(0, 2 * np.pi))
    return 128 + 45 * image / np.sqrt(40 * 0.4)


def as_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def test_registry_lists_dense_and_sparse_methods() -> None:
    names = registry.available()
    for name in ("deepflow-opencv", "dis", "farneback", "klt", "klt-ref"):
        assert name in names
    assert all(registry.describe()[n] for n in names)
    assert registry.kinds()["klt"] == "sparse" and registry.kinds()["dis"] == "dense"
    assert set(registry.unavailable()).isdisjoint(names)


def test_registry_says_why_a_method_is_unavailable() -> None:
    # A fresh interpreter where DeepFlow's refinement cannot be imported (as where a
    # dependency is missing): its methods are left out, the registry says why, and the CLI
    # falls back to deepflow-opencv with that reason, asking the registry only.
    code = ("import contextlib, io, json, sys\n"
            "sys.modules['flow.methods.deepflow.variational'] = None\n"
            "from flow import cli\nfrom flow.methods import registry\n"
            "out = io.StringIO()\n"
            "with contextlib.redirect_stdout(out):\n    cli.main(['methods'])\n"
            "print(json.dumps([registry.available(), registry.unavailable(),"
            " cli._default_method(), out.getvalue()]))\n")
    run = run_fresh(code)
    assert run.returncode == 0, run.stderr
    names, missing, (default, note), listing = json.loads(run.stdout.splitlines()[-1])
    assert {"deepflow", "deepflow-dense", "deepmatching"} <= set(missing)
    assert "dis" in names and set(missing).isdisjoint(names)
    assert "flow.methods.deepflow.variational" in missing["deepflow"]
    assert default == "deepflow-opencv" and f"({missing['deepflow']})" in note
    assert f"(deepflow unavailable: {missing['deepflow']})" in listing


@pytest.mark.parametrize("name", DENSE)
def test_dense_method_recovers_subpixel_translation(name: str) -> None:
    method = registry.get_method(name)
    reference = as_u8(texture(160, 120))
    ys, xs = np.mgrid[30:90:3, 40:120:3]
    for shift in [(0.1, 0.0), (0.0, -0.1), (0.37, -0.21), (1.5, 0.8), (-2.3, 1.1), (5.0, -3.0)]:
        flow = method.calc(reference, as_u8(texture(160, 120, *shift)))
        assert flow.shape == (120, 160, 2) and flow.dtype == np.float32
        at_pois = flow[ys, xs].reshape(-1, 2)
        error = np.abs(at_pois.mean(axis=0) - np.asarray(shift))
        assert error.max() < 0.05, f"{name}: shift {shift} measured {at_pois.mean(axis=0)}"


def test_dense_method_rejects_bad_pairs() -> None:
    method = registry.get_method("dis")
    with pytest.raises(ValueError, match="equal size"):
        method.calc(np.zeros((10, 10), np.uint8), np.zeros((10, 12), np.uint8))
    with pytest.raises(ValueError, match="2-D grey"):
        method.calc(np.zeros((10, 10, 3), np.uint8), np.zeros((10, 10, 3), np.uint8))
    with pytest.raises(ValueError, match="unknown method"):
        registry.get_method("nope")


def _drift_sequence(folder, n_frames: int = 40) -> np.ndarray:
    """Structure band oscillating in x, static background, a top band creeping right, noise."""
    import cv2

    rng = np.random.default_rng(7)
    truth = 1.5 * np.sin(2 * np.pi * np.arange(n_frames) / 20.0)  # back to 0 at frames 20, 40
    background = texture(160, 120, seed=1, max_freq=0.2)
    for i in range(n_frames):
        image = background.copy()
        structure = texture(160, 120, truth[i], 0.0, seed=2, max_freq=0.15)
        image[45:85] = structure[45:85]
        image[:28] = texture(160, 28, 0.3 * i, 0.0, seed=3, max_freq=0.2)  # moving background
        image += rng.normal(0, 2.0, image.shape)
        cv2.imwrite(str(folder / f"f{i:03d}.png"), as_u8(image))
    return truth


@pytest.fixture(scope="module")
def drift(tmp_path_factory):
    folder = tmp_path_factory.mktemp("drift")
    truth = _drift_sequence(folder)
    mask = np.zeros((120, 160), bool)
    mask[50:80, 10:150] = True
    return folder, truth, mask


def test_klt_drifts(drift) -> None:
    folder, truth, mask = drift
    result = measure(track_sparse(open_source(folder, fps=30.0), KLT(), mask), filter_enabled=False)
    assert result.valid.all()
    # KLT averages moving-background corners and integrates frame-to-frame: at the end,
    # where the structure is back at rest, it reports motion.
    assert np.abs(result.filtered.dx - truth)[-5:].mean() > 0.5


@pytest.mark.parametrize("name", REFERENCE_FRAME_METHODS)
def test_reference_frame_methods_do_not_drift(drift, name: str) -> None:
    """Same sequence as :func:`test_klt_drifts`: every frame against the reference, no drift."""
    folder, truth, mask = drift
    poi_xy = np.stack(np.nonzero(mask)[::-1], axis=1)[::7]
    params = FAST_PARAMS.get(name, {})
    tracks = track_dense(open_source(folder, fps=30.0), lambda: registry.get_method(name, **params), poi_xy)
    result = measure(tracks)
    assert result.valid.all()
    error = np.abs(result.filtered.dx - truth)
    assert error.max() < 0.1, f"{name}: max error {error.max():.3f} px"
    assert error[-5:].mean() < 0.06, f"{name}: {error[-5:].mean():.3f} px off at the end"


def test_klt_ref_follows_features_against_reference(tmp_path) -> None:
    truth = _drift_sequence(tmp_path, n_frames=12)
    mask = np.zeros((120, 160), bool)
    mask[50:80, 10:150] = True
    tracks = track_sparse(open_source(tmp_path, fps=30.0), registry.get_method("klt-ref", use_mask=True), mask)
    result = measure(tracks)
    assert np.abs(result.filtered.dx - truth).max() < 0.15


@pytest.mark.parametrize("name", DENSE + ["deepmatching"])
def test_dense_methods_solve_only_the_window_they_are_asked_for(name: str) -> None:
    """Bound to a small POI mask in a large frame, every dense method solves the POIs' window
    (bounding box + margin) and leaves the rest NaN; it reads the POIs as the whole-frame
    solve does; ``crop=False`` and a call without bind solve the whole frame."""
    params = FAST_PARAMS.get(name, {})
    reference = as_u8(texture(480, 320, seed=4))
    current = as_u8(texture(480, 320, 1.3, -0.6, seed=4))
    mask = np.zeros(reference.shape, bool)
    mask[150:170, 200:240] = True
    method = registry.get_method(name, **params)
    method.bind(reference, mask)
    flow = method.calc(reference, current)
    solved = np.isfinite(flow[..., 0])
    rows, cols = np.nonzero(solved)
    margin = method.window_margin(reference.shape)
    assert margin >= CROP_MARGIN_PX
    assert (rows.min(), rows.max() + 1) == (max(150 - margin, 0), min(170 + margin, 320))
    assert (cols.min(), cols.max() + 1) == (max(200 - margin, 0), min(240 + margin, 480))
    assert solved.sum() == (np.ptp(rows) + 1) * (np.ptp(cols) + 1) < 0.8 * reference.size
    whole = registry.get_method(name, crop=False, **params)
    whole.bind(reference, mask)
    full = whole.calc(reference, current)
    assert np.isfinite(full).all()
    assert np.array_equal(registry.get_method(name, **params).calc(reference, current), full)
    at_window, at_whole = flow[mask].mean(axis=0), full[mask].mean(axis=0)
    tolerance = 0.15 if name == "deepmatching" else 0.05
    assert np.abs(at_window - (1.3, -0.6)).max() < tolerance, at_window
    assert np.abs(at_window - at_whole).max() < tolerance, (at_window, at_whole)
