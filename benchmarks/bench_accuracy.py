"""Accuracy of every registered method with its defaults, on data this project did not make.

For each clip of ``../shared/bench/clips`` and ``../shared/bench/gen`` (independent clips with exact truth, see their
README) each method runs as a user runs it, ``refflow track CLIP --mask MASK --mm-per-px 1
--out ...`` and nothing else, and the bench's own scorer (``score.py``) grades the CSV. The
table adds what the scorer does not: the share of frames (outside the occlusion) whose error
is within two of the method's own ``sigma`` (the 2-sigma coverage; 95 % for an honest
Gaussian uncertainty), the time per frame from the run's sidecar, and per clip the physical
floor: the Cramer-Rao bound of a translation along the clip's axis from the reference frame's
gradients and the noise of the video (estimated from frame-to-frame differences of the static
background), over the mask's pixels (the member's interior) and over the member with its
outline (the mask grown to the member's edges, as ``deepflow`` grows it).

The Middlebury 2014 "Motorcycle" pair (scikit-image's ``data.stereo_motorcycle()``: its
disparity is the left image's, so the flow from the left image to the right is (-disparity, 0)
where the disparity is known; occluded pixels included) gives the dense methods' mean
end-point error on large displacements.

The DIC Challenge 1.0 Samples 3 (a speckle image shifted 0.0 ... 1.0 px in 0.1 px steps in x and
y) and 5 (0.0 and 0.1 px with the contrast and noise changed) from ``../shared/data/real`` run
through the CLI as an image folder (the reference first, ``--fps 1``) with a 400x400 mask in the
middle of the 512x512 images: RMSE of dx and dy over every frame against the shifts in the file
names, the largest error, and the 2-sigma coverage.

A method name may carry parameters, ``klt:use_mask=true`` (run as ``--method klt --param
use_mask=true``); by default every registered method runs, and ``klt`` once more with
``use_mask=true`` (KLT's features restricted to the mask, the fairest KLT on a textured region).

    .venv/bin/python benchmarks/bench_accuracy.py [--methods deepflow,dis] [--clips lowtex-wide]
        [--out results/bench_accuracy.md] [--json results/bench_accuracy.json] [--again]

With --json the numbers are kept as they come and a rerun skips what the file holds (unless
--again), so slow methods can run apart and one table shows them all.

Prints a Markdown table (and writes it with --out); asserts nothing.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench_dic_challenge import frames_folder, method_args  # noqa: E402  (a sibling script: the DIC images as one folder)

from flow.methods import registry  # noqa: E402
from flow.methods.deepflow.member import MemberParams, _grow  # noqa: E402

BENCH = ROOT.parent / "shared" / "bench"
REAL = ROOT.parent / "shared" / "data" / "real"
DIC_SAMPLES = {"Sample 3": "dic_challenge1_sample3", "Sample 5": "dic_challenge1_sample5"}
DIC_MASK_PX = 400
EXTRA_METHODS = ["klt:use_mask=true"]
REFFLOW = Path(sys.executable).with_name("refflow")


def read_clip(folder: Path) -> tuple[np.ndarray, dict, np.ndarray]:
    meta = json.loads((folder / "clip.json").read_text())
    truth = np.loadtxt(folder / "truth.csv", delimiter=",", skiprows=1)
    return truth, meta, cv2.imread(str(folder / meta.get("mask", "mask.png")), cv2.IMREAD_GRAYSCALE) > 127


def frames_of(path: Path, limit: int = 40) -> list[np.ndarray]:
    capture = cv2.VideoCapture(str(path))
    out = []
    while len(out) < limit:
        ok, frame = capture.read()
        if not ok:
            break
        out.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY).astype(np.float64))
    capture.release()
    return out


def cramer_rao(folder: Path, meta: dict, mask: np.ndarray) -> tuple[float, float]:
    """(interior, with outline) lower bounds (px) on the error of a translation along the axis."""
    frames = frames_of(folder / meta.get("video", "clip.mp4"))
    reference = frames[0]
    support, _, _ = _grow(reference.astype(np.float32), mask, MemberParams())
    # Static background, well clear of the member: its frame-to-frame change is the noise.
    clear = ~(cv2.dilate(support.astype(np.uint8), np.ones((41, 41), np.uint8)) > 0)
    diffs = [(b - a)[clear] for a, b in zip(frames[:-1], frames[1:], strict=False)]
    noise_var = float(np.median([np.var(d) for d in diffs])) / 2.0
    axis = 1 if meta.get("axis", "x") == "x" else 0
    gradient = np.gradient(reference, axis=axis)
    grown = cv2.dilate(support.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # the outline pixels too
    bounds = []
    for region in (mask, grown):
        information = float(np.sum(gradient[region] ** 2)) / max(noise_var, 1e-9)
        bounds.append(float(np.sqrt(1.0 / information)) if information > 0 else float("nan"))
    return bounds[0], bounds[1]


def run_method(method: str, folder: Path, meta: dict, out: Path) -> dict:
    video, mask = folder / meta.get("video", "clip.mp4"), folder / meta.get("mask", "mask.png")
    cmd = [str(REFFLOW), "track", str(video), "--mask", str(mask), "--mm-per-px", "1", *method_args(method),
           "--out", str(out), "--no-progress"]
    started = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    wall = time.perf_counter() - started
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
    sidecar = json.loads(out.with_suffix(".json").read_text())
    score = subprocess.run([sys.executable, str(BENCH / "score.py"), str(folder), str(out)],
                           capture_output=True, text=True, check=True)
    result = json.loads(score.stdout)
    quality = sidecar["quality"]
    if quality["frames_valid"] == 0:  # the tool flagged every frame; its readings are kept and scored
        typical, ratio = quality.get("typical_sigma_px"), (quality.get("motion") or {}).get("sigma_to_range")
        result["flagged"] = ("every frame flagged valid=0" + (f" (typical sigma {typical:.2f} px" if typical else "")
                             + (f", {ratio:.2f} of the motion's range)" if typical and ratio else ")" if typical else "")
                             + (f"; the kept readings: RMSE {result['rmse_px']:.3f} px" if "rmse_px" in result else ""))
    n_frames = sidecar["input"]["frames_measured"]
    result["s_per_frame"] = sidecar["timings"]["frames_s"] / max(n_frames, 1)
    result["wall_s"] = wall
    result["coverage_2sigma"] = coverage(folder, meta, out)
    return result


def coverage(folder: Path, meta: dict, out: Path) -> float:
    """Share of scored frames with |error| < 2 sigma (sigma_dx_px or sigma_dy_px; NaN without)."""
    truth = np.loadtxt(folder / "truth.csv", delimiter=",", skiprows=1)
    axis = meta.get("axis", "x")
    key, sigma_key, col = (("dx_px", "sigma_dx_px", 2) if axis == "x" else ("dy_px", "sigma_dy_px", 3))
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    if not rows or sigma_key not in rows[0]:
        return float("nan")
    measured = np.array([float(r[key]) for r in rows])
    sigma = np.array([float(r[sigma_key]) for r in rows])
    measured = measured - (measured[0] if np.isfinite(measured[0]) else 0.0)
    true = truth[: len(rows), col] - truth[0, col]
    t = truth[: len(rows), 1]
    inside = np.zeros(len(rows), bool)
    if meta.get("occlusion_s"):
        inside = (t >= meta["occlusion_s"][0]) & (t < meta["occlusion_s"][1])
    use = ~inside & np.isfinite(measured) & np.isfinite(sigma)
    use[0] = False  # the reference frame itself: zero by construction
    if not use.any():
        return float("nan")
    return float(np.mean(np.abs(measured[use] - true[use]) < 2 * sigma[use]))


def dic_sample(method: str, name: str, tmp: Path) -> dict:
    """One method on one DIC Challenge sample through the CLI: RMSE and largest error of dx and dy
    over every frame (the reference included, 0 by construction), 2-sigma coverage."""
    source = REAL / DIC_SAMPLES[name]
    with (source / "truth.csv").open() as handle:
        truth = {row["file"]: (float(row["u_px"]), float(row["v_px"])) for row in csv.DictReader(handle)}
    reference = next(source.glob("* Reference.tif"))
    folder = frames_folder(source, [reference.name, *sorted(truth)], tmp / f"{source.name}-frames")
    image = cv2.imread(str(reference), cv2.IMREAD_UNCHANGED)
    mask = np.zeros(image.shape[:2], np.uint8)
    top, left = (image.shape[0] - DIC_MASK_PX) // 2, (image.shape[1] - DIC_MASK_PX) // 2
    mask[top:top + DIC_MASK_PX, left:left + DIC_MASK_PX] = 255
    mask_path = tmp / f"{source.name}-mask.png"
    cv2.imwrite(str(mask_path), mask)
    out = tmp / f"{source.name}-{method.replace(':', '_')}.csv"
    cmd = [str(REFFLOW), "track", str(folder), "--mask", str(mask_path), "--fps", "1", "--mm-per-px", "1",
           *method_args(method), "--out", str(out), "--no-progress"]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}"}
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    true = np.array([(0.0, 0.0)] + [truth[f] for f in sorted(truth)])
    measured = np.array([(float(r["dx_px"]), float(r["dy_px"])) for r in rows])
    error = measured - true[: len(rows)]
    result = {"rmse_px": float(np.sqrt(np.nanmean(error ** 2))), "max_abs_err_px": float(np.nanmax(np.abs(error))),
              "measured_fraction": float(np.mean(np.isfinite(error).all(axis=1)))}
    if "sigma_dx_px" in rows[0]:
        sigma = np.array([(float(r["sigma_dx_px"]), float(r["sigma_dy_px"])) for r in rows])[1:]
        inside = np.isfinite(sigma) & np.isfinite(error[1:])
        result["coverage_2sigma"] = float(np.mean(np.abs(error[1:][inside]) < 2 * sigma[inside])) if inside.any() \
            else float("nan")
    return result


def motorcycle(methods: list[str]) -> dict[str, dict]:
    try:
        from skimage import data
    except ImportError:
        return {}
    left, right, disparity = data.stereo_motorcycle()
    # The disparity is the left image's (Middlebury's disp0): left pixel x shows what right
    # pixel x - d shows, so the flow from the left image to the right is (-d, 0).
    reference = cv2.cvtColor(left, cv2.COLOR_RGB2GRAY)
    current = cv2.cvtColor(right, cv2.COLOR_RGB2GRAY)
    known = np.isfinite(disparity)
    out = {}
    for name in methods:
        if ":" in name or registry.kinds()[name] != "dense":
            continue
        method = registry.get_method(name)
        started = time.perf_counter()
        flow = method.calc(reference, current)
        elapsed = time.perf_counter() - started
        error = np.hypot(flow[..., 0] + np.where(known, disparity, 0.0), flow[..., 1])[known]
        out[name] = {"epe_px": float(error.mean()), "s": elapsed}
    return out


def publish(text: str, out: str | None) -> int:
    """Print a benchmark's table, write it to ``out`` too where given; the exit status (0)."""
    print(text)
    if out:
        Path(out).write_text(text + "\n")
    return 0


