"""End to end: `refflow track` on small generated clips, and every bad input's message."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main
from flow.io.frames import DEEP_TARGET_LEVEL

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


def ffmpeg(*args: str) -> None:
    """Run the ffmpeg of imageio-ffmpeg (a dependency), quietly."""
    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", *args],
                   check=True, capture_output=True, timeout=120)


def make_bad_videos(folder: Path) -> None:
    """Real containers that cannot be measured whole, as cameras and copies produce them."""
    source = ["-f", "lavfi", "-i", f"testsrc=size={W}x{H}:rate=30"]
    ffmpeg(*source, "-frames:v", "0", "-c:v", "ffv1", str(folder / "zero_frames.mkv"))
    ffmpeg(*source, "-frames:v", "0", "-c:v", "libx264", str(folder / "zero_frames.mp4"))
    # One frame: a still exported as a clip (it read as a row of zeros before 2026-12-06).
    ffmpeg(*source, "-frames:v", "1", "-c:v", "ffv1", str(folder / "one_frame.mkv"))
    # A complete MP4 with its index first (as phones write after recording), then cut:
    # the header promises 30 frames, the data stops after a few.
    ffmpeg(*source, "-frames:v", "30", "-c:v", "libx264", "-pix_fmt", "yuv420p", "-movflags", "+faststart",
           str(folder / "whole.mp4"))
    data = (folder / "whole.mp4").read_bytes()
    (folder / "truncated.mp4").write_bytes(data[: len(data) * 6 // 10])
    # Without the index first, an interrupted recording loses it altogether.
    ffmpeg(*source, "-frames:v", "30", "-c:v", "libx264", "-pix_fmt", "yuv420p", str(folder / "plain.mp4"))
    data = (folder / "plain.mp4").read_bytes()
    (folder / "no_index.mp4").write_bytes(data[: len(data) // 2])
    (folder / "not_a_video.mp4").write_text("this is not a video\n")
    (folder / "empty.avi").write_bytes(b"")
    (folder / "inf_scale.json").write_text('{"mm_per_px": Infinity}')
    huge = "1" + "0" * 400  # an integer no float holds
    (folder / "deep_scale.json").write_text("[" * 100_000 + "]" * 100_000)
    (folder / "digits_scale.json").write_text('{"mm_per_px": ' + "9" * 5000 + "}")
    (folder / "huge_scale.json").write_text('{"mm_per_px": ' + huge + "}")
    (folder / "true_length.json").write_text('{"known_length_mm": true, "between_px": [10, 20, 10, 40]}')
    (folder / "huge_point.json").write_text('{"known_length_mm": 5, "between_px": [10, 20, ' + huge + ", 40]}")


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
    make_bad_videos(folder)
    images = folder / "images"
    images.mkdir()
    cap = cv2.VideoCapture(str(video))
    for i in range(4):
        ok, image = cap.read()
        assert ok
        cv2.imwrite(str(images / f"img_{i:04d}.png"), image)
    (folder / "one_image").mkdir()
    cv2.imwrite(str(folder / "one_image" / "img_0000.png"), image)
    return {"video": video, "mask": folder / "mask.png", "folder": folder, "images": images}


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
                             "sigma_dx_px", "sigma_dy_px", "sigma_px", "poi_kept_frac", "residual", "flow_spread_px", "camera_dx_px", "camera_dy_px"]
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
    # a flag qualifies the reading, never deletes it: the occluded frames keep theirs
    assert np.isfinite(dx[~ok]).all()
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


def test_truncated_video_is_refused_unless_allowed(clip, tmp_path) -> None:
    """A cut file stops well before its container's duration: an error naming --allow-truncated."""
    out = tmp_path / "cut.csv"
    argv = [sys.executable, "-m", "flow.cli", "track", str(clip["folder"] / "truncated.mp4"),
            "--rect", "10,48,140,24", "--method", "dis", "--out", str(out), "--no-progress"]
    refused = subprocess.run(argv, capture_output=True, text=True, timeout=120)
    assert refused.returncode == 2
    assert refused.stderr.count("\n") == 1, refused.stderr  # one line: no decoder noise
    assert "is truncated" in refused.stderr and "--allow-truncated" in refused.stderr
    assert not out.exists() and not out.with_suffix(".json").exists()
    allowed = subprocess.run([*argv, "--allow-truncated"], capture_output=True, text=True, timeout=120)
    assert allowed.returncode == 0, allowed.stderr
    meta = json.loads(out.with_suffix(".json").read_text())
    assert 0 < meta["input"]["frames_decoded"] < 30 == meta["input"]["header_frames"]
    assert meta["input"]["frames_decoded"] == len(read_csv(out))
    assert meta["input"]["truncated"] is True
    assert any("truncated" in note for note in meta["notes"])


