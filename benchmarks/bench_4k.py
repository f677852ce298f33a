"""The paper's own input: a 4K H.264 video of a small member, measured without a crop.

The paper films at 4K (3840x2160). This benchmark builds such a clip at run time (never
committed) from an independent bench clip (``../shared/bench/clips``, ``lowtex-wide`` by
default): each of its 480x320 frames placed in the middle of a 3840x2160 mid-grey frame (the
same member, the same mask, grey around it), encoded with x264 (CRF 12, like the bench clip),
the mask placed alike. Each method then runs ``refflow track`` with its defaults as a user
would, once on the whole frame and once with ``--roi`` holding the member's window
(:data:`ROI`, the crop a user would draw), one process per run, one after the other, on the
same cores. The table gives the frame loop's seconds per frame (the sidecar's ``frames_s``),
the process's peak resident memory (VmHWM), the RMSE against the clip's truth (the bench
scorer's convention: relative to the first frame, valid frames) and the ratio of the time
without ``--roi`` to the time with it.

Every run is held to ``--limit-gb`` of address space (default 4): a method whose memory grows
with the frame fails with an error in the table instead of taking the machine down.

    .venv/bin/python benchmarks/bench_4k.py [--clip lowtex-wide] [--frames 60] [--jobs 2]
        [--methods deepflow,dis,deepflow-opencv] [--out results/bench_4k.md]

Prints a Markdown table; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "bench" / "clips"
METHODS = ("deepflow", "dis", "deepflow-opencv")
WIDTH, HEIGHT = 3840, 2160
GREY = 128
# The --roi of the "with --roi" runs: the member's 480x320 clip (placed in the middle of the
# frame) plus 100 px, as in issue 31.
ROI = (1580, 820, 680, 520)

# Runs refflow in this process and reports its peak resident memory (MB, VmHWM) on stderr's
# last line.
_RUNNER = (
    "import sys\n"
    "from flow.cli import main\n"
    "rc = main(sys.argv[1:])\n"
    "peak = next((int(line.split()[1]) for line in open('/proc/self/status') if line.startswith('VmHWM')), 0)\n"
    "print(f'peak_rss_mb {peak / 1024:.1f}', file=sys.stderr)\n"
    "raise SystemExit(rc)\n"
)


def _frames(video: Path, count: int):
    capture = cv2.VideoCapture(str(video))
    try:
        for _ in range(count):
            ok, frame = capture.read()
            if not ok:
                return
            yield cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY)
    finally:
        capture.release()


def clip_4k(name: str, folder: Path, frames: int) -> Path:
    """A folder like a bench clip's (clip.mp4, mask.png, truth.csv, clip.json): the bench clip
    ``name``'s first ``frames`` frames in the middle of a 4K grey frame."""
    import imageio_ffmpeg

    source = BENCH / name
    meta = json.loads((source / "clip.json").read_text())
    mask = cv2.imread(str(source / meta.get("mask", "mask.png")), cv2.IMREAD_GRAYSCALE)
    height, width = mask.shape
    top, left = (HEIGHT - height) // 2, (WIDTH - width) // 2
    folder.mkdir(parents=True, exist_ok=True)
    big = np.zeros((HEIGHT, WIDTH), np.uint8)
    big[top:top + height, left:left + width] = mask
    cv2.imwrite(str(folder / "mask.png"), big)
    shutil.copy(source / "truth.csv", folder / "truth.csv")
    (folder / "clip.json").write_text(json.dumps({**meta, "video": "clip.mp4", "mask": "mask.png",
                                                  "placed_at_px": [left, top], "frame": [WIDTH, HEIGHT]}))
    crf = int(meta.get("generator", {}).get("crf", 12))
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "gray",
           "-s", f"{WIDTH}x{HEIGHT}", "-r", str(meta.get("fps", 60.0)), "-i", "-", "-c:v", "libx264",
           "-crf", str(crf), "-preset", "veryfast", "-pix_fmt", "yuv420p", str(folder / "clip.mp4")]
    encoder = subprocess.Popen(cmd, stdin=subprocess.PIPE)
    frame = np.full((HEIGHT, WIDTH), GREY, np.uint8)
    for grey in _frames(source / meta.get("video", "clip.mp4"), frames):
        frame[top:top + height, left:left + width] = grey
        encoder.stdin.write(frame.tobytes())
    encoder.stdin.close()
    if encoder.wait() != 0:
        raise RuntimeError(f"ffmpeg failed writing {folder / 'clip.mp4'}")
    return folder


