"""High-speed camera recordings measured end to end: Photron `.cih` + `.mraw` and Phantom
`.cine` (real files from ../shared/data) give the same numbers as the same frames exported as
an image folder, with the frame rate and bit depth from the file's header."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main
from flow.io.camera import open_camera_file

DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"
CIH, CINE = DATA / "data_showcase.cih", DATA / "data_small_cine.cine"
needs_data = pytest.mark.skipif(not (CIH.is_file() and CINE.is_file()),
                                reason=f"shared test data absent: {DATA} (see shared/data/README.md)")

# (file, a rectangle on the structure, frames, fps of the stored frames, bits of the data)
SAMPLES = {
    "photron": (CIH, "60,27,540,5", 75, 150.0, 8),  # 15000 fps, every 100th frame saved
    "phantom": (CINE, "10,3,110,20", 235, 100.0, 10),  # 10-bit packed codes
}


def read_rows(path: Path) -> list[dict[str, str]]:
    with path.open() as handle:
        return list(csv.DictReader(handle))


@needs_data
@pytest.mark.parametrize("sample", sorted(SAMPLES))
def test_camera_file_measures_like_its_frames_as_images(tmp_path, sample) -> None:
    path, rect, frames, fps, bits = SAMPLES[sample]
    out = tmp_path / "camera.csv"
    assert main(["track", str(path), "--rect", rect, "--method", "dis", "--out", str(out),
                 "--no-progress"]) == 0
    rows = read_rows(out)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert len(rows) == frames and meta["input"]["frames_decoded"] == frames
    assert meta["input"]["fps"] == pytest.approx(fps) and meta["input"]["bit_depth"] == bits
    times = np.array([float(r["time_s"]) for r in rows])
    assert np.allclose(np.diff(times), 1 / fps, rtol=1e-6)
    # The same frames as an image folder (8-bit PNGs, or 16-bit PNGs of the 10-bit codes).
    camera = open_camera_file(path)
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(camera.frame_count):
        cv2.imwrite(str(folder / f"f{i:04d}.png"), camera.read(i))
    again = tmp_path / "folder.csv"
    assert main(["track", str(folder), "--fps", str(fps), "--rect", rect, "--method", "dis",
                 "--out", str(again), "--no-progress"]) == 0
    columns = ("time_s", "dx_px", "dy_px", "valid")
    assert [[r[c] for c in columns] for r in rows] == [[r[c] for c in columns] for r in read_rows(again)]
    valid = np.array([r["valid"] == "1" for r in rows])
    dy = np.array([float(r["dy_px"]) for r in rows])
    assert valid.mean() > 0.9 and np.isfinite(dy[valid]).all()
    assert np.ptp(dy[valid]) > 0.05  # the structure vibrates: not a constant read


@needs_data
def test_phantom_blank_last_frame_is_flagged_and_times_follow_the_rate(tmp_path) -> None:
    """The sample's last image is blank and its time stamp is garbage: the frame is measured
    invalid, and the times are index / fps (the file's stamps set aside, said in the notes)."""
    out = tmp_path / "cine.csv"
    assert main(["track", str(CINE), "--rect", SAMPLES["phantom"][1], "--out", str(out),
                 "--no-progress"]) == 0
    rows = read_rows(out)
    assert [r["valid"] for r in rows[-1:]] == ["0"] and all(r["valid"] == "1" for r in rows[:-1])
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["input"]["measured_bits"] == 10  # the default method measures at full depth
    assert any("TIME64 stamp of image 234" in note for note in meta["notes"])
    assert float(rows[-1]["time_s"]) == pytest.approx(2.34)


@needs_data
def test_a_recordings_frames_file_is_an_input_too(tmp_path, capsys) -> None:
    header = tmp_path / "rec.cih"
    shutil.copy(CIH, header)
    shutil.copy(CIH.with_suffix(".mraw"), header.with_suffix(".mraw"))
    before = header.with_suffix(".mraw").read_bytes()
    assert main(["track", str(header), "--rect", SAMPLES["photron"][1], "--out",
                 str(header.with_suffix(".mraw")), "--no-progress"]) == 2
    assert "never writes over an input" in capsys.readouterr().err
    assert header.with_suffix(".mraw").read_bytes() == before
    header.with_suffix(".mraw").write_bytes(before[: len(before) // 2])
    assert main(["track", str(header), "--rect", SAMPLES["photron"][1], "--out",
                 str(tmp_path / "o.csv"), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "truncated" in err and len(err.splitlines()) == 1 and not (tmp_path / "o.csv").exists()