def test_truncated_avi_is_refused_too(tmp_path) -> None:
    video = tmp_path / "clip.avi"
    write_clip(video, "MJPG", occlude=False)
    data = video.read_bytes()
    truncated = tmp_path / "cut.avi"
    truncated.write_bytes(data[: len(data) // 2])
    out = tmp_path / "cut.csv"
    base = ["track", str(truncated), "--rect", "10,48,140,24", "--method", "dis", "--out", str(out), "--no-progress"]
    assert main(base) == 2 and not out.exists()
    assert main([*base, "--allow-truncated"]) == 0
    assert 0 < len(read_csv(out)) < N


def test_variable_frame_rate_video_is_not_called_truncated(tmp_path, capsys) -> None:
    """Its header frame count is an estimate (duration x nominal rate), not a promise."""
    video = tmp_path / "vfr.mkv"
    # 8 frames, the last three at growing intervals; -fps_mode vfr keeps the timestamps.
    ffmpeg("-f", "lavfi", "-i", f"testsrc=size={W}x{H}:rate=30", "-frames:v", "8",
           "-vf", "setpts='if(lt(N,5),N,5+(N-4)*(N-3))/30/TB'", "-fps_mode", "vfr", "-c:v", "ffv1", str(video))
    cap = cv2.VideoCapture(str(video))
    assert cap.get(cv2.CAP_PROP_FRAME_COUNT) > 8, "the header must over-count for this test to mean anything"
    out = tmp_path / "vfr.csv"
    assert main(["track", str(video), "--rect", "10,10,100,80", "--method", "dis", "--out", str(out),
                 "--no-progress"]) == 0
    assert "warning" not in capsys.readouterr().err
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["input"]["truncated"] is False and meta["input"]["frames_measured"] == 8
    assert any("variable frame rate" in note for note in meta["notes"])
    times = np.array([float(r["time_s"]) for r in read_csv(out)])
    assert np.allclose(np.diff(times), np.array([1, 1, 1, 1, 3, 4, 6]) / 30, atol=0.002)


BAD = {
    "missing file": (["{folder}/nope.mp4", "--mask", "{mask}"], "does not exist"),
    "unreadable video": (["{folder}/not_a_video.mp4", "--mask", "{mask}"], "cannot be opened"),
    "empty file": (["{folder}/empty.avi", "--mask", "{mask}"], "is empty (0 bytes)"),
    "zero-frame mkv": (["{folder}/zero_frames.mkv", "--mask", "{mask}"], "zero_frames.mkv' has no frames"),
    "zero-frame mp4": (["{folder}/zero_frames.mp4", "--mask", "{mask}"], "zero_frames.mp4' has no frames"),
    "truncated video": (["{folder}/truncated.mp4", "--mask", "{mask}"], "is truncated: its header lists 30"),
    "truncated mp4 without index": (["{folder}/no_index.mp4", "--mask", "{mask}"], "moov atom) is missing"),
    "empty mask": (["{video}", "--mask", "{folder}/empty.png"], "selects no pixel"),
    "wrong-size mask": (["{video}", "--mask", "{folder}/mask_small.png"], "mask is 80x60 but frames are 160x120"),
    "missing mask": (["{video}", "--mask", "{folder}/nomask.png"], "does not exist"),
    "roi outside": (["{video}", "--mask", "{mask}", "--roi", "100,50,200,100"], "outside the 160x120 frame"),
    "negative scale": (["{video}", "--mask", "{mask}", "--mm-per-px", "-1"], "--mm-per-px -1.0 is not a finite positive number"),
    "zero scale": (["{video}", "--mask", "{mask}", "--mm-per-px", "0"], "--mm-per-px 0.0 is not a finite positive number"),
    "zero known length": (["{video}", "--mask", "{mask}", "--known-length", "0", "--between", "0,0,5,5"],
                          "--known-length 0.0 is not a finite positive number"),
    "negative known length": (["{video}", "--mask", "{mask}", "--known-length", "-5", "--between", "0,0,5,5"],
                              "--known-length -5.0 is not a finite positive number"),
    "coincident points": (["{video}", "--mask", "{mask}", "--known-length", "5", "--between", "3,3,3,3"],
                          "the two points coincide"),
    "zero fps video": (["{video}", "--mask", "{mask}", "--fps", "0"], "--fps 0.0 is not a finite positive number"),
    "negative fps folder": (["{images}", "--mask", "{mask}", "--fps", "-30"], "--fps -30.0 is not a finite positive number"),
    "folder without fps": (["{images}", "--mask", "{mask}"], "pass --fps"),
    "unknown method": (["{video}", "--mask", "{mask}", "--method", "magic"], "unknown method 'magic'"),
    "bad method parameter": (["{video}", "--mask", "{mask}", "--param", "preset=warp"], "bad --param for dis"),
    "no mask": (["{video}"], "--mask"),
    "missing scale file": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/s.json"], "does not exist"),
    "scale file without scale": (["{video}", "--mask", "{mask}", "--scale-file", "{mask}"], "not readable JSON"),
    "two scales": (["{video}", "--mask", "{mask}", "--mm-per-px", "1", "--scale-file", "{mask}"], "pass one scale"),
    "missing calibration": (["{video}", "--mask", "{mask}", "--calibration", "{folder}/c.json"], "refflow calibrate"),
    "bad frame range": (["{video}", "--mask", "{mask}", "--frames", "9:3"], "is not START:END"),
    "frame range past the end": (["{video}", "--mask", "{mask}", "--frames", "40:50"], "no frame to measure in frames 40:50"),
    "frame range for klt": (["{video}", "--mask", "{mask}", "--method", "klt", "--frames", "0:5"],
                            "--frames needs a reference-frame (dense) method"),
    "one-frame video": (["{folder}/one_frame.mkv", "--mask", "{mask}"], "the input holds one frame, the reference"),
    "one-image folder": (["{folder}/one_image", "--mask", "{mask}", "--fps", "30"],
                         "a displacement needs at least one more"),
    "reference beyond the end": (["{video}", "--mask", "{mask}", "--reference-frame", "99"], "beyond the 30"),
    "infinite scale point": (["{video}", "--mask", "{mask}", "--known-length", "5", "--between", "1,1,inf,5"],
                             "holds a NaN or infinite coordinate"),
    "NaN scale point": (["{video}", "--mask", "{mask}", "--known-length", "5", "--between", "1,1,nan,5"],
                        "NaN or infinite coordinate"),
    "scale point off the frame": (["{video}", "--mask", "{mask}", "--known-length", "5", "--between",
                                   "1,1,5000,5"], "lies outside the 160x120 video frame"),
    "infinite scale in file": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/inf_scale.json"],
                               "needs a positive number under 'mm_per_px'"),
    "scale file nested too deeply": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/deep_scale.json"],
                                     "deep_scale.json is not readable JSON (nested too deeply)"),
    "scale file with a 5000-digit number": (["{video}", "--mask", "{mask}", "--scale-file",
                                             "{folder}/digits_scale.json"], "(a number with too many digits)"),
    "scale too large for a float": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/huge_scale.json"],
                                    "'known_length_mm' and 'between_px'), got 1000000000000"),
    "boolean known length in file": (["{video}", "--mask", "{mask}", "--scale-file", "{folder}/true_length.json"],
                                     "four numbers X1,Y1,X2,Y2, got True and [10, 20, 10, 40]"),
    "scale point too large for a float": (["{video}", "--mask", "{mask}", "--scale-file",
                                           "{folder}/huge_point.json"], "got 5 and [10, 20, 1000000000000"),
    "non-numeric method parameter": (["{video}", "--mask", "{mask}", "--method", "deepflow", "--param",
                                      "alpha=abc"], "parameter alpha must be a finite number, got 'abc'"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_input_gives_one_line_and_no_output(case, clip, tmp_path, capsys) -> None:
    argv, expected = BAD[case]
    fill = {key: str(value) for key, value in clip.items()}
    out = tmp_path / "out.csv"
    method = [] if "--method" in argv else ["--method", "dis"]
    rc = main(["track", *[a.format(**fill) for a in argv], *method, "--out", str(out),
               "--save-poi-tracks", str(tmp_path / "poi.npz"), "--no-progress"])
    err = capsys.readouterr().err.strip()
    assert rc == 2
    assert expected in err, err
    assert len(err.splitlines()) == 1 and "Traceback" not in err
    assert list(tmp_path.iterdir()) == [], "no output, no temporary left behind"


def test_a_part_of_one_frame_is_measured(clip, tmp_path) -> None:
    # A --frames part (of a run split by hand, merged later) may hold one frame: it is no input of one.
    out = tmp_path / "part.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--frames", "3:4",
                 "--out", str(out), "--no-progress"]) == 0
    assert [r["frame"] for r in read_csv(out)] == ["3"]


