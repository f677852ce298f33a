"""Peak memory of `refflow track` against clip length: it must not grow with the clip.

Writes synthetic MJPG clips (800x400, a textured plane moving sub-pixel) of several
lengths and runs `refflow track` on each in a fresh process with every pixel of a
800x400 mask as a POI (320 000 POIs: 2.5 MB of per-POI tracks per frame), then
prints each run's peak resident memory (ru_maxrss). Asserts nothing.

    .venv/bin/python benchmarks/bench_memory.py [--frames 100,300,900] [--method dis]
    .venv/bin/python benchmarks/bench_memory.py --size 3840x2160 --rect 400,880,3000,400 --field --frames 30,90

``--size`` and ``--rect`` set the clip and the POIs; ``--field`` writes the whole displacement
field too (``track --field``, streamed frame by frame), and its size.

``--pythonpath DIR`` runs another checkout's ``flow`` (e.g. an older version,
extracted with ``git archive``) for comparison.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

SIZE = (800, 400)
CHILD = """
import resource, sys
import flow
print(f"flow_from={flow.__file__}", file=sys.stderr)
from flow.cli import main
code = main(sys.argv[1:])
print(f"maxrss_kib={resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}", file=sys.stderr)
sys.exit(code)
"""


def make_clip(path: Path, n_frames: int, size: tuple[int, int] = SIZE) -> None:
    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.integers(0, 256, (size[1] + 20, size[0] + 20)).astype(np.float32), (0, 0), 2.0)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, size, True)
    for i in range(n_frames):
        shift = 1.5 * np.sin(2 * np.pi * i / 30)
        matrix = np.float32([[1, 0, shift], [0, 1, 0]])
        image = cv2.warpAffine(base, matrix, (size[0] + 20, size[1] + 20), flags=cv2.INTER_CUBIC)
        grey = np.clip(image[10:-10, 10:-10], 0, 255).astype(np.uint8)
        writer.write(cv2.cvtColor(grey, cv2.COLOR_GRAY2BGR))
    writer.release()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", default="100,300,900", help="comma-separated clip lengths")
    parser.add_argument("--method", default="dis")
    parser.add_argument("--pythonpath", help="run the flow package found here instead")
    parser.add_argument("--size", default=f"{SIZE[0]}x{SIZE[1]}", help="clip size WxH")
    parser.add_argument("--rect", help="POI rectangle X,Y,W,H (default: the whole frame)")
    parser.add_argument("--field", action="store_true", help="also write the whole field (track --field)")
    args = parser.parse_args()
    size = tuple(int(v) for v in args.size.split("x"))
    rect = args.rect or f"0,0,{size[0]},{size[1]}"
    n_points = int(np.prod([int(v) for v in rect.split(",")[2:]]))
    env = dict(os.environ)
    root = Path(__file__).resolve().parents[1]
    env["PYTHONPATH"] = os.pathsep.join(p for p in (args.pythonpath, str(root)) if p)
    print(f"{'frames':>6} {'POIs':>7} {'tracks MB':>10} {'peak RSS MB':>12} {'wall s':>7}"
          + (f" {'field MB':>9}" if args.field else ""))
    with tempfile.TemporaryDirectory(dir=root) as tmp:
        folder = Path(tmp)
        for n_frames in (int(v) for v in args.frames.split(",")):
            clip = folder / f"clip{n_frames}.avi"
            make_clip(clip, n_frames, size)
            field = folder / f"out{n_frames}.h5"
            argv = [sys.executable, "-c", CHILD, "track", str(clip), "--rect", rect,
                    "--method", args.method, "--out", str(folder / f"out{n_frames}.csv"), "--no-progress"]
            if args.field:
                argv += ["--field", str(field)]
            if args.method == "dis":
                argv += ["--preset", "ultrafast"]
            started = time.perf_counter()
            # cwd: `python -c` puts the working directory first on sys.path
            result = subprocess.run(argv, capture_output=True, text=True, env=env, cwd=folder)
            wall = time.perf_counter() - started
            if result.returncode != 0:
                print(f"{n_frames:>6} failed (exit {result.returncode}): {result.stderr.strip()[-300:]}")
                continue
            maxrss_kib = int(result.stderr.rsplit("maxrss_kib=", 1)[1].split()[0])
            source = result.stderr.split("flow_from=", 1)[1].split()[0]
            if args.pythonpath and not source.startswith(str(Path(args.pythonpath).resolve())):
                raise SystemExit(f"the run used {source}, not the flow under {args.pythonpath}")
            print(f"{n_frames:>6} {n_points:>7} {2 * 4 * n_frames * n_points / 1e6:>10.0f} "
                  f"{maxrss_kib / 1024:>12.0f} {wall:>7.1f}"
                  + (f" {field.stat().st_size / 1e6:>9.0f}" if args.field else ""), flush=True)
            clip.unlink()
            field.unlink(missing_ok=True)


if __name__ == "__main__":
    main()
