"""Calibration recovers the camera of synthetic checkerboard views; undistortion and scale."""

from __future__ import annotations

import functools

import cv2
import numpy as np
import pytest

from flow.calibration import Undistorter, calibrate, load_calibration, scale_from_known_length
from flow.io.errors import InputError
from flow.io.frames import Roi

# 960 x 720: at half that size the corner detector's own error (~0.02 px, from the curved,
# blurred edges) still moves k2 by up to ~2.5 %; here it stays within ~0.4 %.
SIZE = (960, 720)
K = np.array([[840.0, 0, 472.0], [0, 830.0, 366.0], [0, 0, 1]])
DIST = np.array([-0.25, 0.08, 0.0, 0.0, 0.0])
BOARD = (8, 6)  # inner corners
SQUARE_MM = 20.0
PX_PER_MM = 12


def board_texture() -> np.ndarray:
    """The board (one white square of margin), pre-blurred as a lens/sensor would area-average it."""
    cols, rows = BOARD[0] + 1, BOARD[1] + 1
    margin = 1
    h, w = (rows + 2 * margin) * SQUARE_MM * PX_PER_MM, (cols + 2 * margin) * SQUARE_MM * PX_PER_MM
    y, x = np.mgrid[0:int(h), 0:int(w)] / (SQUARE_MM * PX_PER_MM) - margin
    black = ((np.floor(x) + np.floor(y)) % 2 == 0) & (x >= 0) & (y >= 0) & (x < cols) & (y < rows)
    return cv2.GaussianBlur(np.where(black, 30, 225).astype(np.uint8), (0, 0), PX_PER_MM * 0.4)


@functools.lru_cache(maxsize=1)
def pixel_rays() -> np.ndarray:
    """Ray direction ``(x, y, 1)`` of every (distorted) pixel: the same for every view."""
    w, h = SIZE
    pix = np.stack(np.meshgrid(np.arange(w), np.arange(h)), -1).reshape(-1, 1, 2).astype(np.float64)
    normalised = cv2.undistortPoints(pix, K, DIST, None, None, None,
                                     (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 40, 1e-10))
    return np.concatenate([normalised.reshape(-1, 2), np.ones((w * h, 1))], axis=1)