def test_every_bad_input_has_its_own_message() -> None:
    messages = [expected for _, expected in BAD.values()]
    generic = {"does not exist", "--mask"}  # shared on purpose: the path in the message tells them apart
    assert len({m for m in messages if m not in generic}) == len([m for m in messages if m not in generic])


def test_zero_frame_container_reports_one_line_without_decoder_noise(clip, tmp_path) -> None:
    out = tmp_path / "o.csv"
    result = subprocess.run([sys.executable, "-m", "flow.cli", "track", str(clip["folder"] / "zero_frames.mkv"),
                             "--mask", str(clip["mask"]), "--method", "dis", "--out", str(out)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 2
    assert result.stderr.count("\n") == 1 and "has no frames" in result.stderr, result.stderr
    assert list(tmp_path.iterdir()) == []


def _undecodable_png(path: Path, image: np.ndarray) -> None:
    """A PNG of ``image`` whose chunks are sound (Pillow's check passes) but whose data is no
    zlib stream: libpng fails on it, printing its error on file descriptor 2 itself."""
    import zlib

    data = cv2.imencode(".png", image)[1].tobytes()
    start = data.index(b"IDAT") - 4
    length = int.from_bytes(data[start:start + 4], "big")
    chunk = b"IDAT" + bytes(i % 251 for i in range(7, 7 + length))
    path.write_bytes(data[:start + 4] + chunk + zlib.crc32(chunk).to_bytes(4, "big") + data[start + 12 + length:])


@pytest.mark.parametrize("problem", ["damaged mp4 header", "first image undecodable", "first image warned about",
                                     "mask undecodable", "mask a JPEG stub"])
def test_decoder_noise_never_joins_the_message(clip, tmp_path, capfd, problem) -> None:
    """OpenCV's log, libpng's and libjpeg's own lines on file descriptor 2 (what a user sees):
    held back, and the decoder's complaint goes into the one line."""
    inputs = tmp_path / "inputs"
    inputs.mkdir()
    source, mask = clip["images"], clip["mask"]
    if problem == "damaged mp4 header":  # once misreported as a missing index (moov)
        source = inputs / "clip.mp4"
        source.write_bytes(b"\x01" + (clip["folder"] / "whole.mp4").read_bytes()[1:])
        expected = "is damaged: it holds its MP4/MOV index (moov atom)"
    elif problem == "first image undecodable":
        source = inputs / "frames"
        shutil.copytree(clip["images"], source)
        _undecodable_png(source / "img_0000.png", np.clip(texture(), 0, 255).astype(np.uint8))
        expected = "img_0000.png' cannot be read (libpng error: "
    elif problem == "first image warned about":  # libjpeg decodes it, with a warning, then it is refused
        source = inputs / "frames"
        shutil.copytree(clip["images"], source)
        data = bytearray(cv2.imencode(".jpg", np.clip(texture(), 0, 255).astype(np.uint8))[1].tobytes())
        at = data.index(b"\xff\xc0")  # the frame header (SOF0): its height, 120, becomes 1
        data[at + 5:at + 7] = (1).to_bytes(2, "big")
        (source / "img_0000.jpg").write_bytes(bytes(data))
        (source / "img_0000.png").unlink()
        expected = "is 160x120 but the first is 160x1"
    else:
        mask = inputs / "mask.png"
        if problem == "mask undecodable":
            _undecodable_png(mask, cv2.imread(str(clip["mask"]), cv2.IMREAD_GRAYSCALE))
            expected = "mask.png' cannot be read (libpng error: "
        else:  # the start of a JPEG, named .png: libjpeg prints on fd 2 itself too
            mask.write_bytes(b"\xff\xd8\xff\xe0")
            expected = "mask.png' cannot be read (Premature end of JPEG file): save it as an 8-bit PNG"
    out = tmp_path / "out" / "o.csv"
    capfd.readouterr()
    assert main(["track", str(source), "--fps", "30", "--mask", str(mask), "--method", "dis",
                 "--out", str(out), "--no-progress"]) == 2
    err = capfd.readouterr().err
    assert err.count("\n") == 1 and expected in err, err
    assert not out.parent.exists()


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
    # or a known length between two points (what a user clicked on the reference frame)
    scale.write_text('{"known_length_mm": 5.0, "between_px": [10, 20, 10, 40]}')
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis",
                 "--scale-file", str(scale), "--max-frames", "3", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())["scale"]
    assert meta["mm_per_px"] == 0.25 and "known length 5.0 mm" in meta["source"]
    scale.write_text('{"known_length_mm": 5.0, "between_px": [10, 20]}')
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis",
                 "--scale-file", str(scale), "--max-frames", "3", "--out", str(tmp_path / "bad.csv"),
                 "--no-progress"]) == 2
    assert not (tmp_path / "bad.csv").exists()


