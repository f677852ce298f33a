"""Render throughput and memory of the synthetic phone camera.

Usage: ``python benchmarks/bench_render.py [--runs 3] [--frames 12] [--skip-4k]``

Prints frames/s (median of ``--runs`` runs) for the default ~800x400 crop and
for full 4K frames, the split of a crop frame's time, and peak resident memory
of `render_clip` subprocesses for clips of increasing length (frames stream
into ffmpeg, so memory should not grow with the clip). Software EGL (Mesa) on a
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


def throughput(full_frame: bool, frames: int, runs: int) -> dict:
    from sim.render import BeamRenderer
    from sim.scene import BeamShapes, synthetic_shapes
    shapes = BeamShapes(**synthetic_shapes(duration_s=2.0))
    t0 = time.perf_counter()
    r = BeamRenderer({"seed": 0}, shapes, full_frame=full_frame)
    setup = time.perf_counter() - t0
    try:
        gains = r.gains(frames)
        r.frame(0, gains[0])  # warm-up (shader compile, texture upload)
        rates = []
        for _ in range(runs):
            t0 = time.perf_counter()
            for i in range(frames):
                r.frame(i, gains[i])
            rates.append(frames / (time.perf_counter() - t0))
        # where a frame's time goes
        t0 = time.perf_counter()
        und = r.render_undistorted(0.01)
        t_render = time.perf_counter() - t0
        t0 = time.perf_counter()
        r.plan.apply(und)
        t_remap = time.perf_counter() - t0
        lin = r.frame_linear(1)
        from sim.camera import sensor_readout
        t0 = time.perf_counter()
        sensor_readout(lin, gains[1], r.cam_cfg, seed=0, frame=1, window=r.window)
        t_sensor = time.perf_counter() - t0
    finally:
        r.close()
    return {"size": f"{r.window.width}x{r.window.height}", "fps_median": float(np.median(rates)),
            "fps_runs": [round(x, 3) for x in rates], "setup_s": setup,
            "subframes": r.cam_cfg.motion_blur_subframes, "subframe_render_s": t_render,
            "remap_s": t_remap, "sensor_s": t_sensor}


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
    crop = throughput(False, args.frames, args.runs)
    results["crop"] = crop
    print(f"crop {crop['size']}: {crop['fps_median']:.2f} frames/s (median of {args.runs}; "
          f"runs {crop['fps_runs']}; target >= 15); per frame: {crop['subframes']} sub-frames x "
          f"{crop['subframe_render_s'] * 1e3:.1f} ms render, remap {crop['remap_s'] * 1e3:.1f} ms, "
          f"sensor {crop['sensor_s'] * 1e3:.1f} ms")
    if not args.skip_4k:
        full = throughput(True, args.frames_4k, args.runs)
        results["full"] = full
        print(f"full {full['size']}: {full['fps_median']:.3f} frames/s (median of {args.runs}; "
              f"target >= 2); sub-frame render {full['subframe_render_s']:.2f} s, "
              f"remap {full['remap_s']:.2f} s, sensor {full['sensor_s']:.2f} s, "
              f"set-up {full['setup_s']:.1f} s")
        print(f"ratio crop/full frames per second: {crop['fps_median'] / full['fps_median']:.1f}")
    with tempfile.TemporaryDirectory() as tmp:
        mem = [peak_memory(int(n), Path(tmp)) for n in args.memory_frames.split(",")]
    results["memory"] = mem
    for m in mem:
        print(f"clip of {m['frames']:4d} crop frames: peak RSS {m['peak_rss_mib']:.0f} MiB, "
              f"wall {m['wall_s']:.1f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(results, indent=2) + "\n")


if __name__ == "__main__":
    main()
