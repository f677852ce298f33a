"""The painted bar at the edges of its kind: the default against the dense baselines on the
tests' faint bar (``tests/unit/_lowtex_clip.py``: exact truth) drawn with one parameter pushed
past the bench's clips, several draws of each.

The bench's painted-bar clips (``../shared/bench/clips``) vary the bar's width, paint, axis,
motion and codec within a band; the project is judged on other clips of that kind. Each
variant here changes the tests' default bar (32 px wide, paint of 2 grey levels, member grey
149 over a wall of 111 +- 35, +-4 px at 4.3 Hz, 90 frames of 240x160 at 60 fps, H.264 CRF 18)
in one or two ways (see VARIANTS). Each method runs ``refflow track CLIP --mask MASK --method
M`` with its defaults; a row gives the default's RMSE, slope and valid share, the best other
method's RMSE and slope, their RMSE ratio and the verdict of issue 30's rule (RMSE within max(1.1 times the
best other's, 0.05 px), slope within 0.015 of 1).

    .venv/bin/python benchmarks/bench_bar_extremes.py [--variants wide,blur] [--seeds 401,402]
        [--methods deepflow,dis,deepflow-dense] [--out results/bench_bar_extremes.md]

Prints a Markdown table; asserts nothing.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_scene_kinds import run  # noqa: E402  (one run of the CLI, scored)

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests" / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402  (the tests' generator)

# name: (what it changes, make_clip's arguments, CRF)
VARIANTS: dict[str, tuple[str, dict, int]] = {
    "wide": ("an 80 px bar, mask 10 px inside, +-3 px", dict(bar_width=80, mask_margin=10, amplitude=3.0), 18),
    "thin": ("a 12 px bar, mask 3 px inside", dict(bar_width=12, mask_margin=3), 18),
    "low-contrast": ("member grey 118 over the wall's 111 +- 35", dict(member_grey=118.0), 18),
    "dark": ("member grey 40", dict(member_grey=40.0), 18),
    "bright-wall": ("a bright wall (200 +- 20), member grey 120", dict(wall_mean=200.0, wall_std=20.0, member_grey=120.0), 18),
    "plain-wall": ("a nearly plain wall (+- 8)", dict(wall_std=8.0), 18),
    "strong-paint": ("paint of 8 grey levels", dict(texture=8.0), 18),
    "noisy": ("sensor noise 4 grey levels, CRF 23", dict(noise=4.0), 23),
    "crf28": ("paint of 1 grey level, CRF 28", dict(texture=1.0), 28),
    "blur": ("the lens's blur 1.5 px (Gaussian sigma)", dict(blur_px=1.5), 18),
    "fast": ("+-2 px at 12 Hz", dict(frequency_hz=12.0, amplitude=2.0), 18),
    "large": ("+-10 px", dict(amplitude=10.0), 18),
    "small": ("+-0.6 px", dict(amplitude=0.6), 18),
    "bent-y": ("a horizontal bar moving along y, the motion 30 % larger at one end", dict(axis="y", bend=0.3), 18),
}
METHODS = ("deepflow", "dis", "deepflow-dense")
SEEDS = (401, 402, 403)


def verdict(ours: dict, best: float) -> str:
    """Issue 30's rule for one clip: RMSE and slope."""
    if "rmse" not in ours:
        return "failed"
    near = ours["rmse"] <= max(1.1 * best, 0.05)
    scale = abs(ours["slope"] - 1.0) <= 0.015
    return "met" if near and scale else ("slope" if near else "**loss**")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--seeds", default=",".join(map(str, SEEDS)))
    parser.add_argument("--methods", default=",".join(METHODS))
    parser.add_argument("--out", help="write the Markdown table here too")
    args = parser.parse_args()
    methods = args.methods.split(",")
    if methods[0] != "deepflow":
        parser.error("--methods must start with deepflow (the default is what the rows compare)")
    lines = ["| variant | seed | deepflow RMSE px / slope / valid | best other: RMSE px / slope | ratio | rule | deepflow's readings |",
             "|---|---|---|---|---|---|---|"]
    with tempfile.TemporaryDirectory() as tmp:
        for name in args.variants.split(","):
            _, kwargs, crf = VARIANTS[name]
            for seed in map(int, args.seeds.split(",")):
                folder = Path(tmp) / f"{name}-{seed}"
                folder.mkdir()
                clip = make_clip(seed=seed, **kwargs)
                encode(clip, folder / "clip.mp4", crf=crf)
                cv2.imwrite(str(folder / "mask.png"), clip.mask.astype(np.uint8) * 255)
                results = {m: run(folder, clip, m) for m in methods}
                ours = results["deepflow"]
                others = {m: r["rmse"] for m, r in results.items() if m != "deepflow" and "rmse" in r}
                best_name = min(others, key=others.get) if others else "-"
                best = others.get(best_name, np.nan)
                best_slope = results[best_name]["slope"] if best_name in results else np.nan
                if "rmse" in ours:
                    cell = f"{ours['rmse']:.3f} / {ours['slope']:.3f} / {ours['valid']:.2f}"
                    ratio = f"{ours['rmse'] / best:.2f}" if np.isfinite(best) else "-"
                else:
                    cell, ratio = f"failed: {ours['error']}", "-"
                lines.append(f"| {name} | {seed} | {cell} | `{best_name}` {best:.3f} / {best_slope:.3f} | {ratio} | "
                             f"{verdict(ours, best)} | {ours.get('models', '')} |")
                print(lines[-1], flush=True)
    table = "\n".join(["Variants (each changes the tests' default bar):", ""]
                      + [f"- `{n}`: {VARIANTS[n][0]}" for n in args.variants.split(",")] + ["", *lines])
    print("\n" + table)
    if args.out:
        Path(args.out).write_text(table + "\n")


if __name__ == "__main__":
    main()
