"""Calibration recovers the camera of synthetic checkerboard views; undistortion and scale."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flow.calibration import Undistorter, calibrate, scale_from_known_length
from flow.io import InputError, Roi

SIZE = (480, 360)
K = np.array([[420.0, 0, 236.0], [0, 415.0, 183.0], [0, 0, 1]])
DIST = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
BOARD = (8, 6)  # inner corners
SQUARE_MM = 20.0
PX_PER_MM = 12


def board_texture() -> np.ndarray:
    cols, rows = BOARD[0] + 1, BOARD[1] + 1
    margin = 1  # one white square around the board
    h, w = (rows + 2 * margin) * SQUARE_MM * PX_PER_MM, (cols + 2 * margin) * SQUARE_MM * PX_PER_MM
    y, x = np.mgrid[0:int(h), 0:int(w)] / (SQUARE_MM * PX_PER_MM) - margin
    black = ((np.floor(x) + np.floor(y)) % 2 == 0) & (x >= 0) & (y >= 0) & (x < cols) & (y < rows)
    return np.where(black, 30, 225).astype(np.uint8)


def render_view(texture: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Ray-trace each (distorted) pixel onto the board plane and sample the texture."""
    w, h = SIZE
    pix = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    normalised = cv2.undistortPoints(pix, K, DIST, None, None, None,
                                         (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
    rays = np.concatenate([normalised.reshape(-1, 2), np.ones((w * h, 1))], axis=1)
    rot, _ = cv2.Rodrigues(rvec)
    rays_b = rays @ rot  # R^T r
    origin_b = -rot.T @ tvec.ravel()  # camera centre in board coordinates
    s = -origin_b[2] / rays_b[:, 2]
    points = origin_b + s[:, None] * rays_b  # board plane, mm; corner (0,0) is the first inner corner
    offset_mm = 2 * SQUARE_MM  # margin square plus first board square
    map_x = ((points[:, 0] + offset_mm) * PX_PER_MM).reshape(h, w).astype(np.float32)
    map_y = ((points[:, 1] + offset_mm) * PX_PER_MM).reshape(h, w).astype(np.float32)
    # Area-average the fine texture by blurring first, as a lens/sensor would.
    blurred = cv2.GaussianBlur(texture, (0, 0), PX_PER_MM * 0.4)
    return cv2.remap(blurred, map_x, map_y, cv2.INTER_LINEAR, borderValue=225)


def make_views(folder) -> None:
    texture = board_texture()
    rng = np.random.default_rng(0)
    centre = np.array([BOARD[0] - 1, BOARD[1] - 1, 0]) * SQUARE_MM / 2
    for i in range(16):
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        rot, _ = cv2.Rodrigues(rvec)
        distance = rng.uniform(230, 300)
        shift = np.array([rng.uniform(-80, 80), rng.uniform(-60, 60), distance])
        tvec = shift - rot @ centre
        image = render_view(texture, rvec, tvec)
        cv2.imwrite(str(folder / f"view{i:02d}.png"), image)


@pytest.fixture(scope="module")
def views(tmp_path_factory):
    folder = tmp_path_factory.mktemp("board")
    make_views(folder)
    return folder


def test_calibration_recovers_intrinsics_and_distortion(views) -> None:
    result = calibrate(views, board=BOARD, square_mm=SQUARE_MM)
    camera = np.asarray(result["camera_matrix"])
    assert result["views_used"] >= 10
    for got, want in [(camera[0, 0], K[0, 0]), (camera[1, 1], K[1, 1]),
                      (camera[0, 2], K[0, 2]), (camera[1, 2], K[1, 2])]:
        assert abs(got - want) / want < 0.01, (got, want)
    dist = np.asarray(result["dist_coeffs"])
    print("calibration", camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2], dist, result["rms_px"])
    assert abs(dist[0] - DIST[0]) / abs(DIST[0]) < 0.01
    assert abs(dist[1] - DIST[1]) / abs(DIST[1]) < 0.05
    # The distortion where it matters: the radial displacement within the image.
    r = np.linspace(0, 0.5, 50)
    radial = lambda d: r * (d[0] * r**2 + d[1] * r**4 + d[4] * r**6)  # noqa: E731
    assert np.abs(radial(dist) - radial(DIST)).max() < 0.01 * np.abs(radial(DIST)).max()
    assert result["rms_px"] < 0.3


def test_calibrate_cli_writes_json_and_rejects_missing_board(views, tmp_path) -> None:
    from flow.cli import main

    out = tmp_path / "calib.json"
    assert main(["calibrate", str(views), "--board", "8x6", "--square-mm", "20", "--out", str(out)]) == 0
    assert out.is_file()
    bad = tmp_path / "bad.json"
    assert main(["calibrate", str(views), "--board", "5x3", "--square-mm", "20", "--out", str(bad)]) == 2
    assert not bad.exists()


def test_roi_undistortion_matches_full_frame_undistortion() -> None:
    calibration = {"camera_matrix": K.tolist(), "dist_coeffs": DIST.tolist(), "image_size": list(SIZE)}
    rng = np.random.default_rng(0)
    full = cv2.GaussianBlur(rng.integers(0, 255, SIZE[::-1]).astype(np.uint8), (0, 0), 2)
    whole = cv2.undistort(full, K, DIST)
    roi = Roi(200, 100, 120, 90)
    crop = full[roi.y:roi.y + roi.height, roi.x:roi.x + roi.width]
    part = Undistorter(calibration, roi, SIZE)(crop)
    expected = whole[roi.y:roi.y + roi.height, roi.x:roi.x + roi.width]
    inner = (slice(10, -10), slice(10, -10))  # source pixels of the border lie outside the crop
    assert np.abs(part[inner].astype(int) - expected[inner]).max() <= 1


def test_scale_from_known_length() -> None:
    assert scale_from_known_length(50.0, "0,0,30,40") == pytest.approx(1.0)
    with pytest.raises(InputError):
        scale_from_known_length(-1.0, "0,0,1,1")
    with pytest.raises(InputError):
        scale_from_known_length(5.0, "1,1,1,1")
