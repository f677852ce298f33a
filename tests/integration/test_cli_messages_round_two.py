"""Issue 32, case 11: the messages a new user met. Each is one line naming the problem and what
to do (exit 2 and no file where it is an error), or the right behaviour:

* a labelled mask whose labels have a gap ({1, 3}) measures regions 1 and 3;
* ``--known-length inf`` is "not a finite positive number";
* a scale file that starts with a UTF-8 byte-order mark (Notepad) is read;
* `merge` of a file that is no .npz says so, without numpy's "load it unsafely" advice;
* `modal` of a displacement that never changes says so, without a RuntimeWarning;
* `gui`/`track` of a Photron ``.mraw`` says to open the ``.cih``;
* ``--frames -10:5`` gets the option's own one line, not the usage;
* a run without a scale says on the console that it measures in pixels;
* `modal` notes a record whose strongest motion lies below the band it searches (0.5 Hz).
"""

from __future__ import annotations

import csv
import json
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main

FPS = 30.0
SIZE = (48, 64)  # rows, columns


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> dict[str, Path]:
    """Eight frames of a textured scene moving right by 0.5 px per frame, as a folder of PNGs."""
    folder = tmp_path_factory.mktemp("messages")
    images = folder / "frames"
    images.mkdir()
    texture = cv2.GaussianBlur(np.random.default_rng(0).uniform(0, 255, (SIZE[0], SIZE[1] + 16)), (0, 0), 1.5)
    for i in range(8):
        shift = np.float32([[1, 0, 0.5 * i], [0, 1, 0]])
        frame = cv2.warpAffine(texture, shift, (texture.shape[1], texture.shape[0]), flags=cv2.INTER_CUBIC)
        cv2.imwrite(str(images / f"f{i:02d}.png"), np.clip(frame[:, 8:8 + SIZE[1]], 0, 255).astype(np.uint8))
    labels = np.zeros(SIZE, np.uint8)
    labels[8:24, 8:28], labels[26:42, 36:56] = 1, 3
    cv2.imwrite(str(folder / "labels13.png"), labels)
    return {"images": images, "labels": folder / "labels13.png", "folder": folder}


def _track(clip: dict[str, Path], out: Path, *extra: str) -> int:
    return main(["track", str(clip["images"]), "--fps", str(FPS), "--method", "dis", "--no-progress",
                 "--out", str(out), *extra])


def _one_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    return lines[0]


def test_a_labelled_mask_with_a_gap_measures_its_regions(clip, tmp_path, capsys) -> None:
    out = tmp_path / "regions.csv"
    assert _track(clip, out, "--mask", str(clip["labels"]), "--rect", "0,0,1,1") == 2  # one mask source only
    capsys.readouterr()
    assert _track(clip, out, "--mask", str(clip["labels"]), "--mm-per-px", "1") == 0
    with out.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert sorted({r["region"] for r in rows}) == ["1", "3"] and len(rows) == 16
    sidecar = json.loads(out.with_suffix(".json").read_text())
    assert [r["label"] for r in sidecar["regions"]] == [1, 3]
    dx = np.array([float(r["dx_px"]) for r in rows if r["frame"] == "7"])
    assert np.allclose(dx, 3.5, atol=0.3), "both regions follow the scene's 3.5 px"


def test_an_infinite_known_length_is_not_a_finite_positive_number(clip, tmp_path, capsys) -> None:
    out = tmp_path / "x.csv"
    assert _track(clip, out, "--rect", "8,8,40,30", "--known-length", "inf", "--between", "1,1,5,5") == 2
    line = _one_line(capsys.readouterr().err)
    assert "--known-length inf is not a finite positive number" in line and not out.exists()


def test_a_scale_file_with_a_byte_order_mark_is_read(clip, tmp_path) -> None:
    scale, out = tmp_path / "scale.json", tmp_path / "bom.csv"
    scale.write_bytes(b"\xef\xbb\xbf" + json.dumps({"mm_per_px": 0.25}).encode())
    assert _track(clip, out, "--rect", "8,8,40,30", "--scale-file", str(scale)) == 0
    assert json.loads(out.with_suffix(".json").read_text())["scale"]["mm_per_px"] == 0.25


