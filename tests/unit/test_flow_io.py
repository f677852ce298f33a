"""Frame input, ROI and POI masks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flow.io import FrameSource, InputError, Roi, as_uint8, deep_image_gain, significant_bits
from flow.poi import load_mask, poi_coordinates, polygon_mask, rect_mask


def test_roi_parse_and_bounds() -> None:
    roi = Roi.parse("10,20,30,40")
    assert roi == Roi(10, 20, 30, 40)
    roi.check(40, 60)
    with pytest.raises(InputError, match="outside the 39x60 frame"):
        roi.check(39, 60)
    with pytest.raises(InputError, match="X,Y,W,H"):
        Roi.parse("1,2,3")


def test_image_folder_streams_grey_roi_with_fps_timestamps(tmp_path) -> None:
    for i in range(3):
        image = np.full((30, 40, 3), 10 * i, np.uint8)
        image[5, 7] = (255, 255, 255)
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), image)
    source = FrameSource(tmp_path, roi=Roi(7, 5, 10, 8), fps=25.0)
    frames = list(source)
    assert [f[0] for f in frames] == [0, 1, 2]
    assert [f[1] for f in frames] == pytest.approx([0, 0.04, 0.08])
    assert frames[1][2].shape == (8, 10) and frames[1][2].dtype == np.uint8
    assert frames[1][2][0, 0] == 255 and frames[1][2][1, 1] == 10
    assert source.frames_read == 3 and not source.truncated


def test_masks_full_size_roi_size_rect_polygon_and_grid(tmp_path) -> None:
    roi = Roi(10, 10, 20, 10)
    full = np.zeros((40, 50), np.uint8)
    full[12:15, 11:16] = 255
    cv2.imwrite(str(tmp_path / "full.png"), full)
    cv2.imwrite(str(tmp_path / "roi.png"), full[10:20, 10:30])
    cv2.imwrite(str(tmp_path / "bad.png"), full[:7, :9])
    a = load_mask(tmp_path / "full.png", frame_size=(50, 40), roi=roi)
    b = load_mask(tmp_path / "roi.png", frame_size=(50, 40), roi=roi)
    assert a.shape == (10, 20) and (a == b).all() and a.sum() == 15
    with pytest.raises(InputError, match="mask is 9x7 but frames are 50x40"):
        load_mask(tmp_path / "bad.png", frame_size=(50, 40), roi=roi)
    assert (rect_mask("11,12,5,3", roi=roi) == a).all()
    assert polygon_mask("10,10,29,10,29,19", roi=roi).sum() > 50
    assert len(poi_coordinates(a)) == 15
    assert len(poi_coordinates(a, grid_step=2)) == 4  # rows 2, 4 x cols 2, 4 of the ROI
    with pytest.raises(InputError, match="selects no pixel"):
        poi_coordinates(np.zeros((4, 4), bool))


def test_frame_ranges_and_fps_checks(tmp_path) -> None:
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), np.full((6, 8), 40 * i, np.uint8))
    source = FrameSource(tmp_path, fps=10.0)
    picked = list(source.frames(1, 4))
    assert [f[0] for f in picked] == [1, 2, 3]
    assert [f[1] for f in picked] == pytest.approx([0.1, 0.2, 0.3])
    assert [int(f[2][0, 0]) for f in picked] == [40, 80, 120]
    assert [f[0] for f in source.frames(3)] == [3, 4]
    with pytest.raises(InputError, match="pass --fps"):
        FrameSource(tmp_path)
    assert [f[1] for f in FrameSource(tmp_path, require_fps=False)] == [0, 1, 2, 3, 4]
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(InputError, match="is not positive"):
            FrameSource(tmp_path, fps=bad)


def test_video_fps_is_checked_too_and_ranges_skip_decoding(tmp_path) -> None:
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (16, 12), True)
    for i in range(6):
        writer.write(np.full((12, 16, 3), 40 * i, np.uint8))
    writer.release()
    with pytest.raises(InputError, match="--fps -1.0 is not positive"):
        FrameSource(video, fps=-1.0)
    source = FrameSource(video)
    picked = list(source.frames(2, 5))
    assert [f[0] for f in picked] == [2, 3, 4]
    assert [f[1] for f in picked] == pytest.approx([0.08, 0.12, 0.16])
    assert abs(int(picked[0][2].mean()) - 80) <= 3
    assert not source.truncated  # stopped early: nothing to judge


def test_sixteen_bit_images_are_measured_at_full_depth(tmp_path) -> None:
    """12-bit data in 16-bit images comes out on the 8-bit grey scale but not rounded to it:
    value x gain exactly, as float32; 8-bit images stay uint8; the data's bits are recorded."""
    rng = np.random.default_rng(3)
    first = rng.integers(1000, 3000, (12, 16)).astype(np.uint16)
    first[0, 0] = 4000  # 12-bit data: 4000 < 4096
    cv2.imwrite(str(tmp_path / "a.png"), first)
    cv2.imwrite(str(tmp_path / "b.png"), first + np.uint16(1))  # one count brighter
    source = FrameSource(tmp_path, fps=10.0)
    frames = [grey for _, _, grey in source]
    gain = np.float32(deep_image_gain(first))
    assert source.bit_depth == 12
    assert frames[0].dtype == np.float32
    assert np.array_equal(frames[0], first.astype(np.float32) * gain)
    # One count of 12-bit data is 0.05 grey levels here: kept, where 8 bits would lose it.
    assert np.allclose(frames[1] - frames[0], gain, rtol=1e-3)
    eight = tmp_path / "eight"
    eight.mkdir()
    cv2.imwrite(str(eight / "a.png"), (first >> 4).astype(np.uint8))
    source = FrameSource(eight, fps=10.0)
    assert source.bit_depth == 8 and next(iter(source))[2].dtype == np.uint8


def test_as_uint8_and_significant_bits() -> None:
    image = np.array([[-3.0, 0.4, 0.6], [254.5, 255.2, 900.0]], np.float32)
    assert as_uint8(image).tolist() == [[0, 0, 1], [254, 255, 255]]
    eight = np.zeros((2, 2), np.uint8)
    assert as_uint8(eight) is eight
    assert significant_bits(np.array([0, 255], np.uint16)) == 8
    assert significant_bits(np.array([0, 1023], np.uint16)) == 10
    assert significant_bits(np.array([0, 2460], np.uint16)) == 12
    assert significant_bits(np.array([0, 65535], np.uint16)) == 16
