"""Property: whatever is in the files `refflow track` reads (the video, the frames of an image
folder, the mask, the scale file, the calibration), it either measures (exit 0, finite numbers
on valid frames) or refuses with one line (exit 2) and leaves nothing in the output folder;
never a traceback, never another exit code.

The companion of test_cli_fuzz.py, which fuzzes option values: here the options are fixed and
valid, and the files are generated or damaged by hypothesis (cut, overwritten, random bytes,
other image modes and sizes, JSON of any shape). stderr is read as a user sees it: at the file
descriptor (capfd), where C libraries write, plus the Python warnings a fresh process would show;
a decoder's own noise next to the message counts as a second line. A traceback is any exception
out of `main` (the test fails with it, one failure per distinct crash site).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import shutil
import subprocess
import warnings
from pathlib import Path

import cv2
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st
from PIL import Image

from flow.cli import main

W, H = 96, 64
N_IMAGES, N_VIDEO = 4, 6
RECT = "20,10,50,40"
EXAMPLES = 80
# No "explain" phase: a failing run (one per distinct bug found) stays within a minute.
fuzz = settings(max_examples=EXAMPLES, deadline=None, derandomize=True,
                phases=[Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink],
                suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow,
                                       HealthCheck.data_too_large])


def texture(shift: int = 0) -> np.ndarray:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 255, (H, W)), (0, 0), 2.0)
    return np.clip(np.roll(base, shift, axis=1), 0, 255).astype(np.uint8)


def ffmpeg(*args: str) -> None:
    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", *args],
                   check=True, capture_output=True, timeout=60)


class Assets(dict):
    def __repr__(self) -> str:  # hypothesis prints the fixtures of a failing example
        return "<assets>"


@pytest.fixture(scope="module")
def assets(tmp_path_factory) -> Assets:
    """Valid inputs the strategies start from: an image folder, videos (MP4 with its index
    first, as phones write, MOV with it last, MJPEG AVI), and the bytes of each."""
    folder = tmp_path_factory.mktemp("reader_fuzz")
    frames = folder / "frames"
    frames.mkdir()
    for i in range(N_VIDEO):
        cv2.imwrite(str(frames / f"f{i}.png"), texture(i))
    source = ["-framerate", "30", "-i", str(frames / "f%d.png")]
    x264 = ["-c:v", "libx264", "-pix_fmt", "yuv420p"]
    ffmpeg(*source, *x264, "-movflags", "+faststart", str(folder / "faststart.mp4"))
    ffmpeg(*source, *x264, str(folder / "plain.mov"))
    ffmpeg(*source, "-c:v", "mjpeg", "-q:v", "3", str(folder / "mjpeg.avi"))
    images = folder / "images"  # the valid folder the mask, scale and calibration runs read
    images.mkdir()
    for i in range(N_IMAGES):
        shutil.copy(frames / f"f{i}.png", images / f"f{i}.png")
    videos = {name: (folder / name).read_bytes() for name in ("faststart.mp4", "plain.mov", "mjpeg.avi")}
    return Assets(images=images, videos=videos)


def fresh(tmp_path: Path) -> tuple[Path, Path]:
    """Empty input and output folders for one example (hypothesis reuses the fixture)."""
    inputs, outputs = tmp_path / "in", tmp_path / "out"
    for folder in (inputs, outputs):
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir()
    return inputs, outputs


# Python's own warning filters (python -W default): what a command-line run would print.
QUIET_BY_DEFAULT = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)


def run_track(argv: list[str], out: Path, capfd) -> tuple[int, str]:
    """``refflow track`` in-process: its exit status and its stderr as a user would see it (the
    file descriptor, where C libraries write, plus the Python warnings a fresh process shows)."""
    capfd.readouterr()
    with warnings.catch_warnings(record=True) as shown:
        warnings.resetwarnings()  # pytest's filters are not a user's
        for category in QUIET_BY_DEFAULT:
            warnings.simplefilter("ignore", category)
        try:  # any other exception is what a user would see as a traceback: it fails the test
            rc = main(["track", *argv, "--method", "dis", "--no-progress", "--out", str(out)])
        except SystemExit as stop:  # argparse's own refusal
            rc = stop.code
    err = capfd.readouterr().err + "".join(
        warnings.formatwarning(w.message, w.category, w.filename, w.lineno, w.line) for w in shown)
    return rc, err


def measures_or_refuses(argv: list[str], outputs: Path, capfd, case: object) -> int:
    """Run `refflow track` on ``argv`` and check the property; return its exit status."""
    out = outputs / "out.csv"
    rc, err = run_track(argv, out, capfd)
    assert rc in (0, 2), f"{case!r}: exit status {rc}\n{err}"
    assert "Traceback" not in err, f"{case!r}: traceback on stderr\n{err}"
    left = sorted(p.name for p in outputs.iterdir())
    if rc == 2:
        lines = [line for line in err.splitlines() if line.strip()]
        logged = [line for line in lines if re.match(r"\[ ?(ERROR|WARN|INFO):", line)]
        assert not logged, f"{case!r}: refused, with OpenCV's log on stderr\n{err}"
        assert len(lines) == 1 and lines[0].startswith("refflow track: error: "), \
            f"{case!r}: refused with {len(lines)} lines on stderr, not one\n{err}"
        assert left == [], f"{case!r}: refused, but left {left} in the output folder\n{err}"
        return rc
    assert left == ["out.csv", "out.json"], f"{case!r}: measured, but the output folder holds {left}"
    json.loads(out.with_suffix(".json").read_text())
    with out.open(newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert rows, f"{case!r}: measured, but the CSV has no row"
    for row in rows:
        assert row["valid"] in ("0", "1") and math.isfinite(float(row["time_s"])), f"{case!r}: {row}"
        if row["valid"] == "1":
            assert all(math.isfinite(float(row[c])) for c in ("dx_px", "dy_px", "dx_mm", "dy_mm")), \
                f"{case!r}: a valid frame with a non-finite displacement: {row}"
    return rc


# -- byte-level damage, shared by videos and images ------------------------------------------

positions = st.floats(0, 1, exclude_max=True)
patches = st.lists(st.tuples(positions, st.binary(min_size=1, max_size=16)), min_size=1, max_size=6)


def cut(data: bytes, where: float) -> bytes:
    return data[: int(where * len(data))]


def overwrite(data: bytes, patch: list[tuple[float, bytes]]) -> bytes:
    damaged = bytearray(data)
    for where, chunk in patch:
        start = int(where * len(damaged))
        damaged[start:start + len(chunk)] = chunk[: len(damaged) - start]
    return bytes(damaged)


# -- the video -------------------------------------------------------------------------------

VIDEO_SUFFIXES = (".mp4", ".mov", ".avi")
base_videos = st.sampled_from(("faststart.mp4", "plain.mov", "mjpeg.avi"))
videos = st.one_of(
    st.tuples(st.just("cut"), base_videos, positions),
    st.tuples(st.just("overwrite"), base_videos, patches),
    st.tuples(st.just("random bytes"), st.sampled_from(VIDEO_SUFFIXES), st.binary(max_size=4096)),
    st.tuples(st.just("zero bytes"), st.sampled_from(VIDEO_SUFFIXES)),
    st.tuples(st.just("text"), st.sampled_from(VIDEO_SUFFIXES), st.text(max_size=200)),
)


def video_file(case: tuple, videos_bytes: dict[str, bytes], inputs: Path) -> Path:
    kind, what, *rest = case
    if kind in ("cut", "overwrite"):
        data = videos_bytes[what]
        data = cut(data, rest[0]) if kind == "cut" else overwrite(data, rest[0])
        path = inputs / f"clip{Path(what).suffix}"
    else:
        path = inputs / f"clip{what}"
        data = {"random bytes": lambda: rest[0], "zero bytes": lambda: b"",
                "text": lambda: rest[0].encode("utf-8", "surrogatepass")}[kind]()
    path.write_bytes(data)
    return path


@fuzz
@given(case=videos, allow_truncated=st.booleans())
@example(case=("cut", "faststart.mp4", 1.0), allow_truncated=False)  # intact: measured
@example(case=("cut", "faststart.mp4", 0.99), allow_truncated=True)  # truncated, measured anyway
@example(case=("cut", "plain.mov", 0.5), allow_truncated=False)  # no index (moov) at all
def test_any_video_file_measures_or_refuses_in_one_line(assets, tmp_path, capfd, case, allow_truncated) -> None:
    inputs, outputs = fresh(tmp_path)
    path = video_file(case, assets["videos"], inputs)
    argv = [str(path), "--rect", RECT, "--mm-per-px", "0.5"] + (["--allow-truncated"] if allow_truncated else [])
    measures_or_refuses(argv, outputs, capfd, (case, allow_truncated))


# -- an image folder ---------------------------------------------------------------------------

IMAGE_MODES = ("16-bit", "RGBA", "P", "L", "1", "LA", "RGB", "CMYK", "F")
damages = st.one_of(
    st.tuples(st.just("truncated"), positions),
    st.tuples(st.just("overwrite"), patches),
    st.tuples(st.just("random bytes"), st.binary(max_size=2048)),
    st.tuples(st.just("size"), st.integers(1, 130), st.integers(1, 100)),
    st.tuples(st.just("mode"), st.sampled_from(IMAGE_MODES)),
    st.tuples(st.just("non-image file"),
              st.sampled_from(("notes.txt", ".DS_Store", "Thumbs.db", "._f0.png", "f1.json", "sub.png")),
              st.binary(max_size=256)),
)
folders = st.tuples(st.sampled_from(("png", "jpg", "tif")), st.sampled_from(("first", "middle", "last")),
                    damages)


def save_mode(image: np.ndarray, mode: str, path: Path) -> Path:
    """``image`` saved in PIL ``mode`` at ``path``; in PNG or TIFF where its format cannot
    hold the mode (a 16-bit frame in a JPEG folder)."""
    if mode == "16-bit":
        pil = Image.fromarray(image.astype(np.uint16) * 257)
    elif mode == "F":
        pil = Image.fromarray(image.astype(np.float32))
    else:
        pil = Image.fromarray(image).convert(mode)
    for candidate in (path, path.with_suffix(".png"), path.with_suffix(".tif")):
        buffer = io.BytesIO()
        try:
            pil.save(buffer, format=Image.registered_extensions()[candidate.suffix])
        except (OSError, KeyError, ValueError):
            continue
        candidate.write_bytes(buffer.getvalue())
        return candidate
    raise AssertionError(f"no format holds mode {mode}")


def image_folder(case: tuple, inputs: Path) -> Path:
    fmt, which, (kind, *rest) = case
    folder = inputs / "frames"
    folder.mkdir()
    paths = [folder / f"f{i}.{fmt}" for i in range(N_IMAGES)]
    for i, path in enumerate(paths):
        cv2.imwrite(str(path), texture(i))
    target = paths[{"first": 0, "middle": N_IMAGES // 2, "last": -1}[which]]
    if kind == "truncated":
        target.write_bytes(cut(target.read_bytes(), rest[0]))
    elif kind == "overwrite":
        target.write_bytes(overwrite(target.read_bytes(), rest[0]))
    elif kind == "random bytes":
        target.write_bytes(rest[0])
    elif kind == "size":
        cv2.imwrite(str(target), cv2.resize(texture(), tuple(rest), interpolation=cv2.INTER_AREA))
    elif kind == "mode":
        target.unlink()
        save_mode(texture(paths.index(target) % N_IMAGES), rest[0], target)
    else:
        name, content = rest
        if name == "sub.png":  # a folder whose name looks like an image
            (folder / name).mkdir()
        else:
            (folder / name).write_bytes(content)
    return folder


@fuzz
@given(case=folders)
@example(case=("png", "last", ("mode", "L")))  # a valid folder: measured
@example(case=("tif", "first", ("mode", "16-bit")))  # one gain from the first image
@example(case=("png", "middle", ("truncated", 0.5)))
@example(case=("jpg", "first", ("non-image file", "._f0.png", b"\x00\x05\x16\x07")))  # macOS AppleDouble
def test_any_image_folder_measures_or_refuses_in_one_line(tmp_path, capfd, case) -> None:
    inputs, outputs = fresh(tmp_path)
    folder = image_folder(case, inputs)
    measures_or_refuses([str(folder), "--fps", "30", "--rect", RECT, "--mm-per-px", "0.5"], outputs, capfd, case)


# -- the mask ----------------------------------------------------------------------------------

MASK_MODES = ("1", "L", "LA", "RGB", "RGBA", "P", "I;16")
masks = st.one_of(
    st.tuples(st.just("image"), st.sampled_from(MASK_MODES),
              st.one_of(st.just((W, H)), st.tuples(st.integers(1, 130), st.integers(1, 100))),
              st.sampled_from(("zero", "set", "rect", "random"))),
    st.tuples(st.just("truncated"), positions),
    st.tuples(st.just("overwrite"), patches),
    st.tuples(st.just("not a png"), st.one_of(st.binary(max_size=512), st.just(b"\xff\xd8\xff\xe0"),
                                             st.text(max_size=100).map(lambda t: t.encode("utf-8", "surrogatepass")))),
)


def mask_file(case: tuple, path: Path) -> Path:
    kind, *rest = case
    valid = np.zeros((H, W), np.uint8)
    valid[20:40, 15:80] = 255
    if kind == "image":
        mode, (width, height), content = rest
        rng = np.random.default_rng(width * 1000 + height)
        values = {"zero": np.zeros((height, width), np.uint8), "set": np.full((height, width), 255, np.uint8),
                  "rect": cv2.resize(valid, (width, height), interpolation=cv2.INTER_NEAREST),
                  "random": (rng.random((height, width)) > 0.5).astype(np.uint8) * 255}[content]
        if mode == "I;16":
            Image.fromarray(values.astype(np.uint16) * 257).save(path, format="PNG")
        else:
            Image.fromarray(values).convert(mode).save(path, format="PNG")
        return path
    buffer = io.BytesIO()
    Image.fromarray(valid).save(buffer, format="PNG")
    data = buffer.getvalue()
    path.write_bytes({"truncated": lambda: cut(data, rest[0]), "overwrite": lambda: overwrite(data, rest[0]),
                      "not a png": lambda: rest[0]}[kind]())
    return path


@fuzz
@given(case=masks)
@example(case=("image", "L", (W, H), "rect"))  # a valid mask: measured
@example(case=("image", "I;16", (W, H), "set"))
def test_any_mask_file_measures_or_refuses_in_one_line(assets, tmp_path, capfd, case) -> None:
    inputs, outputs = fresh(tmp_path)
    mask = mask_file(case, inputs / "mask.png")
    argv = [str(assets["images"]), "--fps", "30", "--mask", str(mask), "--mm-per-px", "0.5"]
    measures_or_refuses(argv, outputs, capfd, case)


# -- JSON files: the scale file and the calibration --------------------------------------------

class Raw(str):
    """A JSON token written as is (numbers Python's json cannot write: 1e400, 5000 digits)."""

    def __repr__(self) -> str:
        text = str(self)
        return f"Raw({text!r})" if len(text) <= 40 else f"Raw({text[:12]!r} + {len(text) - 12} more)"


def dumps(value: object) -> str:
    if isinstance(value, Raw):
        return str(value)
    if isinstance(value, dict):
        return "{" + ", ".join(f"{json.dumps(str(k))}: {dumps(v)}" for k, v in value.items()) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(dumps(v) for v in value) + "]"
    return json.dumps(value)  # NaN, Infinity as Python's json writes and reads them


numbers = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 0, -1, 1e308]),
    st.integers(-1000, 1000), st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from(["1e400", "-1e400", "1e-400", "-0.0", "1" + "0" * 400, "-" + "9" * 400,
                     "9" * 5000]).map(Raw),
)
scalars = st.one_of(st.none(), st.booleans(), numbers, st.text(max_size=10))
json_values = st.recursive(scalars, lambda inner: st.one_of(
    st.lists(inner, max_size=5), st.dictionaries(st.text(max_size=8), inner, max_size=4)), max_leaves=12)
