"""A flagged frame keeps its reading in the track CSV, and every reader of the CSV still treats
it as flagged: `refflow plot` (grey, out of the spectrum), `modal` and `export` (bridged),
the GUI's reading (:func:`flow.figures.read_measurements`) and ``analysis`` (NaN).

The flagged frames here read wild values (50 px spikes) that would show at once in any
number that used them.
"""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import pyuff

from analysis.readers import read_track
from flow.cli import main
from flow.export import write_uff
from flow.figures import read_measurements
from refflow import trackcsv

FRAMES = 240
FPS = 30.0
HZ = 1.5
MM_PER_PX = 0.5


def write_run(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 1.5 Hz swing whose every 7th frame is flagged with a 50 px spike kept in the file."""
    t = np.arange(FRAMES) / FPS
    dx = 4.0 * np.sin(2 * np.pi * HZ * t)
    valid = np.ones(FRAMES, bool)
    valid[3::7] = False
    written = np.where(valid, dx, 50.0)
    with path.open("w", newline="") as handle:
        trackcsv.write(handle, [(1, ({"frame": i, "time_s": float(t[i]), "dx_px": float(written[i]),
                                      "dy_px": float(written[i]), "dx_mm": float(written[i] * MM_PER_PX),
                                      "dy_mm": float(written[i] * MM_PER_PX), "valid": int(valid[i]),
                                      "sigma_dx_px": 0.1, "sigma_dy_px": 0.1, "sigma_px": 0.14}
                                     for i in range(FRAMES)))])
    return t, dx, valid


def test_the_file_keeps_the_readings_and_the_readers_do_not_use_them(tmp_path) -> None:
    source = tmp_path / "run.csv"
    t, dx, valid = write_run(source)
    (columns,) = trackcsv.read(source).values()
    assert np.array_equal(columns["dx_px"][~valid], np.full((~valid).sum(), 50.0)), "the file keeps them"
    # the measurement tool's reader: NaN where flagged, the readings apart for a figure
    (data,) = read_measurements(source)
    assert np.isnan(data["dx_px"][~valid]).all() and np.allclose(data["dx_px"][valid], dx[valid])
    assert np.array_equal(data["flagged"]["dx_mm"][~valid], np.full((~valid).sum(), 25.0))
    assert np.isnan(data["flagged"]["dx_mm"][valid]).all() and data["has_mm"]
    # analysis judges a method on the frames it vouches for
    track = read_track(source)
    for name in ("dx_px", "dy_px", "dx_mm", "dy_mm", "sigma_dx_px"):
        assert np.isnan(track[name][~valid]).all() and np.isfinite(track[name][valid]).all(), name
    # export bridges the flagged frames, as it bridged empty cells
    assert write_uff(source, tmp_path / "run.uff") == 2
    history = pyuff.UFF(str(tmp_path / "run.uff")).read_sets()[1]
    expected = np.interp(t, t[valid], dx[valid] * MM_PER_PX * 1e-3)
    # (the uniform clock is stored with 6 digits: a few tenths of a micrometre; a spike is 25 mm)
    assert np.abs(history["data"] - expected).max() < 1e-6


def test_plot_and_modal_read_the_valid_frames(tmp_path, capsys) -> None:
    source = tmp_path / "run.csv"
    write_run(source)
    assert main(["plot", str(source), "--units", "px", "--out", str(tmp_path / "run.png")]) == 0
    printed = capsys.readouterr().out
    assert float(printed.split("dx ")[1].split(" Hz")[0]) == pytest.approx(HZ, abs=0.02)
    assert main(["modal", str(source), "--out", str(tmp_path / "modes.json"), "--modes", "1"]) == 0
    modes = json.loads((tmp_path / "modes.json").read_text())
    found = [m["freq_hz"] for m in modes["modes"]]
    assert found and found[0] == pytest.approx(HZ, rel=0.02), modes


def test_a_run_whose_every_frame_is_flagged_plots_its_readings_grey(tmp_path, capsys) -> None:
    source = tmp_path / "flagged.csv"
    t = np.arange(60) / FPS
    with source.open("w", newline="") as handle:
        trackcsv.write(handle, [(1, ({"frame": i, "time_s": float(t[i]), "dx_px": float(np.sin(t[i])),
                                      "dy_px": 0.0, "valid": 0} for i in range(60)))])
    assert main(["plot", str(source), "--units", "px", "--out", str(tmp_path / "flagged.png")]) == 0
    err = capsys.readouterr().err
    assert "has no valid frame: its flagged readings are drawn grey" in err
    assert (tmp_path / "flagged.png").is_file()
    rows = list(csv.DictReader(source.open()))
    assert all(r["valid"] == "0" and r["dx_px"] != "" for r in rows)