def test_a_real_bug_shows_its_traceback(clip, tmp_path, monkeypatch) -> None:
    """Only the tool's own input errors become one-line messages; a ValueError inside is a bug."""
    from flow.measure import quality

    def broken(*args, **kwargs):
        raise ValueError("internal slip")

    monkeypatch.setattr(quality, "measure", broken)
    out = tmp_path / "out.csv"
    with pytest.raises(ValueError, match="internal slip"):
        main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis",
              "--max-frames", "3", "--out", str(out), "--no-progress"])
    assert list(tmp_path.iterdir()) == []


def test_failed_sidecar_leaves_no_output_at_all(clip, tmp_path, monkeypatch) -> None:
    """CSV, sidecar and .npz are one set: a failure writing any of them leaves none."""
    real_write_text = Path.write_text

    def failing_write_text(self, *args, **kwargs):
        if self.name.endswith(".json"):
            real_write_text(self, '{"half": ')  # a half-written sidecar, then the disk fills up
            raise OSError(28, "No space left on device", str(self))
        return real_write_text(self, *args, **kwargs)

    monkeypatch.setattr(Path, "write_text", failing_write_text)
    out = tmp_path / "out.csv"
    rc = main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--max-frames", "4",
               "--out", str(out), "--save-poi-tracks", str(tmp_path / "poi.npz"),
               "--raw-tracks", str(tmp_path / "raw.npz"), "--no-progress"])
    assert rc == 2
    assert list(tmp_path.iterdir()) == []


def test_failed_poi_tracks_leave_no_csv(clip, tmp_path, monkeypatch) -> None:
    from flow.measure import storage

    def failing_write_npz(path, arrays, **kwargs):
        Path(path).write_bytes(b"PK half an archive")
        raise RuntimeError("writer crashed")

    monkeypatch.setattr(storage, "write_npz", failing_write_npz)
    with pytest.raises(RuntimeError, match="writer crashed"):
        main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--max-frames", "4",
              "--out", str(tmp_path / "out.csv"), "--save-poi-tracks", str(tmp_path / "poi.npz"), "--no-progress"])
    assert list(tmp_path.iterdir()) == []


def _at_sixth_frame(monkeypatch, action, counter: list | None = None) -> None:
    """Every method built from now on calls ``action()`` when its sixth frame is measured
    (and appends to ``counter`` for every frame)."""
    from flow.methods import registry

    real_get = registry.get_method
    calls = {"n": 0}

    def wrapped(name, **params):
        method = real_get(name, **params)
        real_calc = method.calc

        def calc(reference, current):
            calls["n"] += 1
            if counter is not None:
                counter.append(calls["n"])
            if calls["n"] == 6:
                action()
            return real_calc(reference, current)

        method.calc = calc
        return method

    monkeypatch.setattr(registry, "get_method", wrapped)


@pytest.mark.parametrize("jobs", ["1", "2"])
def test_ctrl_c_during_tracking_leaves_nothing(clip, tmp_path, monkeypatch, capsys, jobs) -> None:
    def interrupt() -> None:
        raise KeyboardInterrupt

    _at_sixth_frame(monkeypatch, interrupt)
    rc = main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--jobs", jobs,
               "--out", str(tmp_path / "out.csv"), "--save-poi-tracks", str(tmp_path / "p.npz"),
               "--raw-tracks", str(tmp_path / "raw.npz"), "--no-progress"])
    assert rc == 130 and "interrupted; no output written" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("when", ["tracking", "writing"])
def test_sigterm_leaves_nothing(clip, tmp_path, monkeypatch, capsys, when) -> None:
    """SIGTERM (timeout, SLURM, kill) while frames are measured or while the outputs are
    written: exit 143, and neither outputs nor hidden temporaries (.part, POI stores) stay."""
    import os
    import signal

    from flow.measure import storage

    if when == "tracking":
        _at_sixth_frame(monkeypatch, lambda: os.kill(os.getpid(), signal.SIGTERM))
    else:
        real_write = storage.write_npz

        def write_then_terminated(path, arrays, **kwargs):
            real_write(path, arrays, **kwargs)
            os.kill(os.getpid(), signal.SIGTERM)

        monkeypatch.setattr(storage, "write_npz", write_then_terminated)
    rc = main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--jobs", "2",
               "--out", str(tmp_path / "out.csv"), "--save-poi-tracks", str(tmp_path / "p.npz"),
               "--raw-tracks", str(tmp_path / "raw.npz"), "--no-progress"])
    assert rc == 143 and "terminated (SIGTERM); no output written" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # handler restored


def _numbers(path: Path) -> np.ndarray:
    return np.array([[float(v) for v in row.values()] for row in read_csv(path)])


@pytest.mark.parametrize("reference", ["0", "20"])
def test_parts_merged_equal_one_run(clip, tmp_path, reference) -> None:
    """--frames parts + merge give the very numbers of one run, wherever the reference frame is."""
    base = ["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--grid-step", "2",
            "--reference-frame", reference, "--no-progress"]
    scale = ["--mm-per-px", "0.5"]
    whole = tmp_path / "whole.csv"
    assert main([*base, *scale, "--out", str(whole)]) == 0
    parts = [tmp_path / "a.npz", tmp_path / "b.npz", tmp_path / "c.npz"]
    for part, frames in zip(parts, ["0:9", "9:17", "17:"], strict=True):
        assert main([*base, "--frames", frames, "--raw-tracks", str(part)]) == 0
    merged = tmp_path / "merged.csv"
    assert main(["merge", str(parts[2]), str(parts[0]), str(parts[1]), *scale, "--out", str(merged)]) == 0
    assert np.array_equal(_numbers(whole), _numbers(merged), equal_nan=True)
    meta_whole = json.loads(whole.with_suffix(".json").read_text())
    meta_merged = json.loads(merged.with_suffix(".json").read_text())
    for key in ("method", "parameters", "poi", "filter", "quality", "scale", "roi", "columns"):
        assert meta_whole[key] == meta_merged[key], key
    assert [p["frames"] for p in meta_merged["parts"]] == [[0, 9], [9, 17], [17, 30]]
    assert meta_merged["quality"]["frames_invalid"] == len(OCCLUDED)