def _limit(gigabytes: float):
    def apply() -> None:
        size = int(gigabytes * 1e9)
        resource.setrlimit(resource.RLIMIT_AS, (size, size))
    return apply


def run(folder: Path, method: str, jobs: int, roi: tuple[int, ...] | None, out: Path, limit_gb: float) -> dict:
    cmd = [sys.executable, "-c", _RUNNER, "track", str(folder / "clip.mp4"), "--mask", str(folder / "mask.png"),
           "--mm-per-px", "1", "--method", method, "--jobs", str(jobs), "--no-progress", "--out", str(out)]
    if roi is not None:
        cmd += ["--roi", ",".join(map(str, roi))]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, preexec_fn=_limit(limit_gb))
    lines = proc.stderr.strip().splitlines()
    if proc.returncode != 0:
        tail = next((line for line in reversed(lines) if not line.startswith("peak_rss")), "")
        return {"error": f"exit {proc.returncode}: {tail[:120]}"}
    peak = float(lines[-1].split()[1])
    sidecar = json.loads(out.with_suffix(".json").read_text())
    timings = sidecar["timings"]
    score = subprocess.run([sys.executable, str(ROOT.parent / "shared" / "bench" / "score.py"), str(folder),
                            str(out)], capture_output=True, text=True)
    rmse = json.loads(score.stdout.strip().splitlines()[-1]).get("rmse_px", float("nan"))
    frames = int(round(timings["frames_per_s"] * timings["frames_s"]))
    return {"s_per_frame": timings["frames_s"] / max(frames, 1), "peak_mb": peak, "rmse_px": rmse,
            "frames": frames, "full_frames": timings.get("full_frames"),
            "window": sidecar.get("parameters", {}).get("window_px") or sidecar.get("window_px")}


def table(results: dict[str, dict[str, dict]], jobs: int, frames: int, clip: str) -> str:
    lines = [f"`{clip}` in a {WIDTH}x{HEIGHT} H.264 frame, {frames} frames, `--jobs {jobs}` on "
             f"{os.cpu_count()} cores, one run; with `--roi {','.join(map(str, ROI))}` and without.", "",
             "| method | s/frame, no --roi | s/frame, --roi | no --roi / --roi | peak MB, no --roi / --roi | "
             "RMSE px, no --roi / --roi |",
             "|---|---|---|---|---|---|"]
    for method, by in results.items():
        whole, roi = by["whole"], by["roi"]
        cells = []
        for key, fmt in (("s_per_frame", "{:.3f}"),):
            cells += [fmt.format(r[key]) if "error" not in r else r["error"] for r in (whole, roi)]
        ratio = (f"{whole['s_per_frame'] / roi['s_per_frame']:.2f}x"
                 if "error" not in whole and "error" not in roi else "-")
        peak = " / ".join("-" if "error" in r else f"{r['peak_mb']:.0f}" for r in (whole, roi))
        rmse = " / ".join("-" if "error" in r else f"{r['rmse_px']:.3f}" for r in (whole, roi))
        lines.append(f"| `{method}` | {cells[0]} | {cells[1]} | {ratio} | {peak} | {rmse} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--clip", default="lowtex-wide", help="bench clip placed in the 4K frame")
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--limit-gb", type=float, default=4.0, help="address-space limit of each run")
    parser.add_argument("--keep", help="build the clip in this folder and keep it (default: a temporary one)")
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args(argv)
    results: dict[str, dict[str, dict]] = {}
    with tempfile.TemporaryDirectory() as tmp:
        folder = clip_4k(args.clip, Path(args.keep or tmp) / "clip4k", args.frames)
        for method in args.methods.split(","):
            results[method] = {}
            for label, roi in (("whole", None), ("roi", ROI)):
                r = run(folder, method, args.jobs, roi, Path(tmp) / f"{method}-{label}.csv", args.limit_gb)
                results[method][label] = r
                print(f"{method:16s} {label:5s} " + (
                    f"{r['s_per_frame']:.3f} s/frame, {r['peak_mb']:.0f} MB, RMSE {r['rmse_px']:.3f} px, "
                    f"full {r['full_frames']}" if "error" not in r else r["error"]), file=sys.stderr, flush=True)
    text = table(results, args.jobs, args.frames, args.clip)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
