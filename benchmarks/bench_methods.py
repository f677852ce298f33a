"""Frames per second per method on an 800x400 ROI, and the speed-up of --jobs 2 over --jobs 1.

Runs the real driver (`flow.measure.driver`) on a synthetic image folder of a textured band
moving sub-pixel. Only the frame loop is timed (decoding, ROI cropping, flow, POI
sampling, residuals): reading the reference frame and building the methods are setup,
and a warm-up run first compiles what numba compiles.

The speed-up compares like with like: both runs pin OpenCV and numba to one thread
per job, so it measures frames processed in parallel. The first column shows jobs=1
with the libraries' own threading (what `refflow track` does by default). Prints a
table; asserts nothing (timings depend on the machine).

    .venv/bin/python benchmarks/bench_methods.py [--frames 12] [--methods dis,farneback]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from flow.io.frames import Roi  # noqa: E402
from flow.io.source import open_source
from flow.measure.driver import track_dense, track_sparse  # noqa: E402
from flow.methods import registry  # noqa: E402

FULL = (1280, 720)
ROI = Roi(240, 160, 800, 400)
SLOW = {"tvl1": 4, "deepflow-opencv": 6, "deepflow": 4, "deepmatching": 4}


def make_frames(folder: Path, n_frames: int) -> None:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 256, (FULL[1] + 20, FULL[0] + 20)).astype(np.float32), (0, 0), 2.0)
    for i in range(n_frames):
        shift = 1.5 * np.sin(2 * np.pi * i / 10)
        matrix = np.float32([[1, 0, shift], [0, 1, 0]])
        image = cv2.warpAffine(base, matrix, (FULL[0] + 20, FULL[1] + 20), flags=cv2.INTER_CUBIC)
        cv2.imwrite(str(folder / f"f{i:04d}.png"), np.clip(image[10:-10, 10:-10], 0, 255).astype(np.uint8))


def run(folder: Path, name: str, n_frames: int, jobs: int) -> float:
    """Frames per second of the frame loop alone."""
    source = open_source(folder, roi=ROI, fps=30.0)
    mask = np.zeros((ROI.height, ROI.width), bool)
    mask[100:300, 50:750] = True
    poi_xy = np.stack(np.nonzero(mask)[::-1], axis=1)[::4].astype(np.int32)
    if registry.kinds()[name] == "sparse":
        tracks = track_sparse(source, registry.get_method(name), mask, max_frames=n_frames)
    else:
        tracks = track_dense(source, lambda: registry.get_method(name), poi_xy, jobs=jobs, max_frames=n_frames)
    return tracks.timings_s["frames_per_s"]


@contextlib.contextmanager
def one_thread_per_job() -> Iterator[None]:
    import numba

    before = cv2.getNumThreads(), numba.get_num_threads()
    cv2.setNumThreads(1)
    numba.set_num_threads(1)
    try:
        yield
    finally:
        cv2.setNumThreads(before[0])
        numba.set_num_threads(before[1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=12)
    parser.add_argument("--methods", help="comma-separated (default: all registered)")
    args = parser.parse_args()
    registered = registry.available()  # also loads the built-in methods
    names = args.methods.split(",") if args.methods else registered
    unknown = sorted(set(names) - set(registered))
    if unknown:
        parser.error(f"unknown method(s) {', '.join(unknown)}; available: {', '.join(registered)}")
    print(f"ROI {ROI.width}x{ROI.height} of a {FULL[0]}x{FULL[1]} image folder; "
          f"{os.cpu_count()} CPUs; OpenCV {cv2.__version__} ({cv2.getNumThreads()} threads by default)")
    print(f"{'method':<16} {'frames':>6} {'fps default':>12} {'fps jobs=1':>11} {'fps jobs=2':>11} {'speed-up':>9}")
    print(f"{'':<16} {'':>6} {'threads':>12} {'1 thread':>11} {'1 thr/job':>11} {'2 vs 1':>9}")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        make_frames(folder, max(args.frames, 2))
        for name in names:
            n_frames = min(args.frames, SLOW.get(name, args.frames))
            run(folder, name, 2, 1)  # warm-up: numba compiles, caches fill
            default = run(folder, name, n_frames, 1)
            if registry.kinds()[name] == "sparse":
                print(f"{name:<16} {n_frames:>6} {default:>12.2f} {'(sequential: frame to frame)':>33}", flush=True)
                continue
            with one_thread_per_job():
                one = run(folder, name, n_frames, 1)
                two = run(folder, name, n_frames, 2)
            print(f"{name:<16} {n_frames:>6} {default:>12.2f} {one:>11.2f} {two:>11.2f} {two / one:>8.2f}x",
                  flush=True)


if __name__ == "__main__":
    main()
