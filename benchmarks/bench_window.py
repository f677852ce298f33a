"""A small member in a large frame: every dense method solves the POIs' window, not the frame.

Without ``--roi`` a user's 720p or 4K video is decoded whole, but each dense method solves the
flow only on the window the driver reads (the POIs' bounding box plus the margin the method
needs: ``flow.methods.base.CROP_MARGIN_PX``, or the matching's search radius for `deepflow` and
`deepmatching`; see ``DenseMethod``). This benchmark measures what that saves, as a user runs
it: a 1280x720 H.264 clip of a low-texture bar over a textured wall (the tests' generator,
``tests/unit/_lowtex_clip.py``, exact truth), POIs in a 100x50 px patch of the bar, each
method with its defaults and with ``--param crop=false`` (the whole frame), one process per
run on the same cores, one run. The table gives the frame loop's time per frame, the ratio
of the two, the peak memory of the process and the RMSE against the truth of both (the
window must not cost accuracy).

    .venv/bin/python benchmarks/bench_window.py [--frames 30] [--methods deepflow,dis]
        [--jobs 2] [--out results/bench_window.md]

Prints a Markdown table; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))
sys.path.insert(0, str(ROOT / "tests" / "unit"))

from bench_clip_speed import run  # noqa: E402

METHODS = ("deepflow", "deepflow-opencv", "dis", "farneback")
WIDTH, HEIGHT = 1280, 720
PATCH = (100, 50)  # the POIs: a --rect of this size on the bar


def clip_720p(folder: Path, frames: int) -> dict:
    from _lowtex_clip import encode, make_clip

    clip = make_clip(seed=5, frames=frames, height=HEIGHT, width=WIDTH, bar_width=124,
                     mask_margin=12, amplitude=3.0, frequency_hz=2.1)
    rows = np.flatnonzero(clip.mask.any(axis=1))
    cols = np.flatnonzero(clip.mask.any(axis=0))
    top = int(rows[len(rows) // 2])
    mask = np.zeros_like(clip.mask)
    mask[top:top + PATCH[1], cols[0]:cols[0] + PATCH[0]] = True
    assert (mask <= clip.mask).all(), "the patch must lie on the bar's interior"
    video = encode(clip, folder / "bar720p.mp4", crf=18)
    mask_path = folder / "bar720p_mask.png"
    cv2.imwrite(str(mask_path), mask.astype(np.uint8) * 255)
    return {"name": f"bar {WIDTH}x{HEIGHT}, POIs {PATCH[0]}x{PATCH[1]}", "video": video, "mask": mask_path,
            "truth": clip.truth_px - clip.truth_px[0], "axis": "x", "skip": np.zeros(frames, bool)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--frames", type=int, default=30)
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--jobs", type=int, default=os.cpu_count() or 1)
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args(argv)
    lines = [f"All with `--jobs {args.jobs}` on {os.cpu_count()} cores, one run at a time, "
             f"{args.frames} frames.", "",
             "| method | s/frame window (default) | s/frame whole frame | whole / window | "
             "peak MB window | peak MB whole | RMSE px window | RMSE px whole |",
             "|---|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        clip = clip_720p(Path(tmp), args.frames)
        for method in args.methods.split(","):
            window = run(clip, method, args.jobs, None, Path(tmp) / f"{method}.csv")
            whole = run(clip, method, args.jobs, None, Path(tmp) / f"{method}-whole.csv",
                        extra=("--param", "crop=false"))
            if "error" in window or "error" in whole:
                lines.append(f"| {method} | {window.get('error', '')} | {whole.get('error', '')} |||||")
                continue
            per = [r["frames_s"] / r["frames"] for r in (window, whole)]
            lines.append(f"| {method} | {per[0]:.3f} | {per[1]:.3f} | {per[1] / per[0]:.1f}x | "
                         f"{window['peak_mb']:.0f} | {whole['peak_mb']:.0f} | {window['rmse_px']:.3f} | "
                         f"{whole['rmse_px']:.3f} |")
            print(lines[-1], file=sys.stderr, flush=True)
    text = "\n".join(lines)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