def test_merge_refuses_parts_that_do_not_fit(clip, tmp_path, capsys) -> None:
    base = ["track", str(clip["video"]), "--mask", str(clip["mask"]), "--grid-step", "3", "--no-progress"]
    made = {}
    for name, extra in {"a": ["--frames", "0:10"], "b": ["--frames", "10:20"], "gap": ["--frames", "12:20"],
                        "overlap": ["--frames", "5:15"], "other": ["--frames", "10:20", "--grid-step", "4"],
                        "farneback": ["--frames", "10:20", "--method", "farneback"]}.items():
        made[name] = tmp_path / f"{name}.npz"
        method = [] if "--method" in extra else ["--method", "dis"]
        assert main([*base, *method, *extra, "--raw-tracks", str(made[name])]) == 0
    capsys.readouterr()
    out = tmp_path / "m.csv"
    cases = {"gap": "frames 10:12 are missing", "overlap": "overlaps", "other": "differ in poi",
             "farneback": "differ in method"}
    for name, expected in cases.items():
        assert main(["merge", str(made["a"]), str(made[name]), "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert expected in err and len(err.strip().splitlines()) == 1, err
    assert main(["merge", str(made["a"]), str(clip["mask"]), "--out", str(out)]) == 2
    assert "is not a .npz archive" in capsys.readouterr().err
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_frame_range_measures_only_that_range(clip, tmp_path) -> None:
    out = tmp_path / "range.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--frames", "20:26",
                 "--reference-frame", "0", "--out", str(out), "--no-progress"]) == 0
    rows = read_csv(out)
    assert [int(r["frame"]) for r in rows] == list(range(20, 26))
    dx = np.array([float(r["dx_px"]) for r in rows])
    assert np.abs(dx - truth_px()[20:26]).max() < 0.05, "measured against frame 0, outside the range"


def test_pois_figure_and_counts(clip, tmp_path, capsys) -> None:
    out = tmp_path / "pois.png"
    assert main(["pois", str(clip["video"]), "--mask", str(clip["mask"]), "--grid-step", "2",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert f"POIs: {12 * 70};" in printed and "harris corners in ROI:" in printed
    corners = int(printed.split("corners in ROI: ")[1].split()[0])
    on_mask = int(printed.split("(")[1].split()[0])
    assert corners > 10 and 0 < on_mask < corners  # the texture is everywhere, the mask a band
    image = cv2.imread(str(out))
    assert image is not None and image.shape[1] > 2 * image.shape[0]  # side by side


def test_plot_marks_the_dominant_frequency(tmp_path, capsys) -> None:
    time_s = np.arange(300) / 30.0
    paths = []
    for name, (f_hz, drift) in {"dense": (0.8, 0.0), "klt": (0.8, 0.3)}.items():
        path = tmp_path / f"{name}.csv"
        dx = 2 * np.sin(2 * np.pi * f_hz * time_s) + drift * time_s
        with path.open("w", newline="") as handle:
            writer = csv.writer(handle)
            writer.writerow(["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid"])
            for i, t in enumerate(time_s):
                writer.writerow([i, t, dx[i], 0.1 * dx[i], "nan", "nan", int(not 100 <= i < 110)])
        paths.append(str(path))
    out = tmp_path / "plot.png"
    assert main(["plot", *paths, "--out", str(out)]) == 0
    printed = capsys.readouterr().out.splitlines()
    for line in printed[:2]:
        hz = float(line.split("dx ")[1].split(" Hz")[0])
        assert hz == pytest.approx(0.8, abs=0.01), line
    assert out.is_file() and cv2.imread(str(out)) is not None
    assert main(["plot", paths[0], "--units", "mm", "--out", str(tmp_path / "mm.png")]) == 2


def test_outputs_sharing_a_name_are_refused_before_tracking(clip, tmp_path, capsys) -> None:
    same = tmp_path / "same.npz"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis",
                 "--out", str(tmp_path / "o.csv"), "--save-poi-tracks", str(same),
                 "--raw-tracks", str(same), "--no-progress"]) == 2
    assert "two outputs share a name" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_an_output_never_overwrites_an_input(clip, tmp_path, capsys) -> None:
    """--out on the video, or a sidecar (<out>.json) on the scale file: refused before any
    work, the input untouched."""
    video = tmp_path / "v.mp4"
    video.write_bytes(clip["video"].read_bytes())
    scale = tmp_path / "s.json"
    scale.write_text('{"mm_per_px": 0.5}')
    before = {p: p.read_bytes() for p in (video, scale)}
    for extra in (["--out", str(video)], ["--scale-file", str(scale), "--out", str(tmp_path / "s.csv")],
                  ["--scale-file", str(scale), "--raw-tracks", str(scale)]):
        assert main(["track", str(video), "--rect", "20,20,40,30", "--method", "dis", *extra,
                     "--no-progress"]) == 2
        err = capsys.readouterr().err
        assert "never writes over an input" in err and len(err.strip().splitlines()) == 1, err
    assert {p: p.read_bytes() for p in (video, scale)} == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.json", "v.mp4"]
    # nor among the images of an input folder
    assert main(["track", str(clip["images"]), "--fps", "30", "--rect", "20,20,40,30", "--method", "dis",
                 "--out", str(clip["images"] / "o.csv"), "--no-progress"]) == 2
    assert "a folder of input images" in capsys.readouterr().err
    assert not (clip["images"] / "o.csv").exists()


@pytest.mark.parametrize("low, high", [(20, 250), (0, 4095), (3000, 60000)])
def test_16_bit_images_keep_their_detail(tmp_path, low, high) -> None:
    """High-speed exports: 10-16-bit data in 16-bit images, often far below full scale (an
    underexposed 10-bit clip spans 20-250). One gain for the sequence keeps the texture; a
    fixed >> 8 would read this 1.5 px shift as 0."""
    folder = tmp_path / "frames"
    folder.mkdir()
    shifts = [0.0, 0.5, 1.0, 1.5]
    for i, shift in enumerate(shifts):
        image = texture(shift)  # about 83-173
        scaled = low + (image - 83.0) / 90.0 * (high - low)
        cv2.imwrite(str(folder / f"f{i}.png"), np.clip(np.rint(scaled), 0, 65535).astype(np.uint16))
    out = tmp_path / "o.csv"
    assert main(["track", str(folder), "--fps", "1000", "--rect", "40,30,80,60", "--method", "dis",
                 "--out", str(out), "--no-progress"]) == 0
    dx = np.array([float(r["dx_px"]) for r in read_csv(out)])
    assert np.allclose(dx, shifts, atol=0.1), dx
    meta = json.loads(out.with_suffix(".json").read_text())
    assert any(note.startswith("16-bit images: grey = value x") for note in meta["notes"])


