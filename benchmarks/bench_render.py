"""Render throughput and memory of the synthetic phone camera.

Usage: ``python benchmarks/bench_render.py [--runs 3] [--frames 12] [--skip-4k]``

Prints frames/s (median of ``--runs`` runs) for the default ~800x400 crop and
for full 4K frames, the split of a frame's time (a whole-window sub-frame
render, a strip sub-frame render, remap, sensor, auto-exposure meter, truth),
and peak resident memory of `render_clip` subprocesses for crop clips of
increasing length with a verdict: frames stream into ffmpeg and the truth into
its files, so memory should not grow with the clip. Software EGL (Mesa) on a
shared machine: read the numbers as this machine's, not the method's.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def _seconds(fn, repeat: int = 3) -> float:
    """Median wall time of ``fn()`` over ``repeat`` calls."""
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def throughput(full_frame: bool, frames: int, runs: int) -> dict:
    from sim.camera import sensor_readout
    from sim.render import BeamRenderer
    from sim.scene import BeamShapes, synthetic_shapes
    shapes = BeamShapes(**synthetic_shapes(duration_s=2.0))
    t0 = time.perf_counter()
    r = BeamRenderer({"seed": 0}, shapes, full_frame=full_frame)
    setup = time.perf_counter() - t0
    try:
        gains = r.gains(frames)
        r.frame(0, gains[0])  # warm-up (shader compile, texture upload, background)
        rates = []
        for _ in range(runs):
            t0 = time.perf_counter()
            for i in range(frames):
                r.frame(i, gains[i])
            rates.append(frames / (time.perf_counter() - t0))
        # where a frame's time goes
        und = r.render_undistorted(0.01)
        split = {"whole_subframe_s": _seconds(lambda: r.render_undistorted(0.01)),
                 "remap_s": _seconds(lambda: r.plan.apply(und)),
                 "meter_s": _seconds(lambda: r.meter(1)),
                 "truth_s": _seconds(lambda: r.truth.frame(1))}
        if r.strip is not None and r.strip[1] > r.strip[0]:
            split["strip_subframe_s"] = _seconds(lambda: r.render_window(r.strip_window(), 0.01))
            split["strip_px"] = r.strip[1] - r.strip[0]
        lin = r.frame_linear(1)
        split["sensor_s"] = _seconds(lambda: sensor_readout(lin, gains[1], r.view.cam_cfg, seed=0,
                                                            frame=1, window=r.view.window))
    finally:
        r.close()
    return {"size": f"{r.view.window.width}x{r.view.window.height}", "fps_median": float(np.median(rates)),
            "fps_runs": [round(x, 3) for x in rates], "setup_s": setup,
            "subframes": r.view.cam_cfg.motion_blur_subframes, **split}


def peak_memory(frames: int, tmp: Path) -> dict:
    """Peak RSS (MiB) of a CLI render of ``frames`` frames, in a fresh process."""
    shapes = tmp / "shapes.npz"
    if not shapes.exists():
        subprocess.run([sys.executable, "-m", "sim.render_cli", "synthetic-shapes", "--out",
                        str(shapes), "--duration-s", "12"], check=True, cwd=ROOT,
                       capture_output=True)
    # VmHWM, not ru_maxrss: Linux carries ru_maxrss over fork+exec, so a child
    # of this (4K-sized) process would report the parent's peak
    code = ("import sys; from sim.render_cli import main; "
            f"rc = main(['--shapes', r'{shapes}', '--out-dir', r'{tmp / f'clip{frames}'}', "
            f"'--max-frames', '{frames}', '--no-progress']); "
            "hwm = open('/proc/self/status').read().split('VmHWM:')[1].split()[0]; "
            "print('PEAK', hwm); sys.exit(rc)")
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                         check=True)
    wall = time.perf_counter() - t0
    peak_kib = int([ln for ln in out.stdout.splitlines() if ln.startswith("PEAK")][0].split()[1])
    return {"frames": frames, "peak_rss_mib": peak_kib / 1024, "wall_s": wall}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--frames", type=int, default=12)
    ap.add_argument("--frames-4k", type=int, default=3)
    ap.add_argument("--skip-4k", action="store_true")
    ap.add_argument("--memory-frames", default="30,120,360")
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
    results = {"cpu_count": os.cpu_count()}
    views = [("crop", False, args.frames, 15)] + ([] if args.skip_4k else
                                                 [("full", True, args.frames_4k, 2)])
    for name, full_frame, frames, target in views:
        res = throughput(full_frame, frames, args.runs)
        results[name] = res
        ms = {k: f"{v * 1e3:.1f} ms" for k, v in res.items() if k.endswith("_s") and k != "setup_s"}
        print(f"{name} {res['size']}: {res['fps_median']:.2f} frames/s (median of {args.runs}; "
              f"runs {res['fps_runs']}; target >= {target}: "
              f"{'met' if res['fps_median'] >= target else 'MISSED'}); {res['subframes']} "
              f"sub-frames; strip {res.get('strip_px', '-')} px wide; {ms}; "
              f"set-up {res['setup_s']:.1f} s")
    if "full" in results:
        print(f"ratio crop/full frames per second: "
              f"{results['crop']['fps_median'] / results['full']['fps_median']:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        mem = [peak_memory(int(n), Path(tmp)) for n in args.memory_frames.split(",")]
    results["memory"] = mem
    for m in mem:
        print(f"clip of {m['frames']:4d} crop frames: peak RSS {m['peak_rss_mib']:.0f} MiB, "
              f"wall {m['wall_s']:.1f} s")
    growth = mem[-1]["peak_rss_mib"] - mem[0]["peak_rss_mib"]
    # flat: the longest clip peaks within 16 MiB or 5 % of the shortest's peak
    flat = growth <= max(16.0, 0.05 * mem[0]["peak_rss_mib"])
    per_frame_kib = 1024 * growth / max(mem[-1]["frames"] - mem[0]["frames"], 1)
    results["memory_verdict"] = {"flat": bool(flat), "growth_mib": growth,
                                 "growth_kib_per_frame": per_frame_kib}
    print(f"memory verdict: {'FLAT' if flat else 'GROWS'} in clip length "
          f"({growth:+.1f} MiB from {mem[0]['frames']} to {mem[-1]['frames']} frames, "
          f"{per_frame_kib:+.1f} KiB/frame)")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