def render_view(texture: np.ndarray, rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    """Ray-trace each (distorted) pixel onto the board plane and sample the texture."""
    w, h = SIZE
    rot, _ = cv2.Rodrigues(rvec)
    rays_b = pixel_rays() @ rot  # R^T r
    origin_b = -rot.T @ tvec.ravel()  # camera centre in board coordinates
    s = -origin_b[2] / rays_b[:, 2]
    points = origin_b + s[:, None] * rays_b  # board plane, mm; corner (0,0) is the first inner corner
    offset_mm = 2 * SQUARE_MM  # margin square plus first board square
    # Texel i holds the board at i / PX_PER_MM, so a square edge falls between texels i - 1
    # and i, at i - 1/2 once interpolated: sample half a texel earlier to put it back (else
    # every corner sits ~0.07 px up-left of the truth and k2 comes out ~3 % low).
    map_x = ((points[:, 0] + offset_mm) * PX_PER_MM - 0.5).reshape(h, w).astype(np.float32)
    map_y = ((points[:, 1] + offset_mm) * PX_PER_MM - 0.5).reshape(h, w).astype(np.float32)
    return cv2.remap(texture, map_x, map_y, cv2.INTER_LINEAR, borderValue=225)


def board_poses(n_views: int, seed: int = 0) -> list[tuple[np.ndarray, np.ndarray]]:
    """Board poses that fill the frame, tilted up to ~30 degrees, the whole board in view.

    Close, well-spread views reach the image corners, where k2 shows (r^4): with
    views only near the centre, k2 is poorly determined.
    """
    rng = np.random.default_rng(seed)
    centre = np.array([BOARD[0] - 1, BOARD[1] - 1, 0]) * SQUARE_MM / 2
    # Corners of the outer squares, one square beyond the inner corners.
    outline = np.array([[-1, -1, 0], [BOARD[0], -1, 0], [-1, BOARD[1], 0], [BOARD[0], BOARD[1], 0]],
                       float) * SQUARE_MM
    poses = []
    while len(poses) < n_views:
        rvec = np.array([rng.uniform(-0.5, 0.5), rng.uniform(-0.5, 0.5), rng.uniform(-0.3, 0.3)])
        rot, _ = cv2.Rodrigues(rvec)
        shift = np.array([rng.uniform(-120, 120), rng.uniform(-90, 90), rng.uniform(180, 260)])  # mm
        tvec = shift - rot @ centre
        corners, _ = cv2.projectPoints(outline, rvec, tvec, K, DIST)
        corners = corners.reshape(-1, 2)
        if (corners > 4).all() and (corners < np.array(SIZE) - 4).all():
            poses.append((rvec, tvec))
    return poses


@pytest.fixture(scope="module")
def view_images() -> list[np.ndarray]:
    texture = board_texture()
    return [render_view(texture, rvec, tvec) for rvec, tvec in board_poses(30)]


@pytest.fixture(scope="module")
def views(tmp_path_factory, view_images):
    folder = tmp_path_factory.mktemp("board")
    for i, image in enumerate(view_images):
        cv2.imwrite(str(folder / f"view{i:02d}.png"), image)
    return folder


def check_calibration(result: dict) -> None:
    camera = np.asarray(result["camera_matrix"])
    dist = np.asarray(result["dist_coeffs"])
    print("calibration", camera[0, 0], camera[1, 1], camera[0, 2], camera[1, 2], dist, result["rms_px"])
    for label, got, want in [("fx", camera[0, 0], K[0, 0]), ("fy", camera[1, 1], K[1, 1]),
                             ("cx", camera[0, 2], K[0, 2]), ("cy", camera[1, 2], K[1, 2]),
                             ("k1", dist[0], DIST[0]), ("k2", dist[1], DIST[1])]:
        assert abs(got - want) / abs(want) < 0.01, (label, got, want)
    # The true p1 = p2 = 0, so "within 1 % of the value" means an absolute bound: 5e-5 moves
    # a point at the image corner (r ~ 0.7) by 2 p r^2 f ~ 0.04 px, below corner-detection noise.
    assert np.abs(dist[2:4]).max() < 5e-5, dist[2:4]
    assert result["rms_px"] < 0.1


def test_calibration_recovers_intrinsics_and_distortion(views) -> None:
    result = calibrate(views, board=BOARD, square_mm=SQUARE_MM)
    assert result["views_used"] == 30
    check_calibration(result)


def test_calibrate_cli_writes_json_and_rejects_missing_board(views, tmp_path) -> None:
    from flow.cli import main

    out = tmp_path / "calib.json"
    assert main(["calibrate", str(views), "--board", "8x6", "--square-mm", "20", "--out", str(out)]) == 0
    assert out.is_file()
    bad = tmp_path / "bad.json"
    assert main(["calibrate", str(views), "--board", "5x3", "--square-mm", "20", "--out", str(bad)]) == 2
    assert not bad.exists()
    assert main(["calibrate", str(views), "--board", "8x6", "--square-mm", "-20", "--out", str(bad)]) == 2
    assert not bad.exists()


def test_calibrate_from_a_video(tmp_path, view_images) -> None:
    """A video of the board: frames without it are skipped, --step thins near-duplicates."""
    import json

    from flow.cli import main

    video = tmp_path / "board.mkv"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, SIZE, True)
    assert writer.isOpened()
    blank = np.full(SIZE[::-1], 225, np.uint8)
    for image in view_images:
        for frame in (image, image, blank):  # each view held for two frames, then the board leaves
            writer.write(cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR))
    writer.release()
    out = tmp_path / "calib.json"
    assert main(["calibrate", str(video), "--board", "8x6", "--square-mm", "20", "--step", "3",
                 "--out", str(out)]) == 0
    result = json.loads(out.read_text())
    assert result["views_used"] == 30
    check_calibration(result)


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