def test_floating_point_images_are_read_as_their_8_bit_twins(tmp_path, capsys) -> None:
    """A DIC tool's export as 0-1 float TIFFs reads what the same frames as 8-bit PNGs read (the
    default method; before, the floats were clipped to grey 0 and the run refused as having no
    texture); a NaN in one image stops the run with one line naming it, and leaves no output."""
    shifts = [0.0, 0.4, 0.8, 1.2]
    readings = {}
    for kind in ("png", "tif"):
        folder = tmp_path / kind
        folder.mkdir()
        for i, shift in enumerate(shifts):
            image = np.clip(np.rint(texture(shift)), 0, 255)
            cv2.imwrite(str(folder / f"f{i}.{kind}"), image.astype(np.uint8) if kind == "png"
                        else (image / 255.0).astype(np.float32))
        out = tmp_path / f"{kind}.csv"
        assert main(["track", str(folder), "--fps", "100", "--rect", "40,30,80,60", "--out", str(out),
                     "--no-progress"]) == 0
        readings[kind] = np.array([float(r["dx_px"]) for r in read_csv(out)])
    assert np.allclose(readings["tif"], shifts, atol=0.05), readings
    assert np.allclose(readings["tif"], readings["png"], atol=0.01), readings
    capsys.readouterr()
    image = (texture(0.4) / 255.0).astype(np.float32)
    image[50, 70] = np.nan
    cv2.imwrite(str(tmp_path / "tif" / "f1.tif"), image)
    out = tmp_path / "nan.csv"
    assert main(["track", str(tmp_path / "tif"), "--fps", "100", "--rect", "40,30,80,60", "--out", str(out),
                 "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "image f1.tif holds 1 NaN or infinite pixel" in err, err
    assert not out.exists() and not out.with_suffix(".json").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["png", "png.csv", "png.json", "tif", "tif.csv", "tif.json"]


def test_a_tiff_stack_is_measured_frame_by_frame(tmp_path) -> None:
    """A 16-bit multi-page TIFF (ImageJ's stacks, scientific cameras): one frame per page, read
    as its shifts; before, OpenCV's video reader measured its first page alone (one frame)."""
    shifts = [0.0, 0.5, 1.0, 1.5, 2.0]
    stack = tmp_path / "stack.tif"
    assert cv2.imwritemulti(str(stack), [np.rint(1000 + 10 * texture(shift)).astype(np.uint16) for shift in shifts])
    out = tmp_path / "o.csv"
    assert main(["track", str(stack), "--fps", "50", "--rect", "40,30,80,60", "--out", str(out), "--no-progress"]) == 0
    rows = read_csv(out)
    assert [float(r["time_s"]) for r in rows] == [0.0, 0.02, 0.04, 0.06, 0.08]
    assert np.allclose([float(r["dx_px"]) for r in rows], shifts, atol=0.02), rows
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["input"]["bit_depth"] > 8 and any(note.startswith("16-bit TIFF pages") for note in meta["notes"])


def test_a_mask_kept_in_the_folder_of_frames_is_not_a_frame(tmp_path) -> None:
    """Users keep the mask beside the frames it was drawn on: it was read as the folder's last
    frame (a 7.5 px reading, flagged invalid, in the time series)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    shifts = [0.0, 0.5, 1.0]
    for i, shift in enumerate(shifts):
        cv2.imwrite(str(folder / f"{i:04d}.png"), np.clip(np.rint(texture(shift)), 0, 255).astype(np.uint8))
    mask = np.zeros((H, W), np.uint8)
    mask[30:90, 40:120] = 255
    cv2.imwrite(str(folder / "mask.png"), mask)
    out = tmp_path / "o.csv"
    assert main(["track", str(folder), "--fps", "10", "--mask", str(folder / "mask.png"), "--out", str(out),
                 "--no-progress"]) == 0
    rows = read_csv(out)
    assert len(rows) == 3 and np.allclose([float(r["dx_px"]) for r in rows], shifts, atol=0.02), rows
    meta = json.loads(out.with_suffix(".json").read_text())
    assert any(note.startswith("mask.png in the folder is one of the run's other inputs") for note in meta["notes"])


def test_deep_data_is_measured_at_full_depth(tmp_path) -> None:
    """A faint texture in 12-bit data (+-11 counts, +-0.6 grey levels on the 8-bit scale):
    the default method reads it at full depth, more accurately than from the same frames
    rounded to 8 bits (as they were before); an 8-bit-only method says it rounds."""
    shifts = [0.0, 0.3, 0.6, 0.9, 1.2]
    gain = DEEP_TARGET_LEVEL / 4000.0
    errors = {}
    for depth in (12, 8):
        folder = tmp_path / f"bits{depth}"
        folder.mkdir()
        for i, shift in enumerate(shifts):
            data = np.rint(2000 + (texture(shift) - 128) * 0.5)
            data[:, :8] = 4000  # a bright edge of the view sets the sequence's gain
            image = (data.astype(np.uint16) if depth == 12
                     else np.clip(np.rint(data * gain), 0, 255).astype(np.uint8))
            cv2.imwrite(str(folder / f"f{i}.png"), image)
        out = tmp_path / f"bits{depth}.csv"
        assert main(["track", str(folder), "--fps", "100", "--rect", "40,30,80,60",
                     "--out", str(out), "--no-progress"]) == 0
        dx = np.array([float(r["dx_px"]) for r in read_csv(out)])
        errors[depth] = float(np.abs(dx - shifts).max())
        meta = json.loads(out.with_suffix(".json").read_text())
        assert meta["input"]["bit_depth"] == depth and meta["input"]["measured_bits"] == depth
    assert errors[12] < 0.08 and errors[12] < 0.8 * errors[8], errors
    out = tmp_path / "dis.csv"
    assert main(["track", str(tmp_path / "bits12"), "--fps", "100", "--rect", "40,30,80,60",
                 "--method", "dis", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["input"]["measured_bits"] == 8
    assert any("12-bit data was rounded to 8 bits" in note for note in meta["notes"])


@pytest.mark.parametrize("problem", ["mis-sized image", "corrupt image", "png checksum error", "truncated jpeg",
                                     "truncated tiff", "parent is a file", "truncated mp4"])
def test_problems_found_before_the_first_frame(clip, tmp_path, monkeypatch, capsys, problem) -> None:
    """What can be checked up front is: a bad image at the end of a folder, an output
    folder that cannot exist. No frame is measured first (no wasted hour)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(6):
        cv2.imwrite(str(folder / f"f{i}.png"), np.clip(texture(0.2 * i), 0, 255).astype(np.uint8))
    out = tmp_path / "o.csv"
    if problem == "mis-sized image":
        cv2.imwrite(str(folder / "f9.png"), np.zeros((10, 10), np.uint8))
        expected = "image f9.png is 10x10 but the first is 160x120"
    elif problem == "corrupt image":
        (folder / "f9.png").write_bytes((folder / "f0.png").read_bytes()[:200])
        expected = "f9.png' cannot be read"
    elif problem == "png checksum error":  # Pillow's check raised SyntaxError: a traceback
        data = bytearray((folder / "f0.png").read_bytes())
        data[data.index(b"IDAT") + 100] ^= 0xFF
        (folder / "f9.png").write_bytes(bytes(data))
        expected = "f9.png' cannot be read (broken PNG file (bad header checksum in b'IDAT'))"
    elif problem in ("truncated jpeg", "truncated tiff"):  # passed the check: refused (or half grey) when reached
        suffix = ".jpg" if problem == "truncated jpeg" else ".tif"
        image = np.clip(texture(2.0), 0, 255).astype(np.uint8)
        if suffix == ".jpg":
            cv2.imwrite(str(folder / "f9.jpg"), image)
        else:  # Pillow's layout: the directory first, the strips after it
            from PIL import Image

            Image.fromarray(image).save(folder / "f9.tif")
        data = (folder / f"f9{suffix}").read_bytes()
        (folder / f"f9{suffix}").write_bytes(data[: len(data) * 3 // 4])
        expected = f"f9{suffix}' cannot be read (truncated: "
    elif problem == "parent is a file":
        (tmp_path / "taken").write_text("a file")
        out = tmp_path / "taken" / "o.csv"
        expected = "is a file, not a folder"
    else:  # index first (+faststart), then cut: the frame count is there, the data is not
        folder = clip["folder"] / "truncated.mp4"
        expected = "the file ends"
    measured = []
    _at_sixth_frame(monkeypatch, lambda: None, counter=measured)
    assert main(["track", str(folder), "--fps", "30", "--rect", "40,30,80,60", "--method", "dis",
                 "--out", str(out), "--no-progress"]) == 2
    assert expected in capsys.readouterr().err
    assert measured == [], "the problem must be found before any frame is measured"
    assert not out.exists() and not out.with_suffix(".json").exists()


def test_rotated_phone_video_is_measured_as_displayed(clip, tmp_path, capsys) -> None:
    """A display matrix (portrait phone video): frames are measured as displayed, the sidecar
    says so, a mask drawn on the stored frames is rotated to match (the same numbers as a
    mask drawn on the displayed frames), and a mis-sized mask's message names the rotation."""
    stored = tmp_path / "stored.mp4"
    ffmpeg("-i", str(clip["video"]), "-c:v", "libx264", "-crf", "0", "-pix_fmt", "yuv420p", str(stored))
    video = tmp_path / "rotated.mp4"
    ffmpeg("-display_rotation", "90", "-i", str(stored), "-c", "copy", str(video))
    raw_mask = cv2.imread(str(clip["mask"]), cv2.IMREAD_GRAYSCALE)  # drawn on the stored 160x120
    shown = tmp_path / "shown.png"
    cv2.imwrite(str(shown), cv2.rotate(raw_mask, cv2.ROTATE_90_COUNTERCLOCKWISE))  # what players show
    runs = {}
    for name, mask in (("raw", clip["mask"]), ("shown", shown)):
        runs[name] = tmp_path / f"{name}.csv"
        assert main(["track", str(video), "--mask", str(mask), "--method", "dis", "--out", str(runs[name]),
                     "--no-progress"]) == 0
    np.testing.assert_array_equal(_numbers(runs["raw"]), _numbers(runs["shown"]))
    meta = json.loads(runs["raw"].with_suffix(".json").read_text())
    assert meta["input"]["rotation_deg"] == 270 and meta["input"]["frame_size"] == [120, 160]
    assert any("display rotation" in n for n in meta["notes"])
    assert any("rotated by 270 degrees" in n for n in meta["notes"])
    small = tmp_path / "small.png"
    cv2.imwrite(str(small), raw_mask[:60, :80])
    assert main(["track", str(video), "--mask", str(small), "--method", "dis", "--out", str(tmp_path / "x.csv"),
                 "--no-progress"]) == 2
    assert "displayed rotated by 270 degrees" in capsys.readouterr().err


def test_a_mask_cut_by_the_roi_is_reported(clip, tmp_path, capsys) -> None:
    """A full-frame mask that --roi cuts: the run says how much of it is left out, in the
    console and the sidecar, instead of silently measuring the rest."""
    out = tmp_path / "o.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--roi", "0,0,80,120",
                 "--method", "dis", "--out", str(out), "--no-progress"]) == 0
    assert "leaves 1680 of the mask's pixels out" in capsys.readouterr().err
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["poi"]["mask_pixels_outside_roi"] == 1680 and meta["poi"]["mask_pixels"] == 24 * 70
    assert any("widen --roi" in note for note in meta["notes"])


def test_fps_on_a_video_is_the_capture_rate(clip, tmp_path) -> None:
    """A slow-motion clip (240 fps captured, 30 fps in the file): --fps 240 puts time_s on
    the capture's clock, says so in the sidecar, and the file is still complete."""
    out = tmp_path / "slow.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--method", "dis", "--fps", "240",
                 "--out", str(out), "--no-progress"]) == 0
    time_s = np.array([float(r["time_s"]) for r in read_csv(out)])
    # (Matroska stores milliseconds: 33 or 34 ms a frame in the file, 1/8 of it here)
    assert np.allclose(np.diff(time_s), 1 / 240, atol=0.001 / 8 + 1e-9)
    assert time_s[-1] == pytest.approx((len(time_s) - 1) / 240, abs=0.001)
    meta = json.loads(out.with_suffix(".json").read_text())
    assert any("overrides the file's 30 fps" in note for note in meta["notes"])
    assert meta["input"]["fps"] == 240 and not meta["input"]["truncated"]