@pytest.mark.parametrize("content", [b"frame,time_s\n0,0\n", b"\x93NUMPY", b"PK\x03\x04 not a zip"])
def test_merge_of_a_file_that_is_no_npz_says_so(tmp_path, capsys, content) -> None:
    part, out = tmp_path / "part.npz", tmp_path / "merged.csv"
    part.write_bytes(content)
    assert main(["merge", str(part), "--out", str(out)]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "is not a .npz archive" in line and "--raw-tracks" in line
    assert "unsafe" not in line and "pickle" not in line and not out.exists()


def _write_csv(path: Path, time_s: np.ndarray, dx: np.ndarray, dy: np.ndarray) -> None:
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid"])
        for i, (t, x, y) in enumerate(zip(time_s, dx, dy, strict=True)):
            writer.writerow([i, repr(float(t)), repr(float(x)), repr(float(y)), "nan", "nan", 1])


def test_modal_of_a_constant_displacement_says_so_without_a_warning(tmp_path, capsys) -> None:
    still = tmp_path / "still.csv"
    t = np.arange(120) / FPS
    _write_csv(still, t, np.zeros_like(t), np.full_like(t, 2.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a RuntimeWarning would raise here
        assert main(["modal", str(still), "--out", str(tmp_path / "modes.json")]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "constant" in line and "nothing moves" in line
    assert list(tmp_path.iterdir()) == [still]


def test_modal_notes_a_strongest_motion_below_its_band(tmp_path, capsys) -> None:
    """Like the Tacoma deck (0.29 Hz, 2.4 cycles in 8.3 s): the band's 0.5 Hz floor stays (too few
    cycles for a modal fit), but the strongest motion is named with the --band that searches it."""
    t = np.arange(300) / FPS
    slow = tmp_path / "slow.csv"
    _write_csv(slow, t, 10.0 * np.sin(2 * np.pi * 0.3 * t) + 0.5 * np.sin(2 * np.pi * 3.0 * t), np.zeros_like(t))
    assert main(["modal", str(slow), "--out", str(tmp_path / "modes_slow.json"), "--modes", "1"]) == 0
    err = capsys.readouterr().err
    assert "the record's strongest motion is at 0.299 Hz" in err and "--band 0.2,12" in err
    notes = json.loads((tmp_path / "modes_slow.json").read_text())["notes"]
    assert any("below the band searched (0.5-12 Hz)" in note for note in notes)
    fast = tmp_path / "fast.csv"
    _write_csv(fast, t, 10.0 * np.sin(2 * np.pi * 2.0 * t), np.zeros_like(t))
    assert main(["modal", str(fast), "--out", str(tmp_path / "modes_fast.json"), "--modes", "1"]) == 0
    assert "strongest motion" not in capsys.readouterr().err


@pytest.mark.parametrize("command", ["gui", "track"])
@pytest.mark.parametrize("with_header", [False, True])
def test_a_photron_mraw_says_to_open_its_header(tmp_path, capsys, command, with_header) -> None:
    mraw = tmp_path / "beam.mraw"
    mraw.write_bytes(bytes(640 * 40))
    if with_header:
        (tmp_path / "beam.cih").write_text("#Camera Information Header\n")
    extra = ["--no-browser", "--out-dir", str(tmp_path / "pages")] if command == "gui" else \
        ["--rect", "0,0,8,8", "--out", str(tmp_path / "beam.csv")]
    assert main([command, str(mraw), *extra]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "open the .cih (the Photron header)" in line
    assert (str(tmp_path / "beam.cih") in line) is with_header
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["beam.mraw"] + ["beam.cih"] * with_header)


@pytest.mark.parametrize("frames", ["-10:5", "-3"])
def test_a_negative_frame_range_gets_one_line_not_the_usage(clip, tmp_path, capsys, frames) -> None:
    out = tmp_path / "x.csv"
    assert _track(clip, out, "--rect", "8,8,40,30", "--frames", frames) == 2
    line = _one_line(capsys.readouterr().err)
    assert f"--frames '{frames}' is not START:END" in line and "usage" not in line and not out.exists()


def test_a_run_without_a_scale_says_it_measures_in_pixels(clip, tmp_path, capsys) -> None:
    out = tmp_path / "px.csv"
    assert _track(clip, out, "--rect", "8,8,40,30") == 0
    assert "note: no scale given: measuring in pixels (the mm columns are NaN)" in capsys.readouterr().err
    assert _track(clip, tmp_path / "mm.csv", "--rect", "8,8,40,30", "--mm-per-px", "1") == 0
    assert "no scale given" not in capsys.readouterr().err
