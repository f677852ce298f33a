"""A member measured through a mask drawn past its outlines, as a user's loose mask often is.

Each clip of ``../shared/bench/clips`` and ``../shared/bench/gen`` whose mask is a band (the
painted bars; the shaded column, the large swing) is run again with its mask widened across
the band by ``PAST`` px on each side, so that it reaches over the member's long outlines onto
the still wall behind (the bench's masks lie 3-12 px inside the bars' edges: 12 px reaches up
to 9 px past them, 20 px up to 17; lowtex-wide's +12 ends on its outlines). Every method runs as a user runs it, ``refflow track
CLIP --mask WIDE_MASK --mm-per-px 1``, and the bench's own scorer grades it against the clip's
truth: the member's motion, which the widened mask does not change (the truth is the mean over
the bar's interior, where every row moves alike or, for ``bend``, the same rows).

    .venv/bin/python benchmarks/bench_loose_mask.py [--methods deepflow,dis] [--past 12,20]
        [--clips bend,jump] [--out results/bench_loose_mask.md]

Prints a Markdown table (and writes it with --out): RMSE px, slope and 2-sigma coverage per
clip, widening and method; asserts nothing. bench_accuracy.py gives the same clips' numbers
with their own masks.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from bench_accuracy import BENCH, method_table, publish, read_clip, run_method, scored  # noqa: E402  (a sibling script)

# The mask is a band at least this many times longer than wide (the member's long outlines
# run along it).
BAND = 2.0


def widened(mask: np.ndarray, past_px: int) -> np.ndarray | None:
    """``mask`` grown by ``past_px`` on each side across its band (its shorter image axis);
    None where the mask is no band along an image axis."""
    ys, xs = np.nonzero(mask)
    tall, wide = int(np.ptp(ys)) + 1, int(np.ptp(xs)) + 1
    if max(tall, wide) < BAND * min(tall, wide):
        return None
    kernel = np.ones((1, 2 * past_px + 1) if tall > wide else (2 * past_px + 1, 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel) > 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default="deepflow,dis", help="comma-separated (default: deepflow,dis)")
    parser.add_argument("--past", default="12,20", help="px the mask is widened by on each side (default: 12,20)")
    parser.add_argument("--clips", help="comma-separated clip names (default: every clip whose mask is a band)")
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args(argv)
    methods = args.methods.split(",")
    widths = [int(p) for p in args.past.split(",")]
    folders = {p.name: p for sub in ("clips", "gen") if (BENCH / sub).is_dir()
               for p in sorted((BENCH / sub).iterdir()) if (p / "clip.json").is_file()}
    if not folders:
        print(f"no bench clips under {BENCH}", file=sys.stderr)
        return 2
    clips = args.clips.split(",") if args.clips else list(folders)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for clip in clips:
            _, meta, mask = read_clip(folders[clip])
            for past in widths:
                wide = widened(mask, past)
                if wide is None:
                    continue
                path = Path(tmp) / f"{clip}-{past}.png"
                cv2.imwrite(str(path), wide.astype(np.uint8) * 255)
                cells = [run_method(name, folders[clip], {**meta, "mask": str(path)}, Path(tmp) / f"{clip}-{past}-{name}.csv")
                         for name in methods]
                for name, r in zip(methods, cells, strict=True):
                    print(f"{clip:14s} +{past:2d} px {name:10s} {scored(r)}", file=sys.stderr, flush=True)
                rows.append(([clip, str(past)], cells))
    return publish(method_table(["clip", "past px"], rows, methods), args.out)


if __name__ == "__main__":
    raise SystemExit(main())