def test_reference_average_of_frames_at_rest(tmp_path) -> None:
    """A key frame that differs from the frames after it (as a codec's first I-frame does)
    biases every measurement against it; a reference averaged over the frames at rest does not."""
    video = tmp_path / "keyframe.mkv"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"FFV1"), 30.0, (W, H), True)
    rest, truth = 10, np.r_[np.zeros(10), 1.2 * np.sin(np.linspace(0, 3 * np.pi, 20))]
    for i, shift in enumerate(truth):
        # frame 0 is rebuilt a little to the left of the frames that follow it
        image = texture(shift - (0.4 if i == 0 else 0.0), seed=4)
        grey = np.clip(np.rint(image), 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), np.pad(np.full((H - 40, W - 40), 255, np.uint8), 20))
    results = {}
    for average in (1, rest):
        out = tmp_path / f"avg{average}.csv"
        assert main(["track", str(video), "--mask", str(mask), "--method", "dis", "--mm-per-px", "1",
                     "--reference-average", str(average), "--out", str(out), "--no-progress"]) == 0
        dx = np.array([float(r["dx_px"]) for r in read_csv(out)])
        results[average] = float(np.sqrt(np.mean((dx[1:] - truth[1:]) ** 2)))
        assert json.loads(out.with_suffix(".json").read_text())["reference_average"] == average
    print(f"RMSE vs truth: frame-0 reference {results[1]:.3f} px, mean of {rest} frames {results[rest]:.3f} px")
    assert results[1] > 0.3 and results[rest] < 0.06
    assert main(["track", str(video), "--mask", str(mask), "--method", "dis", "--reference-average", "40",
                 "--out", str(tmp_path / "bad.csv"), "--no-progress"]) == 2
    assert not (tmp_path / "bad.csv").exists()
    # parts measured against the same averaged reference merge to the whole run
    parts = []
    for span in ("0:14", "14:"):
        parts.append(str(tmp_path / f"part{len(parts)}.npz"))
        assert main(["track", str(video), "--mask", str(mask), "--method", "dis", "--reference-average", str(rest),
                     "--frames", span, "--raw-tracks", parts[-1], "--no-progress"]) == 0
    assert main(["merge", *parts, "--mm-per-px", "1", "--out", str(tmp_path / "merged.csv")]) == 0
    assert (tmp_path / "merged.csv").read_text() == (tmp_path / f"avg{rest}.csv").read_text()


