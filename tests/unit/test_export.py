"""UFF dataset 58 export: the file reads back (with pyuff, as modal software would) to the
CSV's numbers, in SI units, on a uniform clock with invalid frames bridged."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
import pyuff

from flow.export import write_uff
from flow.io.errors import InputError

COLUMNS = ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid"]


def write_csv(path: Path, time_s, dx_px, dy_px, valid, mm_per_px: float | None) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for i, (t, x, y, ok) in enumerate(zip(time_s, dx_px, dy_px, valid, strict=True)):
            scale = mm_per_px if mm_per_px is not None else float("nan")
            x, y = (x, y) if ok else (float("nan"), float("nan"))
            writer.writerow([i, *(repr(float(v)) for v in (t, x, y, x * scale, y * scale)), int(ok)])


def test_uff_reads_back_to_the_csv_numbers_in_si(tmp_path) -> None:
    t = np.arange(50) / 60.0
    dx, dy = 3.0 * np.sin(2 * np.pi * 2.5 * t), 0.5 * np.cos(2 * np.pi * 1.1 * t)
    valid = np.ones(50, bool)
    valid[[10, 11, 30]] = False
    source = tmp_path / "run.csv"
    write_csv(source, t, dx, dy, valid, mm_per_px=0.4)
    out = tmp_path / "run.uff"
    assert write_uff(source, out) == 2
    units, *histories = pyuff.UFF(str(out)).read_sets()
    assert units["type"] == 164 and units["length"] == pytest.approx(1.0)
    assert [h["type"] for h in histories] == [58, 58] and [h["rsp_dir"] for h in histories] == [1, 2]
    for history, truth in zip(histories, (dx, dy), strict=True):
        assert history["func_type"] == 1 and history["ordinate_axis_units_lab"].strip() == "m"
        # The time step is stored with 6 digits (UFF's E13.5): 2e-6 relative, far below any
        # modal quantity's uncertainty.
        assert history["x"] == pytest.approx(t, rel=1e-5, abs=1e-9)
        expected = np.interp(t, t[valid], (truth * 0.4e-3)[valid])  # mm -> m, gaps bridged
        assert np.allclose(history["data"], expected, rtol=1e-9, atol=1e-12)
        assert "3 invalid frames bridged" in history["id4"]
    # The numbers move with the measurement: a 5 % smaller scale reads 5 % smaller.
    write_csv(source, t, dx, dy, valid, mm_per_px=0.38)
    write_uff(source, out)
    smaller = pyuff.UFF(str(out)).read_sets()[1]["data"]
    assert np.allclose(smaller, histories[0]["data"] * 0.95)


def test_uff_without_a_scale_is_in_pixels_and_says_so(tmp_path) -> None:
    t = np.arange(8) / 30.0
    source = tmp_path / "px.csv"
    write_csv(source, t, np.linspace(0, 1, 8), np.zeros(8), np.ones(8, bool), mm_per_px=None)
    write_uff(source, tmp_path / "px.uff")
    history = pyuff.UFF(str(tmp_path / "px.uff")).read_sets()[1]
    assert history["ordinate_axis_units_lab"].strip() == "px" and "not SI" in history["id3"]
    assert np.allclose(history["data"], np.linspace(0, 1, 8))


def test_uff_refuses_a_run_without_enough_valid_frames(tmp_path) -> None:
    t = np.arange(6) / 30.0
    source = tmp_path / "bad.csv"
    write_csv(source, t, np.zeros(6), np.zeros(6), np.array([1, 1, 1, 0, 0, 0], bool), mm_per_px=1.0)
    with pytest.raises(InputError, match="fewer than 4 valid frames"):
        write_uff(source, tmp_path / "bad.uff")
    assert not (tmp_path / "bad.uff").exists() and list(tmp_path.iterdir()) == [source]


def test_refflow_export_command(tmp_path, capsys) -> None:
    from flow.cli import main

    t = np.arange(10) / 30.0
    source = tmp_path / "run.csv"
    write_csv(source, t, np.linspace(0, 2, 10), np.zeros(10), np.ones(10, bool), mm_per_px=0.5)
    assert main(["export", str(source), "--out", str(tmp_path / "run.uff")]) == 0
    assert len(pyuff.UFF(str(tmp_path / "run.uff")).read_sets()) == 3
    for bad in (source, source / "inside.uff"):  # the input itself; a folder that is a file
        before = sorted(tmp_path.iterdir())
        code = main(["export", str(source), "--out", str(bad)])
        err = capsys.readouterr().err.strip()
        assert code == 2 and len(err.splitlines()) == 1 and sorted(tmp_path.iterdir()) == before, err
