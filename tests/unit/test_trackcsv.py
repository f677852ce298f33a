"""The track CSV, defined once in refflow.trackcsv: what the writer puts down, the one reader
gives back (to flow and analysis alike), and each malformed file's message."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from refflow import trackcsv


def _rows(n: int, shift: float) -> list[dict]:
    rows = []
    for i in range(n):
        row = dict.fromkeys(trackcsv.COLUMNS, float("nan"))
        row.update(frame=i, time_s=i / 30.0, dx_px=shift + 0.1 * i, dy_px=0.0, dx_mm=shift + 0.1 * i,
                   dy_mm=0.0, valid=int(i != 2))
        rows.append(row)
    return rows


def _written(tmp_path: Path, series: list) -> Path:
    path = tmp_path / "run.csv"
    with path.open("w", newline="") as handle:
        trackcsv.write(handle, series)
    return path


def test_one_region_has_no_region_column_and_reads_back(tmp_path) -> None:
    path = _written(tmp_path, [(1, _rows(5, 0.0))])
    assert path.read_text().splitlines()[0].split(",") == list(trackcsv.COLUMNS)
    (key, columns), = trackcsv.read(path).items()
    assert key is None
    assert np.allclose(columns["dx_px"], 0.1 * np.arange(5))
    assert columns["valid"].tolist() == [1, 1, 0, 1, 1]


def test_several_regions_interleave_frame_by_frame_and_split_on_reading(tmp_path) -> None:
    path = _written(tmp_path, [(1, _rows(4, 0.0)), (2, _rows(4, 5.0))])
    lines = path.read_text().splitlines()
    assert lines[0].split(",") == trackcsv.columns(regions=True)
    assert lines[0].split(",")[2] == "region"  # right after time_s
    assert [line.split(",")[:3] for line in lines[1:3]] == [["0", "0", "1"], ["0", "0", "2"]]
    read = trackcsv.read(path)
    assert list(read) == [1, 2]
    assert np.allclose(read[2]["dx_px"] - read[1]["dx_px"], 5.0)
    assert "region" not in read[1]


def test_floats_are_written_with_nine_significant_digits() -> None:
    handle = io.StringIO()
    row = dict.fromkeys(trackcsv.COLUMNS, 1 / 3)
    row.update(frame=7, valid=1)
    trackcsv.write(handle, [(1, [row])])
    assert handle.getvalue().splitlines()[1].startswith("7,0.333333333,")


def test_units_follow_the_region_rule() -> None:
    assert "region" not in trackcsv.units(regions=False)
    assert trackcsv.units(regions=True)["region"].startswith("label")
    assert set(trackcsv.units(regions=False)) <= set(trackcsv.COLUMNS)


@pytest.mark.parametrize("text, message", [
    ("frame,time_s,dx_px,dy_px,dx_mm,dy_mm\n0,0,0,0,0,0\n", "no valid column"),
    ("frame,time_s,dx_px,dy_px,dx_mm,dy_mm,valid\n", "no data rows"),
    ("frame,time_s,dx_px,dy_px,dx_mm,dy_mm,valid\n0,0,abc,0,0,0,1\n", "'dx_px' row 2 is not a number"),
    ("frame,time_s,dx_px,dy_px,dx_mm,dy_mm,valid\n0,,0,0,0,0,1\n", "'time_s' has 1 NaN"),
    ("frame,time_s,region,dx_px,dy_px,dx_mm,dy_mm,valid\n0,0,0,0,0,0,0,1\n", "region '0' in row 2 is not a label"),
])
def test_a_malformed_file_names_itself_and_the_problem(tmp_path, text, message) -> None:
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(trackcsv.TrackCsvError, match=message) as caught:
        trackcsv.read(path)
    assert "bad.csv" in str(caught.value)
    with pytest.raises(ValueError, match="does not exist"):
        trackcsv.read(tmp_path / "missing.csv")


def test_flow_and_analysis_read_through_it(tmp_path) -> None:
    from analysis.readers import read_track
    from flow.figures import read_measurements
    from flow.io.errors import InputError

    one = _written(tmp_path, [(1, _rows(6, 0.0))])
    flow_view = read_measurements(one)[0]
    analysis_view = read_track(one)
    assert np.array_equal(flow_view["time_s"], analysis_view["time_s"])
    assert np.isnan(flow_view["dx_px"][2]) and analysis_view["valid"][2] == 0  # invalid frame
    several = tmp_path / "several.csv"
    with several.open("w", newline="") as handle:
        trackcsv.write(handle, [(1, _rows(6, 0.0)), (2, _rows(6, 1.0))])
    assert [data["region"] for data in read_measurements(several)] == [1, 2]
    with pytest.raises(ValueError, match="2 regions"):
        read_track(several)
    with pytest.raises(InputError, match="no data rows"):
        read_measurements(_written(tmp_path, [(1, [])]))
