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


def test_cropped_recording_uses_the_full_sensor_calibration(lens_clip, tmp_path) -> None:
    """A video that is a window of the calibrated sensor (--video-origin) measures like
    the full frames with that window as --roi."""
    x0, y0, w, h = 4, 2, 160, 120
    crops = tmp_path / "crops"
    crops.mkdir()
    for path in sorted(lens_clip["frames"].iterdir()):
        cv2.imwrite(str(crops / path.name), cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)[y0:y0 + h, x0:x0 + w])
    (x1, y1, x2, y2) = (float(v) for v in lens_clip["between"].split(","))
    common = ["--fps", "30", "--method", "dis", "--known-length", str(100 * MM_PER_IDEAL_PX),
              "--calibration", str(lens_clip["calibration"]), "--no-progress"]
    whole, cropped = tmp_path / "whole.csv", tmp_path / "cropped.csv"
    assert main(["track", str(lens_clip["frames"]), "--roi", f"{x0},{y0},{w},{h}", "--rect", "10,8,106,78",
                 "--between", lens_clip["between"], *common, "--out", str(whole)]) == 0
    recording = tmp_path / "recording.json"
    recording.write_text(json.dumps({"video_origin_px": [x0, y0]}))
    assert main(["track", str(crops), "--video-origin", str(recording), "--rect", f"{10 - x0},{8 - y0},106,78",
                 "--between", f"{x1 - x0},{y1 - y0},{x2 - x0},{y2 - y0}", *common, "--out", str(cropped)]) == 0
    a, b = (list(csv.DictReader(p.open())) for p in (whole, cropped))
    for key in ("dx_px", "dy_px", "dx_mm"):
        assert np.allclose([float(r[key]) for r in a], [float(r[key]) for r in b], atol=1e-6), key
    assert json.loads(cropped.with_suffix(".json").read_text())["calibration"]["video_origin"] == [x0, y0]
    # Parts of the cropped run merge to the same numbers (the scale from --between needs the origin).
    between = f"{x1 - x0},{y1 - y0},{x2 - x0},{y2 - y0}"
    parts = []
    for span in ("0:3", "3:8"):
        parts.append(str(tmp_path / f"part{span[0]}.npz"))
        assert main(["track", str(crops), "--video-origin", f"{x0},{y0}", "--rect", f"{10 - x0},{8 - y0},106,78",
                     *common, "--between", between, "--frames", span, "--raw-tracks", parts[-1]]) == 0
    merged = tmp_path / "merged.csv"
    assert main(["merge", *parts, "--known-length", str(100 * MM_PER_IDEAL_PX), "--between", between,
                 "--out", str(merged)]) == 0
    assert merged.read_text() == cropped.read_text()
    # A window that does not fit on the sensor, and an origin without a calibration, are refused.
    assert main(["track", str(crops), "--video-origin", "200,0", "--rect", "0,0,50,50", *common,
                 "--out", str(tmp_path / "bad.csv")]) == 2
    assert main(["track", str(crops), "--video-origin", "1,1", "--rect", "0,0,50,50", "--fps", "30",
                 "--out", str(tmp_path / "bad.csv"), "--no-progress"]) == 2
    assert not (tmp_path / "bad.csv").exists()


@pytest.mark.parametrize("scale_kind", ["scale-file", "known-length"])
def test_merge_of_parts_scales_like_one_track_run(lens_clip, tmp_path, scale_kind) -> None:
    """`merge` carries the scale points through the calibration exactly as `track` does: the
    same mm per pixel and a byte-identical CSV, whether the points come from a scale file or
    from --known-length/--between (issue 14: merge once skipped the scale file's points)."""
    length = 100 * MM_PER_IDEAL_PX
    if scale_kind == "scale-file":
        scale_file = tmp_path / "scale.json"
        scale_file.write_text(json.dumps({"known_length_mm": length,
                                          "between_px": [float(v) for v in lens_clip["between"].split(",")]}))
        scale = ["--scale-file", str(scale_file)]
    else:
        scale = ["--known-length", str(length), "--between", lens_clip["between"]]
    common = [str(lens_clip["frames"]), "--fps", "30", "--rect", "6,6,110,80", "--method", "dis",
              "--calibration", str(lens_clip["calibration"]), "--no-progress"]
    whole = tmp_path / "whole.csv"
    assert main(["track", *common, *scale, "--out", str(whole)]) == 0
    parts = [str(tmp_path / "a.npz"), str(tmp_path / "b.npz")]
    for span, part in zip(("0:4", "4:8"), parts, strict=True):
        assert main(["track", *common, "--frames", span, "--raw-tracks", part]) == 0
    merged = tmp_path / "merged.csv"
    assert main(["merge", *parts, *scale, "--out", str(merged)]) == 0
    assert merged.read_text() == whole.read_text()
    track_meta, merge_meta = (json.loads(p.with_suffix(".json").read_text()) for p in (whole, merged))
    assert merge_meta["scale"]["mm_per_px"] == track_meta["scale"]["mm_per_px"]
    # The undistorted scale, not the raw one: 100 ideal px between the points.
    assert track_meta["scale"]["mm_per_px"] == pytest.approx(MM_PER_IDEAL_PX, rel=0.002)
    assert "(undistorted)" in merge_meta["scale"]["source"]


def test_an_rms_that_is_no_number_is_reported_as_null(lens_clip, tmp_path) -> None:
    """A calibration's rms_px is only reported: NaN there (JSON allows it in Python) once failed
    the run at its very end, when the sidecar was written, after every frame was measured."""
    calibration = tmp_path / "calibration.json"
    calibration.write_text(lens_clip["calibration"].read_text().replace('"rms_px": 0.0', '"rms_px": NaN'))
    out = tmp_path / "out.csv"
    assert main(["track", str(lens_clip["frames"]), "--fps", "30", "--rect", "6,6,110,80", "--method", "dis",
                 "--calibration", str(calibration), "--max-frames", "3", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["calibration"]["rms_px"] is None and meta["calibration"]["camera_matrix"] == K.tolist()