def fmt(value: float | None, digits: int = 3) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def scored(result: dict) -> str:
    """One run's ``run_method`` result as "RMSE px / slope / 2-sigma coverage" (or its error)."""
    if "rmse_px" not in result:
        return result.get("error", "?")
    return f"{fmt(result.get('rmse_px'))} / {fmt(result.get('slope'), 4)} / {fmt(result.get('coverage_2sigma'), 2)}"


def method_table(keys: list[str], rows: list[tuple[list[str], list[dict]]], methods: list[str]) -> str:
    """A Markdown table: the ``keys`` columns, then each of the ``methods``' :func:`scored` run."""
    lines = ["| " + " | ".join(keys) + " | " + " | ".join(f"{m} RMSE px / slope / 2-sigma" for m in methods) + " |",
             "|" + "---|" * (len(keys) + len(methods))]
    lines += ["| " + " | ".join(values) + " | " + " | ".join(scored(c) for c in cells) + " |" for values, cells in rows]
    return "\n".join(lines)


def table(results: dict, floors: dict, moto: dict, methods: list[str], dic: dict | None = None) -> str:
    lines = ["| clip | floor px (interior / with outline) | method | RMSE px | slope | max err px | "
             "measured | 2-sigma coverage | post-recovery bias px | occluded flagged | s/frame |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for clip, per_method in results.items():
        floor = floors.get(clip, (float("nan"), float("nan")))
        best = min((r["rmse_px"] for r in per_method.values() if "rmse_px" in r and "flagged" not in r), default=None)
        for i, name in enumerate(methods):
            r = per_method.get(name, {"error": "not run"})
            head = (f"{clip} | {fmt(floor[0])} / {fmt(floor[1])}" if i == 0 else " | ")
            if "error" in r:
                lines.append(f"| {head} | {name} | failed: {r['error']} | | | | | | | |")
                continue
            if "flagged" in r:
                lines.append(f"| {head} | {name} | {r['flagged']} | | | 0.000 | | | | |")
                continue
            rmse = fmt(r["rmse_px"]) + (" **best**" if best is not None and r["rmse_px"] == best else "")
            lines.append(f"| {head} | {name} | {rmse} | {fmt(r['slope'], 4)} | {fmt(r['max_abs_err_px'])} | "
                         f"{fmt(r['measured_fraction'], 3)} | {fmt(r.get('coverage_2sigma'), 2)} | "
                         f"{fmt(r.get('post_recovery_bias_px'))} | {fmt(r.get('occluded_flagged_fraction'), 2)} | "
                         f"{fmt(r['s_per_frame'], 3)} |")
    if moto:
        lines += ["", "| Motorcycle (Middlebury 2014) | mean EPE px | s |", "|---|---|---|"]
        lines += [f"| {name} | {fmt(v['epe_px'], 2)} | {fmt(v['s'], 1)} |" for name, v in moto.items()]
    if dic:
        lines += ["", "| DIC Challenge (400x400 mask) | method | RMSE px (dx, dy, every frame) | max err px | "
                  "measured | 2-sigma coverage |", "|---|---|---|---|---|---|"]
        for sample, per_method in dic.items():
            best = min((r["rmse_px"] for r in per_method.values() if "rmse_px" in r), default=None)
            for i, (name, r) in enumerate(per_method.items()):
                head = sample if i == 0 else ""
                if "error" in r:
                    lines.append(f"| {head} | {name} | failed: {r['error']} | | | |")
                    continue
                rmse = fmt(r["rmse_px"], 4) + (" **best**" if r["rmse_px"] == best else "")
                lines.append(f"| {head} | {name} | {rmse} | {fmt(r['max_abs_err_px'], 4)} | "
                             f"{fmt(r['measured_fraction'], 2)} | {fmt(r.get('coverage_2sigma'), 2)} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", help="comma-separated (default: every registered method)")
    parser.add_argument("--clips", help="comma-separated clip names (default: all; none: only the DIC samples "
                        "and Motorcycle)")
    parser.add_argument("--no-motorcycle", action="store_true")
    parser.add_argument("--no-dic", action="store_true", help="skip the DIC Challenge Samples 3 and 5")
    parser.add_argument("--out", help="write the Markdown table here too")
    parser.add_argument("--json", help="write the numbers as JSON here; a rerun skips what it holds (unless "
                        "--again), so the methods can run apart and the table is made from all of them")
    parser.add_argument("--again", action="store_true", help="rerun the --methods given even where the JSON "
                        "holds them (the other methods' numbers are kept)")
    args = parser.parse_args(argv)
    methods = args.methods.split(",") if args.methods else registry.available() + EXTRA_METHODS
    # The painted bars of clips/ and the other scene kinds of gen/ (textured panel, whole moving
    # view, shaded column, bolted plate, rotating slab, tiny and large motion).
    folders = {p.name: p for sub in ("clips", "gen") if (BENCH / sub).is_dir()
               for p in sorted((BENCH / sub).iterdir()) if (p / "clip.json").is_file()}
    if not folders:
        print(f"no bench clips under {BENCH}", file=sys.stderr)
        return 2
    clips = [] if args.clips == "none" else args.clips.split(",") if args.clips else list(folders)
    store = Path(args.json) if args.json else None
    held = json.loads(store.read_text()) if store is not None and store.is_file() else {}
    results: dict[str, dict] = held.get("clips", {})
    floors: dict[str, tuple[float, float]] = held.get("floors", {})
    moto: dict[str, dict] = held.get("motorcycle", {})
    dic: dict[str, dict] = held.get("dic", {})

    def save() -> None:
        if store is not None:
            store.write_text(json.dumps({"clips": results, "floors": floors, "motorcycle": moto, "dic": dic},
                                        indent=1) + "\n")

    with tempfile.TemporaryDirectory() as tmp:
        for clip in clips:
            folder = folders[clip]
            _, meta, mask = read_clip(folder)
            if clip not in floors:
                floors[clip] = cramer_rao(folder, meta, mask)
            results.setdefault(clip, {})
            for name in methods:
                if name in results[clip] and not args.again:
                    continue
                results[clip][name] = run_method(name, folder, meta, Path(tmp) / f"{clip}-{name}.csv")
                save()
                r = results[clip][name]
                print(f"{clip:14s} {name:16s} " + (f"rmse {r['rmse_px']:.3f} slope {r['slope']:.4f} "
                      f"cov {r['coverage_2sigma']:.2f} {r['s_per_frame']:.3f} s/frame"
                      if "rmse_px" in r and "flagged" not in r else r.get("error") or r["flagged"]),
                      file=sys.stderr, flush=True)
        for sample in () if args.no_dic or not REAL.is_dir() else DIC_SAMPLES:
            dic.setdefault(sample, {})
            for name in methods:
                if name not in dic[sample] or args.again:
                    dic[sample][name] = dic_sample(name, sample, Path(tmp))
                    save()
    if not args.no_motorcycle:
        moto.update(motorcycle([name for name in methods if name not in moto or args.again]))
        save()
    shown = list(dict.fromkeys([*methods, *(name for per in results.values() for name in per)]))
    return publish(table({clip: results[clip] for clip in clips}, floors, moto, shown, dic), args.out)


if __name__ == "__main__":
    raise SystemExit(main())
