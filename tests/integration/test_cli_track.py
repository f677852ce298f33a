"""End to end: `refflow track` on small generated clips, and every bad input's message."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main

W, H, N = 160, 120, 30
OCCLUDED = range(12, 17)


def texture(dx: float = 0.0, *, seed: int = 0, width: int = W, height: int = H) -> np.ndarray:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(float)
    x = x - dx
    image = np.zeros((height, width))
    for _ in range(40):
        fx, fy = rng.uniform(-0.12, 0.12, 2)
        image += rng.uniform(0.5, 1.0) * np.cos(2 * np.pi * (fx * x + fy * y) + rng.uniform(0, 2 * np.pi))
    return 128 + 45 * image / 4.0


def truth_px() -> np.ndarray:
    return 1.8 * np.sin(2 * np.pi * np.arange(N) / 15.0)


def write_clip(path: Path, fourcc: str, *, occlude: bool = True) -> None:
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30.0, (W, H), True)
    assert writer.isOpened()
    background = texture(seed=1)
    truth = truth_px()
    for i in range(N):
        image = background.copy()
        image[40:80] = texture(truth[i], seed=2)[40:80]
        if occlude and i in OCCLUDED:  # a white sheet in front of the camera
            image = 235 - 10 * np.linspace(0, 1, W)[None, :] + 0 * image
        grey = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("clip")
    video = folder / "occluded.mkv"
    write_clip(video, "FFV1")
    mask = np.zeros((H, W), np.uint8)
    mask[48:72, 10:150] = 255
    cv2.imwrite(str(folder / "mask.png"), mask)
    cv2.imwrite(str(folder / "mask_small.png"), mask[:60, :80])
    cv2.imwrite(str(folder / "empty.png"), np.zeros((H, W), np.uint8))
    (folder / "not_a_video.mp4").write_text("this is not a video\n")
    (folder / "zero.avi").write_bytes(b"")
    return {"video": video, "mask": folder / "mask.png", "folder": folder}


def read_csv(path: Path) -> list[dict[str, str]]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def test_occlusion_is_flagged_and_tracking_resumes(clip, tmp_path) -> None:
    out = tmp_path / "dis.csv"
    tracks = tmp_path / "poi.npz"
    rc = main([
        "track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis",
        "--mm-per-px", "0.5", "--out", str(out), "--save-poi-tracks", str(tracks), "--no-progress",
    ])
    assert rc == 0
    rows = read_csv(out)
    assert list(rows[0]) == ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid",
                             "poi_kept_frac", "residual", "flow_spread_px"]
    assert len(rows) == N
    valid = np.array([int(r["valid"]) for r in rows])
    assert (valid[list(OCCLUDED)] == 0).all()
    assert valid.sum() == N - len(OCCLUDED)
    dx = np.array([float(r["dx_px"]) for r in rows])
    truth = truth_px()
    ok = valid == 1
    assert np.abs(dx[ok] - truth[ok]).max() < 0.05
    after = np.arange(N) > max(OCCLUDED)
    assert np.abs(dx[after] - truth[after]).max() < 0.05, "tracking must resume after the occlusion"
    assert np.isnan(dx[~ok]).all()
    assert np.allclose([float(r["dx_mm"]) for r in rows if r["valid"] == "1"], 0.5 * dx[ok], atol=1e-5)
    times = np.array([float(r["time_s"]) for r in rows])
    assert np.allclose(np.diff(times), 1 / 30.0, atol=0.002)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["method"] == "dis" and meta["poi"]["count"] == 24 * 140
    assert meta["scale"]["mm_per_px"] == 0.5 and meta["quality"]["frames_invalid"] == len(OCCLUDED)
    assert {"versions", "timings", "roi", "parameters", "calibration"} <= set(meta)
    saved = np.load(tracks)
    assert saved["dx_px"].shape == (N, 24 * 140) and saved["x_px"].shape == (24 * 140,)


def test_klt_baseline_is_lost_after_the_occlusion(clip, tmp_path) -> None:
    out = tmp_path / "klt.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "klt",
                 "--out", str(out), "--no-progress"]) == 0
    rows = read_csv(out)
    dx = np.array([float(r["dx_px"]) for r in rows])
    after = np.arange(N) > max(OCCLUDED)
    error_after = np.nan_to_num(np.abs(dx[after] - truth_px()[after]), nan=np.inf)
    assert error_after.max() > 0.2  # features are lost or wrong; the paper's Fig. 10(b)


def test_jobs_and_roi_give_the_same_measurement(clip, tmp_path) -> None:
    one, two = tmp_path / "one.csv", tmp_path / "two.csv"
    base = ["track", str(clip["video"]), "--rect", "10,48,140,24", "--method", "farneback",
            "--max-frames", "10", "--no-progress"]
    assert main([*base, "--out", str(one)]) == 0
    assert main([*base, "--out", str(two), "--jobs", "2", "--roi", "0,30,160,60"]) == 0
    a = np.array([float(r["dx_px"]) for r in read_csv(one)])
    b = np.array([float(r["dx_px"]) for r in read_csv(two)])
    assert len(a) == len(b) == 10
    assert np.abs(a - truth_px()[:10]).max() < 0.05 and np.abs(b - truth_px()[:10]).max() < 0.05


def test_image_folder_input_and_known_length_scale(clip, tmp_path) -> None:
    frames = tmp_path / "frames"
    frames.mkdir()
    cap = cv2.VideoCapture(str(clip["video"]))
    for i in range(6):
        ok, image = cap.read()
        assert ok
        cv2.imwrite(str(frames / f"img_{i:04d}.png"), image)
    out = tmp_path / "f.csv"
    assert main(["track", str(frames), "--fps", "60", "--mask", str(clip["mask"]), "--method", "dis",
                 "--known-length", "100", "--between", "0,0,0,50", "--out", str(out), "--no-progress"]) == 0
    rows = read_csv(out)
    assert float(rows[1]["time_s"]) == pytest.approx(1 / 60, abs=1e-6)
    assert float(rows[3]["dx_mm"]) == pytest.approx(2 * float(rows[3]["dx_px"]), abs=1e-5)


def test_truncated_video_is_reported_and_measured_honestly(tmp_path) -> None:
    video = tmp_path / "clip.avi"
    write_clip(video, "MJPG", occlude=False)
    data = video.read_bytes()
    truncated = tmp_path / "cut.avi"
    truncated.write_bytes(data[: len(data) // 2])
    out = tmp_path / "cut.csv"
    result = subprocess.run(
        [sys.executable, "-m", "flow.cli", "track", str(truncated), "--rect", "10,48,140,24",
         "--method", "dis", "--out", str(out), "--no-progress"],
        capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    meta = json.loads(out.with_suffix(".json").read_text())
    assert 0 < meta["input"]["frames_decoded"] < N == meta["input"]["header_frames"]
    assert meta["input"]["frames_decoded"] == len(read_csv(out))
    assert meta["input"]["truncated"] is True
    assert "header says 30 frames but only" in result.stderr
    assert any("truncated" in note for note in meta["notes"])


BAD = {
    "missing file": (["{folder}/nope.mp4", "--mask", "{mask}"], "does not exist"),
    "unreadable video": (["{folder}/not_a_video.mp4", "--mask", "{mask}"], "cannot be opened"),
    "zero-frame video": (["{folder}/zero.avi", "--mask", "{mask}"], "cannot be opened"),
    "empty mask": (["{video}", "--mask", "{folder}/empty.png"], "selects no pixel"),
    "wrong-size mask": (["{video}", "--mask", "{folder}/mask_small.png"], "mask is 80x60 but frames are 160x120"),
    "missing mask": (["{video}", "--mask", "{folder}/nomask.png"], "does not exist"),
    "roi outside": (["{video}", "--mask", "{mask}", "--roi", "100,50,200,100"], "outside the 160x120 frame"),
    "negative scale": (["{video}", "--mask", "{mask}", "--mm-per-px", "-1"], "not positive"),
    "zero scale": (["{video}", "--mask", "{mask}", "--mm-per-px", "0"], "not positive"),
    "unknown method": (["{video}", "--mask", "{mask}", "--method", "magic"], "unknown method 'magic'"),
    "no mask": (["{video}"], "--mask"),
    "missing scale file": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/s.json"], "does not exist"),
    "scale file without scale": (["{video}", "--mask", "{mask}", "--scale-file", "{mask}"], "not readable JSON"),
    "two scales": (["{video}", "--mask", "{mask}", "--mm-per-px", "1", "--scale-file", "{mask}"], "pass one scale"),
    "missing calibration": (["{video}", "--mask", "{mask}", "--calibration", "{folder}/c.json"], "refflow calibrate"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_gives_one_line_and_no_output(case, clip, tmp_path, capsys) -> None:
    argv, expected = BAD[case]
    fill = {"folder": clip["folder"], "mask": clip["mask"], "video": clip["video"]}
    out = tmp_path / "out.csv"
    method = [] if "--method" in argv else ["--method", "dis"]
    rc = main(["track", *[a.format(**fill) for a in argv], *method, "--out", str(out), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert expected in err, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out")]


def test_console_script_reports_bad_input_without_traceback(tmp_path) -> None:
    exe = Path(sys.executable).with_name("refflow")
    if not exe.exists():
        pytest.skip("refflow console script not installed in this environment")
    result = subprocess.run([str(exe), "track", str(tmp_path / "missing.mp4"), "--rect", "0,0,5,5",
                             "--out", str(tmp_path / "o.csv")], capture_output=True, text=True, timeout=60)
    assert result.returncode == 2 and "does not exist" in result.stderr
    assert "Traceback" not in result.stderr and not (tmp_path / "o.csv").exists()


def test_methods_lists_every_method(capsys) -> None:
    assert main(["methods"]) == 0
    out = capsys.readouterr().out
    for name in ("deepflow-opencv", "dis", "farneback", "klt", "klt-ref"):
        assert name in out


def test_scale_file_gives_the_mm_columns(clip, tmp_path) -> None:
    scale = tmp_path / "scale.json"
    scale.write_text('{"mm_per_px": 0.25, "other": 1}')
    out = tmp_path / "out.csv"
    rc = main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--scale-file", str(scale),
               "--max-frames", "3", "--out", str(out), "--no-progress"])
    assert rc == 0
    rows = list(csv.DictReader(out.open()))
    for row in rows:
        assert float(row["dx_mm"]) == pytest.approx(0.25 * float(row["dx_px"]), abs=1e-6)
    assert json.loads(out.with_suffix(".json").read_text())["scale"]["mm_per_px"] == 0.25
