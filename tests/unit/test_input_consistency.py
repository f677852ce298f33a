"""Inputs that contradict each other or the video (issue 32, cases 2 and 4): a scale file
that states two scales, a calibration made for another camera or size."""

from __future__ import annotations

import json

import numpy as np
import pytest

from flow.io.errors import InputError
from flow.options import ScaleOptions
from flow.scale import measurement_scale


def _scale_file(tmp_path, **entries) -> str:
    path = tmp_path / "scale.json"
    path.write_text(json.dumps(entries))
    return str(path)


def test_a_scale_file_with_two_different_scales_is_refused_naming_both(tmp_path) -> None:
    path = _scale_file(tmp_path, mm_per_px=0.5, known_length_mm=200, between_px=[0, 0, 20, 0])
    with pytest.raises(InputError, match=r"two scales: 'mm_per_px' 0\.5 and .* 10 mm per pixel: keep one"):
        measurement_scale(ScaleOptions(scale_file=path), None, (100, 100))


@pytest.mark.parametrize("written", [10, 10.0, 3.3, 3.333])
def test_a_scale_file_stating_its_scale_twice_agrees_within_its_rounding(tmp_path, written) -> None:
    # 3.3 and 3.333 are 100 mm over 30 px (3.333...) rounded to the digits they are written with.
    length = 100.0 if written < 4 else 200.0
    between = [0, 0, 30, 0] if written < 4 else [0, 0, 20, 0]
    path = _scale_file(tmp_path, mm_per_px=written, known_length_mm=length, between_px=between)
    scale = measurement_scale(ScaleOptions(scale_file=path), None, (100, 100))
    assert scale.mm_per_px == pytest.approx(length / between[2]) and "known length" in scale.source


@pytest.mark.parametrize("written", [10.1, 10.00001, 3.4, 3.33334])
def test_a_scale_file_whose_scales_differ_beyond_rounding_is_refused(tmp_path, written) -> None:
    length, between = (200.0, [0, 0, 20, 0]) if written > 10 else (100.0, [0, 0, 30, 0])
    path = _scale_file(tmp_path, mm_per_px=written, known_length_mm=length, between_px=between)
    with pytest.raises(InputError, match="two scales"):
        measurement_scale(ScaleOptions(scale_file=path), None, (100, 100))


def _calibration(tmp_path, camera, dist=(0.0, 0.0, 0.0, 0.0, 0.0), **extra) -> str:
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps({"camera_matrix": camera, "dist_coeffs": list(dist), **extra}))
    return str(path)


# A 1920x1080 camera's intrinsics, as another camera's file would hold them.
FULL_HD = [[1500.0, 0.0, 960.0], [0.0, 1500.0, 540.0], [0.0, 0.0, 1.0]]


@pytest.mark.parametrize("last_row", [[0, 0, 0], [0, 0, 2], [1e-3, 0, 1]])
def test_a_camera_matrix_whose_last_row_is_not_0_0_1_is_refused_in_one_line(tmp_path, last_row) -> None:
    from flow.calibration import load_calibration

    path = _calibration(tmp_path, [FULL_HD[0], FULL_HD[1], last_row])
    with pytest.raises(InputError, match=r"'camera_matrix' has the last row .*, a camera matrix's is \[0, 0, 1\]"):
        load_calibration(path)


@pytest.mark.parametrize("camera, dist, size, expected", [
    (FULL_HD, (0, 0, 0, 0, 0), (334, 250), r"principal point \(960, 540\) lies outside the 334x250 frame"),
    ([[1e-9, 0, 160], [0, 1e-9, 120], [0, 0, 1]], (0, 0, 0, 0, 0), (334, 250), r"focal length \(fx 1e-09"),
    ([[1e6, 0, 160], [0, 1e6, 120], [0, 0, 1]], (0, 0, 0, 0, 0), (334, 250), r"not between 0.1x and 100x"),
    (FULL_HD, (500, 0, 0, 0, 0), (1920, 1080), r"scales a radius within the frame by 2\d\d"),
    (FULL_HD, (-0.6, 0, 0, 0, 0), (1920, 1080), r"folds back within the frame"),
    (FULL_HD, (0.0, 0.0, 5.0, 0.0, 0.0), (1920, 1080), r"comes back .* px away from undistortion"),
])
def test_a_calibration_that_does_not_belong_to_the_frames_is_refused(camera, dist, size, expected) -> None:
    from flow.calibration import check_fits_frame

    with pytest.raises(InputError, match=expected):
        check_fits_frame(np.array(camera, float), np.array(dist, float), size, "calibration file 'c.json'")


@pytest.mark.parametrize("dist", [(0, 0, 0, 0, 0), (-0.3, 0.1, 0, 0, 0), (0.06, -0.02, 1e-3, -5e-4, 0.0),
                                  (-0.4, 0.2, 0.001, -0.002, -0.05), (0.2, -0.5, 0, 0)])
def test_real_lenses_fit_their_frames(dist) -> None:
    from flow.calibration import check_fits_frame

    check_fits_frame(np.array(FULL_HD), np.array(dist, float), (1920, 1080))


def test_another_cameras_intrinsics_stop_the_undistorter_with_the_files_name(tmp_path) -> None:
    from flow.calibration import Undistorter, load_calibration
    from flow.io.frames import Roi

    calibration = load_calibration(_calibration(tmp_path, FULL_HD))
    with pytest.raises(InputError, match=r"^calibration file 'x.json': its principal point"):
        Undistorter(calibration, Roi(0, 0, 334, 250), (334, 250), name="calibration file 'x.json'")