DEEP = "<100000 nested lists>"
not_json = st.one_of(
    st.just(""), st.text(max_size=40),
    st.binary(max_size=40).map(lambda b: Raw(b.decode("latin-1"))),
    st.sampled_from(["{", "nul", "{'mm_per_px': 0.5}", '{"mm_per_px": 0.5,}', DEEP]),
)
bad_texts = st.tuples(st.just("text"), not_json)

on_frame = st.lists(st.one_of(st.integers(0, H), st.floats(0, H)), min_size=4, max_size=4)
scale_values = st.one_of(
    st.fixed_dictionaries({}, optional={
        "mm_per_px": st.one_of(st.floats(1e-3, 10), numbers, json_values),
        "known_length_mm": st.one_of(st.floats(0.1, 1e3), numbers, json_values),
        "between_px": st.one_of(on_frame, st.lists(numbers, min_size=4, max_size=4),
                                st.lists(numbers, max_size=6), json_values),
    }),
    json_values,
)
scale_documents = st.tuples(st.just("json"), scale_values)


def json_file(case: tuple, path: Path) -> Path:
    kind, value = case
    if kind == "text" and value == DEEP:
        path.write_text("[" * 100_000 + "]" * 100_000)
    elif kind == "text":
        path.write_bytes(value.encode("latin-1") if isinstance(value, Raw)
                         else value.encode("utf-8", "surrogatepass"))
    else:
        path.write_text(dumps(value))
    return path


