"""Inputs that contradict each other or the video (issue 32, cases 2 and 4): a scale file
that states two scales, a calibration made for another camera or size."""

from __future__ import annotations

import json

import pytest

from flow.errors import InputError
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
