"""Speed of whole clips, as a user measures them: `deepflow` (the default) against OpenCV's
DeepFlow and DIS on the same clips, the same cores and the same --jobs, in one run.

A video is not a set of unrelated pairs: `deepflow` measures each chain's first frame in full
and tracks the member through the rest (see `flow.methods.deepflow.method`), so its speed is a
property of the clip, not of one pair (`bench_deepflow.py` keeps the pair-wise comparison).
Each method runs `refflow track CLIP --mask MASK --mm-per-px 1 --jobs J` in its own process,
one after the other; the table gives frames per second of the frame loop (the sidecar's
`frames_s`), the ratio of each method's time to OpenCV DeepFlow's, the process's peak
memory, the RMSE against the clip's truth (so that speed is never bought with accuracy
unseen) and, for `deepflow`, how many frames it measured in full (and how many it only glimpsed,
showing nothing of the scene: see `flow.methods.deepflow.hidden`).

Clips: the independent bench clips in ``../shared/bench/clips`` (480x320; lowtex-wide,
jump and occlusion by default: the warm start's easy case and its two fall-backs), the
workbench's `ambient` render when `make all` has made it (``results/ambient/render``), and
an 800x400 low-texture bar over a textured wall drawn here with exact truth (the tests'
generator, ``tests/unit/_lowtex_clip.py``).

    .venv/bin/python benchmarks/bench_clip_speed.py [--jobs 2] [--clips lowtex-wide,jump]
        [--max-frames 180] [--out results/bench_clip_speed.md]

Prints a Markdown table; asserts nothing (timings depend on the machine and its load).
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BENCH = ROOT.parent / "shared" / "bench" / "clips"
WORKBENCH = ROOT / "results" / "ambient" / "render"
METHODS = ("deepflow", "deepflow-opencv", "dis")
BASELINE = "deepflow-opencv"

# Runs refflow in this process and reports its peak resident memory (MB, the kernel's VmHWM of
# this process; ru_maxrss can carry the parent's over exec) on stderr's last line.
_RUNNER = (
    "import sys\n"
    "from flow.cli import main\n"
    "rc = main(sys.argv[1:])\n"
    "peak = next((int(line.split()[1]) for line in open('/proc/self/status') if line.startswith('VmHWM')), 0)\n"
    "print(f'peak_rss_mb {peak / 1024:.1f}', file=sys.stderr)\n"
    "raise SystemExit(rc)\n"
)


def synthetic_clip(folder: Path, frames: int) -> dict:
    """An 800x400 low-texture bar (vertical, moving along x) over a textured wall, H.264."""
    sys.path.insert(0, str(ROOT / "tests" / "unit"))
    from _lowtex_clip import encode, make_clip

    clip = make_clip(seed=3, frames=frames, height=400, width=800, bar_width=48, amplitude=3.0,
                     frequency_hz=2.1)
    video = encode(clip, folder / "bar800x400.mp4", crf=18)
    mask = folder / "bar800x400_mask.png"
    cv2.imwrite(str(mask), clip.mask.astype(np.uint8) * 255)
    return {"name": "synthetic bar 800x400", "video": video, "mask": mask,
            "truth": clip.truth_px - clip.truth_px[0], "axis": "x", "skip": np.zeros(frames, bool)}


def bench_clip(name: str) -> dict:
    folder = BENCH / name
    meta = json.loads((folder / "clip.json").read_text())
    truth = np.loadtxt(folder / "truth.csv", delimiter=",", skiprows=1)
    axis = meta.get("axis", "x")
    true = truth[:, 2 if axis == "x" else 3]
    skip = np.zeros(len(truth), bool)
    if meta.get("occlusion_s"):
        t0, t1 = meta["occlusion_s"]
        skip = (truth[:, 1] >= t0) & (truth[:, 1] < t1)
    return {"name": f"bench {name}", "video": folder / meta.get("video", "clip.mp4"),
            "mask": folder / meta.get("mask", "mask.png"), "truth": true - true[0], "axis": axis,
            "skip": skip}


def workbench_clip() -> dict | None:
    video, truth_csv = WORKBENCH / "video.mp4", WORKBENCH / "truth.csv"
    if not (video.exists() and truth_csv.exists()):
        return None
    with truth_csv.open() as handle:
        rows = list(csv.DictReader(handle))
    dx = np.array([float(r["dx_px"]) for r in rows])
    dy = np.array([float(r["dy_px"]) for r in rows])
    axis, true = ("x", dx) if np.ptp(dx) >= np.ptp(dy) else ("y", dy)
    occluded = np.array([r.get("occluded", "0") == "1" for r in rows])
    width = int(cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FRAME_WIDTH))
    height = int(cv2.VideoCapture(str(video)).get(cv2.CAP_PROP_FRAME_HEIGHT))
    return {"name": f"workbench ambient {width}x{height}", "video": video, "mask": WORKBENCH / "mask.png",
            "truth": true - true[0], "axis": axis, "skip": occluded}


def run(clip: dict, method: str, jobs: int, max_frames: int | None, out: Path,
        extra: tuple[str, ...] = ()) -> dict:
    cmd = [sys.executable, "-c", _RUNNER, "track", str(clip["video"]), "--mask", str(clip["mask"]),
           "--mm-per-px", "1", "--method", method, "--jobs", str(jobs), "--no-progress",
           "--out", str(out), *extra]
    if max_frames:
        cmd += ["--max-frames", str(max_frames)]
    proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    lines = proc.stderr.strip().splitlines()
    if proc.returncode != 0:
        return {"error": next((line for line in reversed(lines) if not line.startswith("peak_rss")),
                              f"exit {proc.returncode}")}
    peak = float(lines[-1].split()[1])
    timings = json.loads(out.with_suffix(".json").read_text())["timings"]
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    key = "dx_px" if clip["axis"] == "x" else "dy_px"
    measured = np.array([float(r[key]) for r in rows])
    valid = np.array([r["valid"] == "1" for r in rows])
    true, skip = clip["truth"][: len(rows)], clip["skip"][: len(rows)]
    use = valid & np.isfinite(measured) & ~skip
    rmse = float(np.sqrt(np.mean((measured[use] - true[use]) ** 2))) if use.any() else float("nan")
    return {"frames": len(rows), "frames_s": timings["frames_s"], "fps": timings["frames_per_s"],
            "peak_mb": peak, "rmse_px": rmse, "measured": float(use.sum() / max((~skip).sum(), 1)),
            "full_frames": timings.get("full_frames"), "hidden_frames": timings.get("hidden_frames")}


def table(results: list[tuple[dict, dict]], jobs: int) -> str:
    lines = [f"All with `--jobs {jobs}` on {os.cpu_count()} cores, one method at a time.", "",
             f"| clip | method | frames | frames/s | time vs {BASELINE} | peak MB | RMSE px | measured | "
             "measured in full |",
             "|---|---|---|---|---|---|---|---|---|"]
    for clip, per_method in results:
        base = per_method.get(BASELINE, {}).get("frames_s")
        for method, r in per_method.items():
            if "error" in r:
                lines.append(f"| {clip['name']} | {method} | {r['error']} |||||||")
                continue
            ratio = f"{r['frames_s'] / base:.2f}x" if base else "-"
            full = "-" if r["full_frames"] is None else f"{int(r['full_frames'])}"
            if r.get("hidden_frames"):
                full += f" (+{int(r['hidden_frames'])} showing nothing, glimpsed)"
            lines.append(f"| {clip['name']} | {method} | {r['frames']} | {r['fps']:.2f} | {ratio} | "
                         f"{r['peak_mb']:.0f} | {r['rmse_px']:.3f} | {r['measured']:.2f} | {full} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--clips", default="lowtex-wide,jump,occlusion", help="bench clips (comma-separated)")
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--max-frames", type=int, default=180, help="frames per clip (0: all)")
    parser.add_argument("--synthetic-frames", type=int, default=120, help="frames of the 800x400 clip (0: none)")
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args(argv)
    methods = args.methods.split(",")
    results: list[tuple[dict, dict]] = []
    with tempfile.TemporaryDirectory() as tmp:
        clips = [bench_clip(name) for name in args.clips.split(",") if name and (BENCH / name).is_dir()]
        workbench = workbench_clip()
        if workbench is None:
            print(f"no workbench render at {WORKBENCH} (make all makes it): skipped", file=sys.stderr)
        else:
            clips.append(workbench)
        if args.synthetic_frames:
            clips.append(synthetic_clip(Path(tmp), args.synthetic_frames))
        for clip in clips:
            per_method = {}
            for method in methods:
                r = run(clip, method, args.jobs, args.max_frames or None, Path(tmp) / f"{method}.csv")
                per_method[method] = r
                print(f"{clip['name']:28s} {method:16s} " + (
                    f"{r['fps']:.2f} frames/s, RMSE {r['rmse_px']:.3f} px, {r['peak_mb']:.0f} MB"
                    if "error" not in r else r["error"]), file=sys.stderr, flush=True)
            results.append((clip, per_method))
    text = table(results, args.jobs)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