@fuzz
@given(case=st.one_of(scale_documents, bad_texts))
@example(case=("json", {"mm_per_px": 0.5}))  # valid: measured
@example(case=("json", {"known_length_mm": 10, "between_px": [10, 10, 30, 10]}))
def test_any_scale_file_measures_or_refuses_in_one_line(assets, tmp_path, capfd, case) -> None:
    inputs, outputs = fresh(tmp_path)
    scale = json_file(case, inputs / "scale.json")
    argv = [str(assets["images"]), "--fps", "30", "--rect", RECT, "--scale-file", str(scale)]
    measures_or_refuses(argv, outputs, capfd, case)


CALIBRATION = {  # as `refflow calibrate` writes it (flow.calibration.calibrate)
    "camera_matrix": [[110.0, 0.0, 47.5], [0.0, 110.0, 31.5], [0.0, 0.0, 1.0]],
    "dist_coeffs": [-0.12, 0.05, 0.001, -0.001, 0.0],
    "rms_px": 0.21, "image_size": [W, H], "board": [9, 6], "square_mm": 25.0,
    "views_used": 12, "fix_k3": True, "notes": [],
}
matrices = st.one_of(
    st.lists(st.lists(numbers, max_size=4), max_size=4),
    st.lists(numbers, max_size=16),
    st.tuples(st.integers(0, 2), st.integers(0, 2), st.one_of(numbers, st.text(max_size=4), st.none())),
)
edits = st.one_of(
    st.tuples(st.just("drop"), st.sampled_from(sorted(CALIBRATION))),
    st.tuples(st.just("set"), st.sampled_from(sorted(CALIBRATION)), json_values),
    st.tuples(st.just("set"), st.sampled_from(["rms_px", "square_mm", "views_used"]), numbers),
    st.tuples(st.just("set"), st.just("camera_matrix"), matrices),
    st.tuples(st.just("set"), st.just("dist_coeffs"),
              st.one_of(st.lists(st.floats(-1, 1), max_size=15), st.lists(numbers, max_size=15))),
    st.tuples(st.just("set"), st.just("image_size"),
              st.one_of(st.lists(st.integers(-1, 200), max_size=3), st.just([H, W]), st.lists(numbers, max_size=3))),
)
calibrations = st.one_of(
    st.tuples(st.just("json"), st.lists(edits, min_size=1, max_size=3)),
    bad_texts,
)


def calibration_file(case: tuple, path: Path) -> Path:
    kind, value = case
    if kind == "text":
        return json_file(case, path)
    data = json.loads(json.dumps(CALIBRATION))
    for edit in value:
        if edit[0] == "drop":
            data.pop(edit[1], None)
        elif edit[1] == "camera_matrix" and isinstance(edit[2], tuple):  # one entry replaced
            row, column, entry = edit[2]
            data["camera_matrix"] = json.loads(json.dumps(CALIBRATION["camera_matrix"]))
            data["camera_matrix"][row][column] = entry
        else:
            data[edit[1]] = edit[2]
    path.write_text(dumps(data))
    return path


@fuzz
@given(case=calibrations)
@example(case=("json", [("set", "notes", [])]))  # valid: measured
@example(case=("json", [("drop", "image_size")]))
def test_any_calibration_file_measures_or_refuses_in_one_line(assets, tmp_path, capfd, case) -> None:
    inputs, outputs = fresh(tmp_path)
    calibration = calibration_file(case, inputs / "calibration.json")
    argv = [str(assets["images"]), "--fps", "30", "--rect", RECT, "--mm-per-px", "0.5",
            "--calibration", str(calibration)]
    measures_or_refuses(argv, outputs, capfd, case)