def test_mask_and_points_drawn_on_raw_frames_follow_the_undistortion() -> None:
    """Masks and --between points are raw video pixels; the flow runs on undistorted frames."""
    calibration = {"camera_matrix": K.tolist(), "dist_coeffs": DIST.tolist(), "image_size": list(SIZE)}
    roi = Roi(40, 40, 300, 220)  # near the top-left corner, where the distortion is strong
    undistorter = Undistorter(calibration, roi, SIZE)
    raw = np.zeros((roi.height, roi.width), bool)
    raw[60:100, 60:140] = True  # full frame x 100..180, y 100..140
    mapped = undistorter.map_mask(raw)
    ys, xs = np.mgrid[62:98:4, 62:138:4]  # raw points inside the rectangle
    ideal = undistorter.undistort_points(np.stack([xs.ravel() + roi.x, ys.ravel() + roi.y], 1))
    cols, rows = np.round(ideal[:, 0] - roi.x).astype(int), np.round(ideal[:, 1] - roi.y).astype(int)
    assert mapped[rows, cols].all()
    # The ideal position of a raw point is where the undistorted frame shows it.
    assert np.allclose(undistorter.map_x[rows, cols], xs.ravel(), atol=0.6)
    assert np.allclose(undistorter.map_y[rows, cols], ys.ravel(), atol=0.6)
    # Barrel distortion: the undistorted rectangle is larger and moved outwards (up-left here).
    assert mapped.sum() > 1.1 * raw.sum()
    assert np.argwhere(mapped).mean(axis=0)[1] < np.argwhere(raw).mean(axis=0)[1] - 3
    # A known length between raw points is measured in undistorted pixels.
    plain = scale_from_known_length(50.0, "100,100,180,100")
    corrected = scale_from_known_length(50.0, "100,100,180,100", undistorter.undistort_points)
    assert corrected < 0.95 * plain


CALIBRATION_FILE = {"camera_matrix": [[110.0, 0.0, 47.5], [0.0, 110.0, 31.5], [0.0, 0.0, 1.0]],
                    "dist_coeffs": [-0.12, 0.05, 0.001, -0.001, 0.0], "rms_px": 0.21, "image_size": [96, 64]}
HUGE = "1" + "0" * 400  # an integer no float holds


def _entry(key: str, text: str) -> str:
    """The calibration file's JSON with ``key`` set to the JSON ``text`` as written."""
    import json

    return json.dumps({**CALIBRATION_FILE, key: "@"}).replace('"@"', text)


BAD_CALIBRATIONS = {
    "nested too deeply": ("[" * 100_000 + "]" * 100_000, "is not readable JSON (nested too deeply)"),
    "5000-digit number": (_entry("rms_px", "9" * 5000), "is not readable JSON (a number with too many digits)"),
    "not an object": ("[1, 2]", "is not a refflow calibration"),
    "focal length too large for a float": (_entry("camera_matrix", f"[[{HUGE}, 0, 47], [0, 110, 31], [0, 0, 1]]"),
                                           "'camera_matrix' needs 3x3 finite numbers"),
    "NaN focal length": (_entry("camera_matrix", "[[NaN, 0, 47], [0, 110, 31], [0, 0, 1]]"), "'camera_matrix'"),
    "zero focal length": (_entry("camera_matrix", "[[110, 0, 47], [0, 0, 31], [0, 0, 1]]"), "positive focal"),
    "boolean in the matrix": (_entry("camera_matrix", "[[110, 0, 47], [0, 110, 31], [0, 0, true]]"), "'camera_matrix'"),
    "ragged matrix": (_entry("camera_matrix", "[[110, 0], [0, 110, 31, 0], [0, 0, 1]]"), "'camera_matrix'"),
    "one distortion coefficient": (_entry("dist_coeffs", "[0.1]"), "'dist_coeffs' needs 4, 5, 8, 12, 14 finite"),
    "null distortion": (_entry("dist_coeffs", "null"), "'dist_coeffs' needs"),
    "infinite distortion": (_entry("dist_coeffs", f"[-0.1, 0.05, 0, 0, {HUGE}]"), "'dist_coeffs' needs"),
    "empty image size": (_entry("image_size", "[]"), "'image_size' needs [width, height]"),
    "one-entry image size": (_entry("image_size", "[96]"), "'image_size' needs"),
    "null image size": (_entry("image_size", "null"), "'image_size' needs"),
    "number as image size": (_entry("image_size", "5"), "'image_size' needs"),
    "boolean image size": (_entry("image_size", "false"), "'image_size' needs"),
    "fractional image size": (_entry("image_size", "[96.5, 64]"), "'image_size' needs"),
}


@pytest.mark.parametrize("case", sorted(BAD_CALIBRATIONS))
def test_a_malformed_calibration_file_is_refused_in_one_line(tmp_path, case) -> None:
    """Every entry the undistortion uses is checked on loading: nothing reaches OpenCV, a
    formatted message or the sidecar as a traceback."""
    text, expected = BAD_CALIBRATIONS[case]
    path = tmp_path / "calibration.json"
    path.write_text(text)
    with pytest.raises(InputError) as refused:
        load_calibration(path)
    message = str(refused.value)
    assert expected in message and str(path) in message and "\n" not in message, message
    assert len(message) < 400, message


