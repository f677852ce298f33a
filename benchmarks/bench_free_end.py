"""A member measured through a mask drawn past its free end (a cantilever's tip) onto the wall.

The tests' faint bar (``tests/unit/_lowtex_clip.py``: 32 px wide, paint of about 2 grey levels
over a still, textured wall of the same range of greys, +-2 px across, exact truth, 60 frames,
H.264 CRF 18) ends at row 150 of a 240 x 200 frame, the wall below it. Its mask over the bar's
interior is drawn to the tip, then ``PAST`` px past it (and, last, 12 px past the tip and 6 px
past each long edge). Every method runs as a user runs it, ``refflow track CLIP --mask MASK
--mm-per-px 1``, and the bench's own scorer (``../shared/bench/score.py``) grades it against
the bar's motion, which the mask does not change.

    .venv/bin/python benchmarks/bench_free_end.py [--methods deepflow,dis] [--seeds 3,4,5]
        [--past 0,6,24] [--out results/bench_free_end.md]

Prints a Markdown table (and writes it with --out): RMSE px, slope and 2-sigma coverage per
seed, mask and method; asserts nothing. About 2 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).parent))
sys.path.insert(0, str(ROOT / "tests" / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402  (the tests' generator)
from bench_accuracy import method_table, publish, run_method, scored  # noqa: E402  (a sibling script)

TIP_ROW = 150
SIDE_PX = 12  # the last mask: this much wider on each side than the clip's own (6 px inside the edges)


def clip_folder(seed: int, folder: Path) -> tuple[Path, np.ndarray]:
    """A bench-like folder (clip.mp4, truth.csv, clip.json) of seed ``seed``'s clip; its own mask."""
    clip = make_clip(seed=seed, frames=60, amplitude=2.0, height=200, tip_row=TIP_ROW)
    folder.mkdir(parents=True)
    encode(clip, folder / "clip.mp4", crf=18)
    t = np.arange(len(clip.truth_px)) / clip.fps
    np.savetxt(folder / "truth.csv", np.column_stack([np.arange(len(t)), t, clip.truth_px, np.zeros_like(t)]),
               delimiter=",", header="frame,time_s,dx_px,dy_px", comments="", fmt=["%d", "%.6f", "%.6f", "%.6f"])
    (folder / "clip.json").write_text(json.dumps({"video": "clip.mp4", "mask": "mask.png", "fps": clip.fps,
                                                  "axis": "x", "occlusion_s": None, "jump_s": None}))
    return folder, clip.mask


def past_mask(mask: np.ndarray, past_px: int, side_px: int = 0) -> np.ndarray:
    """The clip's mask from its top row down to ``past_px`` beyond the tip, ``side_px`` wider on
    each side."""
    rows, cols = np.nonzero(mask.any(axis=1))[0], np.nonzero(mask.any(axis=0))[0]
    out = np.zeros(mask.shape, bool)
    out[rows.min():TIP_ROW + past_px, cols.min() - side_px:cols.max() + 1 + side_px] = True
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default="deepflow,dis", help="comma-separated (default: deepflow,dis)")
    parser.add_argument("--seeds", default="3,4,5", help="the clips' seeds (default: 3,4,5)")
    parser.add_argument("--past", default="0,6,24", help="px past the tip (default: 0,6,24; 12 px and the "
                        "long edges come last)")
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args(argv)
    methods = args.methods.split(",")
    masks = [(int(p), 0) for p in args.past.split(",")] + [(12, SIDE_PX)]
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            folder, own = clip_folder(seed, Path(tmp) / f"seed{seed}")
            for past, side in masks:
                path = folder / f"mask-{past}-{side}.png"
                cv2.imwrite(str(path), past_mask(own, past, side).astype(np.uint8) * 255)
                cells = [run_method(name, folder, {"mask": path.name}, folder / f"{past}-{side}-{name}.csv")
                         for name in methods]
                for name, r in zip(methods, cells, strict=True):
                    print(f"seed {seed} +{past:2d} px (sides {side}) {name:10s} {scored(r)}", file=sys.stderr, flush=True)
                rows.append(([str(seed), f"{past} px past the tip" + (f", {side - 6} px past each edge" if side else "")],
                             cells))
    return publish(method_table(["seed", "mask"], rows, methods), args.out)


if __name__ == "__main__":
    raise SystemExit(main())
