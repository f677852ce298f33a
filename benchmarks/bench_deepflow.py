"""Per-frame time and peak memory: refflow ``deepflow`` vs OpenCV's DeepFlow.

Run ``python benchmarks/bench_deepflow.py`` (add ``--frames N``). Each method
runs in its own subprocess on the same synthetic 800x400 and 512x256 pairs
(textured scene, smooth deformation of a few pixels, as in a structural ROI)
for the peak memory (the subprocess's ``ru_maxrss``; the resident size after
imports is printed as the baseline). The times come from one process that
calls both methods alternately, ``--frames`` times each, after a warm-up
call (numba compilation or cache load) timed separately: the ratio is that
of the fastest frames, and the median of the ratios of neighbouring calls is
printed beside it, as a check that other jobs on the machine did not skew it.

OpenCV's DeepFlow runs its variational part on all cores (``parallel_for_``;
on a 2-core machine about 1.8x faster than on one), ours on one core per
frame. So three comparisons are printed: OpenCV as it comes (all cores)
against ours on one core; both on one core (``cv2.setNumThreads(1)``), the
per-core cost of the two algorithms; and the throughput of the whole machine
when every core is busy, as ``refflow track --jobs N`` uses it: ours with one
frame per core at once, OpenCV both ways (its own threads on one frame at a
time, and one single-threaded frame per core), the better of the two kept.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SIZES = ((800, 400), (512, 256))


def _pair(width: int, height: int):
    import cv2
    import numpy as np

    rng = np.random.default_rng(0)
    img = np.zeros((height, width), np.float32)
    for sigma, amp in ((1.0, 0.5), (3.0, 1.0), (8.0, 1.0)):
        img += (
            amp
            * sigma
            * cv2.GaussianBlur(
                rng.standard_normal((height, width)).astype(np.float32), (0, 0), sigma
            )
        )
    img = np.clip(128 + 40 * (img - img.mean()) / img.std(), 0, 255).astype(np.float32)
    gx, gy = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    fx = 3.0 * np.sin(2 * np.pi * gy / height) + 1.5
    fy = 2.0 * np.cos(2 * np.pi * gx / width)
    current = cv2.remap(img, gx - fx, gy - fy, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)
    return img.astype(np.uint8), np.clip(current, 0, 255).astype(np.uint8)


def _maxrss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _worker(method: str, width: int, height: int, frames: int, preset: str = "default") -> dict:
    sys.path.insert(0, str(ROOT))
    import cv2

    reference, current = _pair(width, height)
    if method == "opencv":
        engine = cv2.optflow.createOptFlow_DeepFlow()

        def calc():
            return engine.calc(reference, current, None)
    else:
        import flow.methods.deepflow.method as deepflow_module

        engine = deepflow_module.DeepFlow(preset=preset)

        def calc():
            return engine.calc(reference, current)

    baseline = _maxrss_mb()
    t0 = time.perf_counter()
    calc()
    warmup = time.perf_counter() - t0
    times = []
    for _ in range(frames):
        t0 = time.perf_counter()
        calc()
        times.append(time.perf_counter() - t0)
    result = {
        "warmup_s": warmup,
        "frame_s": min(times),
        "frame_mean_s": sum(times) / len(times),
        "baseline_mb": baseline,
        "peak_mb": _maxrss_mb(),
    }
    if method == "ours":
        # Where the time goes: matching vs variational, one more frame.
        from flow.methods.deepflow.deepmatching import deep_matching, densify
        from flow.methods.deepflow.variational import refine

        t0 = time.perf_counter()
        grid = deep_matching(reference, current, engine._match)
        mflow, mweight = densify(grid, reference.shape, nearest=True)
        t1 = time.perf_counter()
        refine(
            reference,
            current,
            engine._var,
            match_flow=mflow,
            match_weight=mweight,
            workspace=engine._workspace,
        )
        t2 = time.perf_counter()
        result["matching_s"] = t1 - t0
        result["variational_s"] = t2 - t1
    return result


def _interleaved_times(
    width: int, height: int, frames: int, preset: str, opencv_threads: int | None = None
) -> dict:
    """Per-frame times of both methods measured alternately in this process.

    Alternating A, B, A, B and keeping each method's fastest frame makes the
    ratio robust to other jobs on a shared machine; the median ratio of each
    call of ours to the OpenCV call just before it is kept as a check.
    """
    sys.path.insert(0, str(ROOT))
    import cv2

    import flow.methods.deepflow.method as deepflow_module

    reference, current = _pair(width, height)
    threads_before = cv2.getNumThreads()
    if opencv_threads is not None:
        cv2.setNumThreads(opencv_threads)
    opencv = cv2.optflow.createOptFlow_DeepFlow()
    ours = deepflow_module.DeepFlow(preset=preset)
    t0 = time.perf_counter()
    ours.calc(reference, current)
    warmup = time.perf_counter() - t0
    opencv.calc(reference, current, None)
    times: dict[str, list[float]] = {"opencv": [], "ours": []}
    for _ in range(frames):
        t0 = time.perf_counter()
        opencv.calc(reference, current, None)
        times["opencv"].append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        ours.calc(reference, current)
        times["ours"].append(time.perf_counter() - t0)
    cv2.setNumThreads(threads_before)
    pairs = sorted(b / a for a, b in zip(times["opencv"], times["ours"], strict=True))
    return {
        "opencv": min(times["opencv"]),
        "ours": min(times["ours"]),
        "median_pair_ratio": pairs[len(pairs) // 2],
        "warmup_s": warmup,
    }


def _throughput(
    method: str, width: int, height: int, frames: int, preset: str, cores: int, opencv_threads: int
) -> float:
    """Seconds per frame with ``cores`` frames computed at once (one thread each).

    Every thread has its own engine and computes ``frames`` frames; the time
    is that of the whole batch over the number of frames, best of two batches.
    """
    sys.path.insert(0, str(ROOT))
    from concurrent.futures import ThreadPoolExecutor

    import cv2

    import flow.methods.deepflow.method as deepflow_module

    reference, current = _pair(width, height)
    threads_before = cv2.getNumThreads()
    cv2.setNumThreads(opencv_threads)
    if method == "opencv":
        engines = [cv2.optflow.createOptFlow_DeepFlow() for _ in range(cores)]
        calls = [lambda e=e: e.calc(reference, current, None) for e in engines]
    else:
        engines = [deepflow_module.DeepFlow(preset=preset) for _ in range(cores)]
        calls = [lambda e=e: e.calc(reference, current) for e in engines]
    for call in calls:  # warm-up (numba cache load, buffers)
        call()

    def run(call):
        for _ in range(frames):
            call()

    best = float("inf")
    with ThreadPoolExecutor(max_workers=cores) as pool:
        for _ in range(2):
            t0 = time.perf_counter()
            list(pool.map(run, calls))
            best = min(best, (time.perf_counter() - t0) / (frames * cores))
    cv2.setNumThreads(threads_before)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=7)
    parser.add_argument(
        "--preset", default="default", help="preset of refflow deepflow (default, fast)"
    )
    parser.add_argument("--worker", nargs=3, metavar=("METHOD", "W", "H"))
    args = parser.parse_args()
    if args.worker:
        method, width, height = args.worker[0], int(args.worker[1]), int(args.worker[2])
        print(json.dumps(_worker(method, width, height, args.frames, args.preset)))
        return
    # Memory first, in fresh subprocesses: a child forked from a big parent
    # inherits the parent's RSS high-water mark in ru_maxrss.
    results = {}
    for width, height in SIZES:
        res = results[(width, height)] = {}
        for method in ("opencv", "ours"):
            out = subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--frames",
                    str(args.frames),
                    "--preset",
                    args.preset,
                    "--worker",
                    method,
                    str(width),
                    str(height),
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            res[method] = json.loads(out.stdout.strip().splitlines()[-1])
    for width, height in SIZES:
        ours, cv = results[(width, height)]["ours"], results[(width, height)]["opencv"]
        both = _interleaved_times(width, height, args.frames, args.preset)
        print(
            f"{width}x{height}: OpenCV DeepFlow {both['opencv']:.3f} s/frame, "
            f"peak RSS {cv['peak_mb']:.0f} MB (after imports {cv['baseline_mb']:.0f} MB)"
        )
        print(
            f"{width}x{height}: refflow deepflow [{args.preset}] {both['ours']:.3f} s/frame "
            f"(one frame split: matching {ours['matching_s']:.3f} s, "
            f"variational {ours['variational_s']:.3f} s), "
            f"warm-up {both['warmup_s']:.2f} s (first call in a fresh process "
            f"{ours['warmup_s']:.2f} s), peak RSS {ours['peak_mb']:.0f} MB "
            f"(after imports {ours['baseline_mb']:.0f} MB)"
        )
        print(
            f"{width}x{height}: time ratio ours/OpenCV = {both['ours'] / both['opencv']:.2f} "
            f"(interleaved, best of {args.frames}; median of neighbouring calls "
            f"{both['median_pair_ratio']:.2f}); peak memory ratio = "
            f"{ours['peak_mb'] / cv['peak_mb']:.2f}"
        )
        one = _interleaved_times(width, height, args.frames, args.preset, opencv_threads=1)
        print(
            f"{width}x{height}: both on one core: OpenCV {one['opencv']:.3f} s/frame, "
            f"ours {one['ours']:.3f} s/frame, ratio ours/OpenCV = "
            f"{one['ours'] / one['opencv']:.2f} (median of neighbouring calls "
            f"{one['median_pair_ratio']:.2f})"
        )
        cores = os.cpu_count() or 1
        if cores > 1:
            batch = max(2, args.frames // 2)
            ours_t = _throughput("ours", width, height, batch, args.preset, cores, 1)
            cv_own = _throughput("opencv", width, height, batch, args.preset, 1, cores)
            cv_par = _throughput("opencv", width, height, batch, args.preset, cores, 1)
            cv_best = min(cv_own, cv_par)
            print(
                f"{width}x{height}: all {cores} cores busy: ours {ours_t:.3f} s/frame "
                f"({cores} frames at once); OpenCV {cv_own:.3f} s/frame on its own threads, "
                f"{cv_par:.3f} s/frame with {cores} frames at once; ratio ours/OpenCV's "
                f"better = {ours_t / cv_best:.2f}"
            )


if __name__ == "__main__":
    main()