def test_load_calibration_hands_on_clean_values(tmp_path) -> None:
    """A flat matrix becomes 3x3, integers floats; an rms_px that is no finite number is only
    reported, so it becomes None (JSON null in the sidecar) instead of failing the run's end."""
    import json

    path = tmp_path / "calibration.json"
    path.write_text(json.dumps({**CALIBRATION_FILE, "camera_matrix": [110, 0, 47, 0, 110, 31, 0, 0, 1]}))
    loaded = load_calibration(path)
    assert loaded["camera_matrix"] == [[110.0, 0.0, 47.0], [0.0, 110.0, 31.0], [0.0, 0.0, 1.0]]
    assert loaded["dist_coeffs"] == CALIBRATION_FILE["dist_coeffs"] and loaded["image_size"] == [96, 64]
    assert loaded["rms_px"] == 0.21
    for rms in ("NaN", "Infinity", "true", '"small"', HUGE):
        path.write_text(_entry("rms_px", rms))
        assert load_calibration(path)["rms_px"] is None, rms
    without = {k: v for k, v in CALIBRATION_FILE.items() if k != "image_size"}
    path.write_text(json.dumps(without))
    assert "image_size" not in load_calibration(path)
    Undistorter(load_calibration(path), Roi(0, 0, 96, 64), (96, 64))  # OpenCV takes what it hands on


def test_identical_board_views_are_refused_not_written(tmp_path, view_images) -> None:
    """Four views of a board that did not move cannot calibrate a lens (RMS of millions of px)."""
    from flow.cli import main

    folder = tmp_path / "same"
    folder.mkdir()
    for i in range(4):
        cv2.imwrite(str(folder / f"view{i}.png"), view_images[0])
    out = tmp_path / "calib.json"
    with pytest.raises(InputError, match="the board views are .nearly. the same: 1 of the 4 views differ"):
        calibrate(folder, board=BOARD, square_mm=SQUARE_MM)
    assert main(["calibrate", str(folder), "--board", f"{BOARD[0]}x{BOARD[1]}", "--square-mm",
                 str(SQUARE_MM), "--out", str(out)]) == 2
    assert not out.exists()


def _true_corners(rvec: np.ndarray, tvec: np.ndarray) -> np.ndarray:
    grid = np.array([[c, r, 0.0] for r in range(BOARD[1]) for c in range(BOARD[0])]) * SQUARE_MM
    return cv2.projectPoints(grid, rvec, tvec, K, DIST)[0].reshape(-1, 2)


def test_full_size_search_finds_the_board_the_reduced_search_missed(monkeypatch) -> None:
    """Where the search on the reduced copy finds nothing (a board too small for it), the
    full-size search must find the corners, sub-pixel; the search it uses there must not be
    the reduced one's again (minutes on a 4K frame where the board is cut by the edge)."""
    import flow.calibration as calibration

    rvec, tvec = board_poses(1, seed=3)[0]
    image = render_view(board_texture(), rvec, tvec)
    big = cv2.resize(image, None, fx=2.0, fy=2.0, interpolation=cv2.INTER_LINEAR)  # 1920 px: reduced first
    monkeypatch.setattr(calibration.cv2, "findChessboardCorners",
                        lambda *args, **kwargs: (False, None))  # the reduced (and classic) search misses
    corners = calibration.find_corners(big, BOARD)
    assert corners is not None
    found = (corners.reshape(-1, 2) + 0.5) / 2.0 - 0.5  # back to the rendered view's pixels
    truth = _true_corners(rvec, tvec)
    if np.linalg.norm(found[0] - truth[0]) > np.linalg.norm(found[0] - truth[-1]):
        found = found[::-1]  # the board is symmetric: either corner may come first
    assert np.abs(found - truth).max() < 0.15


def test_a_board_cut_by_the_frame_edge_is_not_found() -> None:
    """A view with part of the board outside the frame gives no corners (not a wrong grid)."""
    from flow.calibration import find_corners

    rvec, tvec = board_poses(1, seed=3)[0]
    image = render_view(board_texture(), rvec, tvec)
    truth = _true_corners(rvec, tvec)
    cut = int(np.sort(truth[:, 0])[len(truth) // 3])  # a third of the corners left of the cut
    assert find_corners(np.ascontiguousarray(image[:, cut:]), BOARD) is None