def _small_folder(tmp_path: Path) -> Path:
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"f{i}.png"), np.clip(np.rint(texture(0.3 * i)), 0, 255).astype(np.uint8))
    return folder


def test_jobs_beyond_the_cores_are_capped_and_said(tmp_path) -> None:
    from flow.cli import available_cores

    out = tmp_path / "o.csv"
    assert main(["track", str(_small_folder(tmp_path)), "--fps", "30", "--rect", "40,30,80,60",
                 "--method", "dis", "--jobs", "64", "--out", str(out), "--no-progress"]) == 0
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["jobs"] == available_cores()
    assert any(note.startswith("--jobs 64 is more than the") for note in meta["notes"])


def test_two_runs_never_write_one_output_at_once(tmp_path, capsys) -> None:
    """A run whose --out another live run is writing is refused (its process named); a claim
    left by a killed run is taken over; a re-run says it replaced the earlier output."""
    folder = _small_folder(tmp_path)
    out = tmp_path / "o.csv"
    argv = ["track", str(folder), "--fps", "30", "--rect", "40,30,80,60", "--method", "dis",
            "--out", str(out), "--no-progress"]
    lock = tmp_path / ".o.csv.refflow-lock"
    other = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        lock.write_text(str(other.pid))
        assert main(argv) == 2
        err = capsys.readouterr().err.strip()
        assert f"another refflow run (process {other.pid}) is writing" in err and len(err.splitlines()) == 1
        assert not out.exists() and lock.read_text() == str(other.pid)
    finally:
        other.kill()
        other.wait()
    assert main(argv) == 0  # the claim of a process that is gone is taken over
    assert out.exists() and not lock.exists()
    assert "replaced" not in capsys.readouterr().err
    assert main(argv) == 0
    assert f"replaced the earlier {out}" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["frames", "o.csv", "o.json"]


def test_the_bias_correction_follows_the_input_unless_asked(tmp_path) -> None:
    """The default's texture fit takes its own sub-pixel bias off lossless frames (FFV1) and not
    off a lossy codec's (MJPEG here, H.264 alike); the sidecar says which; a user's choice wins."""
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), np.pad(np.full((30, 100), 255, np.uint8), ((45, 45), (30, 30))))
    taken = {}
    for name, fourcc, extra in (("lossless", "FFV1", ()), ("lossy", "MJPG", ()),
                                ("asked", "MJPG", ("--param", "bias_correction=true"))):
        video = tmp_path / f"{name}.avi"
        write_clip(video, fourcc, occlude=False)
        out = tmp_path / f"{name}.csv"
        assert main(["track", str(video), "--mask", str(mask), "--max-frames", "4", "--out", str(out),
                     "--no-progress", *extra]) == 0
        taken[name] = json.loads(out.with_suffix(".json").read_text())["parameters"]["bias_correction"]
    assert taken == {"lossless": True, "lossy": False, "asked": True}
