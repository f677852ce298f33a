"""End to end: `refflow track --calibration` on a clip through a strongly distorting lens.

A textured plane moves by known shifts in ideal (pinhole) pixels; the camera
films it through barrel distortion. Near the image corner the lens shrinks the
motion by ~10 %; undistorting the frames (and carrying the mask and the
--between points drawn on the raw frames along) must give the true shift and
the true mm.
"""

from __future__ import annotations

import csv
import json

import cv2
import numpy as np
import pytest

from flow.cli import main

SIZE = (320, 240)
K = np.array([[300.0, 0, 162.0], [0, 300.0, 118.0], [0, 0, 1]])
DIST = np.array([-0.3, 0.09, 0.0, 0.0, 0.0])
SHIFTS_PX = np.array([0.0, 0.5, 1.0, 2.0, 3.0, 2.0, 1.0, 0.0])  # along x, ideal pixels
MM_PER_IDEAL_PX = 0.5


def texture(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Band-limited texture at any (ideal) coordinates: exact sub-pixel motion when shifted."""
    rng = np.random.default_rng(3)
    image = np.zeros_like(u)
    for _ in range(40):
        fx, fy = rng.uniform(-0.09, 0.09, 2)
        image += rng.uniform(0.5, 1.0) * np.cos(2 * np.pi * (fx * u + fy * v) + rng.uniform(0, 2 * np.pi))
    return 128 + 45 * image / 4.0


def distort(points_ideal: np.ndarray) -> np.ndarray:
    """Raw (distorted) pixels where the lens images ideal pixels."""
    normalised = (points_ideal - K[:2, 2]) / np.diag(K)[:2]
    homogeneous = np.hstack([normalised, np.ones((len(normalised), 1))])
    raw, _ = cv2.projectPoints(homogeneous, np.zeros(3), np.zeros(3), K, DIST)
    return raw.reshape(-1, 2)


@pytest.fixture(scope="module")
def lens_clip(tmp_path_factory):
    folder = tmp_path_factory.mktemp("lens")
    frames = folder / "frames"
    frames.mkdir()
    w, h = SIZE
    pixels = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    ideal = cv2.undistortPoints(pixels, K, DIST, None, None, K,
                                (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 50, 1e-12)).reshape(h, w, 2)
    for i, shift in enumerate(SHIFTS_PX):
        image = texture(ideal[..., 0] - shift, ideal[..., 1])
        cv2.imwrite(str(frames / f"f{i:03d}.png"), np.clip(np.rint(image), 0, 255).astype(np.uint8))
    calibration = folder / "calibration.json"
    calibration.write_text(json.dumps({"camera_matrix": K.tolist(), "dist_coeffs": DIST.tolist(),
                                       "image_size": list(SIZE), "rms_px": 0.0}))
    # Two points 100 ideal px apart near the corner, given where they appear in the raw frames.
    (x1, y1), (x2, y2) = distort(np.array([[20.0, 40.0], [120.0, 40.0]]))
    return {"frames": frames, "calibration": calibration, "between": f"{x1:.4f},{y1:.4f},{x2:.4f},{y2:.4f}"}


def run(lens_clip, tmp_path, *calibrated: str) -> np.ndarray:
    out = tmp_path / f"out{len(calibrated)}.csv"
    argv = ["track", str(lens_clip["frames"]), "--fps", "30", "--rect", "6,6,110,80", "--method", "dis",
            "--known-length", str(100 * MM_PER_IDEAL_PX), "--between", lens_clip["between"],
            *calibrated, "--out", str(out), "--no-progress"]
    assert main(argv) == 0
    with out.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert all(r["valid"] == "1" for r in rows)
    return np.array([[float(r["dx_px"]), float(r["dx_mm"])] for r in rows])


def test_undistortion_removes_the_lens_scale_error(lens_clip, tmp_path) -> None:
    moving = SHIFTS_PX >= 1.0
    raw = run(lens_clip, tmp_path)
    raw_ratio = raw[moving, 0] / SHIFTS_PX[moving]
    assert raw_ratio.mean() < 0.95, f"the lens must shrink the motion near the corner: {raw_ratio}"
    # A known length measured near the POIs cancels part of it, not all (~3.5 % here).
    raw_mm_ratio = raw[moving, 1] / (MM_PER_IDEAL_PX * SHIFTS_PX[moving])
    assert np.abs(raw_mm_ratio - 1).min() > 0.02, raw_mm_ratio
    fixed = run(lens_clip, tmp_path, "--calibration", str(lens_clip["calibration"]))
    ratio = fixed[moving, 0] / SHIFTS_PX[moving]
    assert np.abs(ratio - 1).max() < 0.01, ratio
    mm_ratio = fixed[moving, 1] / (MM_PER_IDEAL_PX * SHIFTS_PX[moving])
    assert np.abs(mm_ratio - 1).max() < 0.01, mm_ratio
    meta = json.loads((tmp_path / "out2.csv").with_suffix(".json").read_text())
    assert meta["scale"]["mm_per_px"] == pytest.approx(MM_PER_IDEAL_PX, rel=0.002)
    assert meta["calibration"]["camera_matrix"] == K.tolist()
