"""The whole displacement field against the DIC Challenge's known fields (issue 33).

Every dense method runs as a user runs it, ``refflow track FRAMES --rect ... --field F.h5``
with its defaults, on the challenge's images (``../shared/data/real``, see its README), and
this script reads the field file:

* **Sample 14** (2048x589 speckle, u(x) a 0.1 px sine whose period shortens along x, levels
  L1, L3, L5; truth per column in ``command.csv``): the column means of u over rows 100-488
  (``--rect 20,100,2008,389``, columns 20-2027), their RMSE against the command, the gain
  (least-squares slope of measured on commanded) and the shortest period read within 10 %
  (each half period between the command's zero crossings has its own gain; the shortest
  full period from which on every longer one reads within 10 % of the command).
* **Sample 3** (512x512, uniform shifts 0.0-1.0 px in x and y): the bias of the CSV's
  reading (the mean over ``--rect 56,56,400,400``) against the shift, per shift; the table
  gives its RMS and largest value.
* **Sample 12** (real camera images of an open-hole CFRP coupon in tension, 400x1040, 11
  frames against the first, up to 12 px; no truth): agreement with DICe's own solution kept
  beside the images (ZNSSD, 27 px subsets every 35 px, 230 points; another code's answer, not
  the truth), over DICe's region of interest (a 313x977 rectangle less the hole, ``--mask``):
  per frame, the RMS of our field minus DICe's at its points and the mean of that difference,
  for u and v. The codes differ among themselves by their interpolants and shape functions
  (DICe's has no shear or rotation): a few thousandths of a pixel is agreement.
* **Sample 12's replica** (known fields): Sample 12's reference warped by the affine fit of
  DICe's solution of frames 1, 3, 5 and 11 (a quintic B-spline of the image), 1 grey level of
  fresh noise in every frame; per method the RMS and mean of its field's error over the region.
  Agreement with DICe is not accuracy: this says who reads such a field right.
* **Star 1, 2, 5** (DIC Challenge 2.0, v = 0.5 cos(2 pi (y - 250) / p(x)), p growing along x;
  ``--stars``): the amplitude read at each column (the field's v over rows 40-460 projected on
  the known cosine, 41-column running mean), the spatial resolution (the shortest period from
  which on the amplitude stays within 10 % of 0.5 px) and the noise floor (the standard
  deviation of v minus the fitted cosine where p > 100 px).

    .venv/bin/python benchmarks/bench_dic_challenge.py [--methods deepflow,dis] [--stars]
        [--samples sample14,sample3,sample12] [--json results/bench_dic_challenge.json]
        [--out results/bench_dic_challenge.md] [--figure results/figures/dic_challenge_sample14.png]
        [--figure12 results/figures/dic_challenge_sample12.png]

A method name may carry parameters, ``deepflow:alpha=0.3`` (run as ``--method deepflow --param
alpha=0.3``, one parameter per name since the names are comma-separated; as in bench_accuracy.py):
its rows follow the registered methods' under that name.

Each method's numbers are kept in the JSON as they come (a rerun skips what it holds, unless
--again), so the slow methods can run apart. Prints a Markdown table; asserts nothing.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import h5py
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "real"
REFFLOW = Path(sys.executable).with_name("refflow")
DENSE = ("deepflow", "deepflow-dense", "deepmatching", "deepflow-opencv", "dis", "farneback", "tvl1")

S14 = DATA / "dic_challenge1_sample14"
S14_FRAMES = ("Sample14 Reference.tif", "Sample14 L1 Amp0.1b.tif", "Sample14 L3 Amp0.1b.tif",
              "Sample14 L5 Amp0.1b.tif")
S14_RECT = "20,100,2008,389"
S14_LEVELS = ("L1", "L3", "L5")
S3 = DATA / "dic_challenge1_sample3"
S3_RECT = "56,56,400,400"
S12 = DATA / "dic_challenge1_sample12_oht_cfrp"
S12_FRAMES = tuple(f"oht_cfrp_{k:02d}.tiff" for k in range(12))
# DICe's region of interest (its subset_file.dat): a rectangle less the hole.
S12_RECTANGLE = (195.0, 517.0, 313.0, 977.0)  # centre x, y, width, height (px)
S12_HOLE = (194.0, 543.0, 51.0)  # centre x, y, radius (px)
STARS = {
    "star1": (DATA / "dic_challenge2_star1", ("DIC_Challenge_Wave_Reference_NoiseFree.tif",
                                              "DIC_Challenge_Wave_Deformed_NoiseFree.tif"),
              lambda x: 10 + 140 * (x + 1) / 2000),
    "star2": (DATA / "dic_challenge2_star2", ("DIC_Challenge_Wave_Reference_Noisy.tif",
                                              "DIC_Challenge_Wave_Deformed_Noisy.tif"),
              lambda x: 10 + 140 * (x + 1) / 2000),
    "star5": (DATA / "dic_challenge2_star5", ("DIC_Challenge_Star_Noise_Ref.tiff", "DIC_Challenge_Star_Noise_Def.tiff"),
              lambda x: 10 + 290 * x / 4000),
}
WITHIN = 0.10  # "read within 10 %"
STAR_CURVE_STEP = 4  # columns between the points of a Star's amplitude curve kept in the JSON


def frames_folder(folder: Path, names: tuple[str, ...] | list[str], into: Path) -> Path:
    """An image folder whose sorted names put the reference first (links to the originals)."""
    into.mkdir(parents=True, exist_ok=True)
    for k, name in enumerate(names):
        link = into / f"f{k:03d}{Path(name).suffix}"
        if not link.exists():
            link.symlink_to(folder / name)
    return into


# ``refflow track --jobs`` (None: its default, the cores this process may use); --jobs sets it.
JOBS: int | None = None


def method_args(spec: str) -> list[str]:
    """``--method NAME [--param KEY=VALUE ...]`` of ``NAME[:KEY=VALUE,...]``."""
    name, _, params = spec.partition(":")
    args = ["--method", name]
    for pair in filter(None, params.split(",")):
        args += ["--param", pair]
    return args


def track(frames: Path, method: str, rect: str | None, out: Path, *, mask: Path | None = None) -> dict:
    """``refflow track`` with the method's defaults over ``rect`` (or ``mask``); the field file
    and the run's timings."""
    region = ["--rect", rect] if mask is None else ["--mask", str(mask)]
    cmd = [str(REFFLOW), "track", str(frames), "--fps", "1", *region, *method_args(method), "--no-progress",
           "--out", str(out.with_suffix(".csv")), "--field", str(out.with_suffix(".h5"))]
    if JOBS is not None:
        cmd += ["--jobs", str(JOBS)]
    started = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise RuntimeError(proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit {proc.returncode}")
    sidecar = json.loads(out.with_suffix(".json").read_text())
    timings = sidecar["timings"]
    models = {k: timings[k] for k in timings
              if k in ("affine_readings", "outline_readings", "dense_readings") or k.startswith("field_window_")}
    return {"wall_s": time.perf_counter() - started, "models": models}


def gain_of(measured: np.ndarray, truth: np.ndarray) -> float:
    return float(np.dot(measured, truth) / np.dot(truth, truth))


def shortest_period_within(measured: np.ndarray, truth: np.ndarray, *, within: float = WITHIN) -> float:
    """The shortest full period (px) from which on every longer half period of the command
    reads within ``within`` of it (its own gain, least squares); NaN when none does."""
    crossings = np.flatnonzero(np.diff(np.signbit(truth)))
    segments = []
    for a, b in zip(crossings[:-1], crossings[1:], strict=True):
        part = slice(a + 1, b + 1)
        if np.abs(truth[part]).max() > 0:
            segments.append((2.0 * (b - a), gain_of(measured[part], truth[part])))
    segments.sort(key=lambda s: -s[0])
    shortest = float("nan")
    for period, gain in segments:
        if abs(gain - 1) > within:
            break
        shortest = period
    return shortest


def sample14(method: str, work: Path) -> dict:
    frames = frames_folder(S14, S14_FRAMES, work / "s14")
    out = work / f"s14_{method}"
    run = track(frames, method, S14_RECT, out)
    command = np.loadtxt(S14 / "command.csv", delimiter=",")
    columns = {"L1": 1, "L3": 3, "L5": 5}
    levels = {}
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        x = f["x_px"][()].astype(int)
        for k, level in enumerate(S14_LEVELS, start=1):
            measured = np.nanmean(f["u_px"][k].astype(np.float64), axis=0)
            truth = command[x, columns[level]]
            levels[level] = {"rmse_px": float(np.sqrt(np.mean((measured - truth) ** 2))),
                             "gain": gain_of(measured, truth),
                             "shortest_period_px": shortest_period_within(measured, truth),
                             "column_mean_u_px": [round(float(m), 5) for m in measured],
                             **pixel_sigma(f, k, f["u_px"][k] - truth[None, :], f["v_px"][k])}
        levels["x_px"] = x.tolist()
    return {**run, **levels}


def pixel_sigma(f, k: int, error_u: np.ndarray, error_v: np.ndarray, where: np.ndarray | None = None) -> dict:
    """How a field file's per-pixel uncertainty (``sigma_u_px``, ``sigma_v_px`` of frame ``k``)
    describes the pixels' errors (``where``: the pixels looked at): the RMS of error / sigma and
    the share within 2 sigma, per axis, and the median sigma; {} where the file has none."""
    if "sigma_u_px" not in f:
        return {}
    out = {}
    for axis, error in (("u", error_u), ("v", error_v)):
        sigma = f[f"sigma_{axis}_px"][k].astype(np.float64)
        error = np.asarray(error, np.float64)
        ok = np.isfinite(sigma) & np.isfinite(error) & (sigma > 0)
        if where is not None:
            ok &= where
        if not ok.any():
            return {}
        z = error[ok] / sigma[ok]
        out[f"pixel_z_rms_{axis}"] = float(np.sqrt(np.mean(z ** 2)))
        out[f"pixel_within_2sigma_{axis}"] = float(np.mean(np.abs(z) < 2))
        out[f"pixel_sigma_median_{axis}_px"] = float(np.median(sigma[ok]))
    return out


def sample3(method: str, work: Path) -> dict:
    names = ["Sample3 Reference.tif"] + sorted(p.name for p in S3.glob("Sample3-0*.tif"))
    frames = frames_folder(S3, names, work / "s3")
    out = work / f"s3_{method}"
    run = track(frames, method, S3_RECT, out)
    truth = np.genfromtxt(S3 / "truth.csv", delimiter=",", names=True)
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        kept = f["kept"][()] == 1
        dx = np.array([np.nanmean(f["u_px"][k][kept]) for k in range(1, len(names))])
        dy = np.array([np.nanmean(f["v_px"][k][kept]) for k in range(1, len(names))])
    shift_x, shift_y = _truth_columns(truth, len(names) - 1)
    bias = np.concatenate([dx - shift_x, dy - shift_y])
    return {**run, "bias_rms_px": float(np.sqrt(np.mean(bias**2))), "bias_max_px": float(np.max(np.abs(bias))),
            "bias_x_px": [round(float(b), 5) for b in dx - shift_x],
            "bias_y_px": [round(float(b), 5) for b in dy - shift_y]}


def _truth_columns(truth: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    names = truth.dtype.names
    x_name = next(n for n in names if n.lower().startswith(("dx", "u", "x")))
    y_name = next(n for n in names if n.lower().startswith(("dy", "v", "y")) and n != x_name)
    return np.asarray(truth[x_name][-n:], float), np.asarray(truth[y_name][-n:], float)


def sample12_mask(shape: tuple[int, int]) -> np.ndarray:
    """DICe's region of interest on Sample 12 (its ``subset_file.dat``) as a boolean mask."""
    cx, cy, width, height = S12_RECTANGLE
    hx, hy, radius = S12_HOLE
    ys, xs = np.mgrid[0:shape[0], 0:shape[1]]
    return (np.abs(xs - cx) <= width / 2) & (np.abs(ys - cy) <= height / 2) & (np.hypot(xs - hx, ys - hy) > radius)


def dice_solution(frame: int) -> np.ndarray:
    """DICe's solution of Sample 12's ``frame`` against frame 0: rows of x, y, u, v (px)."""
    text = (S12 / "dice_reference_solution" / f"DICe_solution_{frame:02d}.txt").read_text()
    rows = [line for line in text.splitlines() if line.strip() and not line.startswith("***")]
    header = rows[0].split(",")
    table = np.array([[float(v) for v in row.split(",")] for row in rows[1:]])
    return table[:, [header.index(name) for name in ("COORDINATE_X", "COORDINATE_Y", "DISPLACEMENT_X",
                                                      "DISPLACEMENT_Y")]]


def against_dice(x_px: np.ndarray, y_px: np.ndarray, u: np.ndarray, v: np.ndarray, frame: int) -> dict:
    """A field's (``u``, ``v`` over the columns ``x_px`` and rows ``y_px``) difference from DICe's
    solution at DICe's points: RMS and mean per axis, and how many of its points were read."""
    points = dice_solution(frame)
    cols = np.searchsorted(x_px, points[:, 0])
    rows = np.searchsorted(y_px, points[:, 1])
    inside = (cols < len(x_px)) & (rows < len(y_px))
    inside[inside] &= (x_px[cols[inside]] == points[inside, 0]) & (y_px[rows[inside]] == points[inside, 1])
    du = np.full(len(points), np.nan)
    dv = np.full(len(points), np.nan)
    du[inside] = u[rows[inside], cols[inside]] - points[inside, 2]
    dv[inside] = v[rows[inside], cols[inside]] - points[inside, 3]
    read = np.isfinite(du) & np.isfinite(dv)
    out = {"points": int(len(points)), "read": int(read.sum()),
           "v_range_px": [float(points[:, 3].min()), float(points[:, 3].max())]}
    for axis, d in (("u", du[read]), ("v", dv[read])):
        out[f"rms_{axis}_px"] = float(np.sqrt(np.mean(d ** 2))) if d.size else float("nan")
        out[f"mean_{axis}_px"] = float(np.mean(d)) if d.size else float("nan")
    return out


def sample12_mask_file(path: Path) -> Path:
    """:func:`sample12_mask` over Sample 12's reference, written as a PNG at ``path``."""
    import cv2

    reference = cv2.imread(str(S12 / S12_FRAMES[0]), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(path), sample12_mask(reference.shape).astype(np.uint8) * 255)
    return path


def _track_sample12(frames: Path, method: str, out: Path) -> dict:
    """``refflow track`` over DICe's region of Sample 12 (the mask beside ``out``)."""
    return track(frames, method, None, out, mask=sample12_mask_file(out.parent / "s12_mask.png"))


def sample12(method: str, work: Path) -> dict:
    out = work / f"s12_{method}"
    run = _track_sample12(frames_folder(S12, S12_FRAMES, work / "s12"), method, out)
    per_frame = []
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        x, y = f["x_px"][()], f["y_px"][()]
        for k in range(1, len(S12_FRAMES)):
            per_frame.append(against_dice(x, y, f["u_px"][k].astype(np.float64), f["v_px"][k].astype(np.float64), k))
    return {**run, "frames": per_frame}


# The replica of Sample 12: the real reference warped by the affine fit of DICe's solution of
# these frames (known fields of the same size and kind), with fresh noise in every frame.
S12_REPLICA_FRAMES = (1, 3, 5, 11)
S12_REPLICA_NOISE = 1.0  # grey levels, per frame
S12_CENTRE = (195.0, 517.0)


def _replica_fields(frames: tuple[int, ...]) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per frame, the affine fits ``(a, b, c)`` of DICe's u and v: value = a + b (x - cx) + c (y - cy)."""
    fits = []
    for frame in frames:
        x, y, u, v = dice_solution(frame).T
        design = np.column_stack([np.ones_like(x), x - S12_CENTRE[0], y - S12_CENTRE[1]])
        fits.append((np.linalg.lstsq(design, u, rcond=None)[0], np.linalg.lstsq(design, v, rcond=None)[0]))
    return fits


def _affine(fit: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return fit[0] + fit[1] * (x - S12_CENTRE[0]) + fit[2] * (y - S12_CENTRE[1])


def sample12_replica_frames(into: Path) -> Path:
    """Sample 12's reference, and copies of it warped by each replica field (``deformed(x + u(x))
    = reference(x)``, a quintic B-spline of the 8-bit image), each with its own noise, as PNGs."""
    import cv2
    from scipy import ndimage

    into.mkdir(parents=True, exist_ok=True)
    reference = cv2.imread(str(S12 / S12_FRAMES[0]), cv2.IMREAD_GRAYSCALE).astype(np.float64)
    rng = np.random.default_rng(12)
    coefficients = ndimage.spline_filter(reference, order=5, mode="mirror")
    ys, xs = np.mgrid[0:reference.shape[0], 0:reference.shape[1]].astype(np.float64)
    images = [reference]
    for fit_u, fit_v in _replica_fields(S12_REPLICA_FRAMES):
        source_x, source_y = xs.copy(), ys.copy()
        for _ in range(6):  # the reference point that lands on each pixel
            source_x, source_y = xs - _affine(fit_u, source_x, source_y), ys - _affine(fit_v, source_x, source_y)
        images.append(ndimage.map_coordinates(coefficients, [source_y, source_x], order=5, prefilter=False,
                                              mode="mirror"))
    for k, image in enumerate(images):
        noisy = np.clip(np.rint(image + rng.normal(0, S12_REPLICA_NOISE, image.shape)), 0, 255).astype(np.uint8)
        cv2.imwrite(str(into / f"f{k:03d}.png"), noisy)
    return into


def sample12_replica(method: str, work: Path) -> dict:
    """Each method on the replica (known fields): per frame the mean and RMS of its field's
    error over DICe's region, u and v."""
    frames = work / "s12_replica"
    if not frames.is_dir():
        sample12_replica_frames(frames)
    out = work / f"s12r_{method}"
    run = _track_sample12(frames, method, out)
    per_frame = []
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        x, y = f["x_px"][()], f["y_px"][()]
        for k, (fit_u, fit_v) in enumerate(_replica_fields(S12_REPLICA_FRAMES), start=1):
            errors = {}
            for axis, fit in (("u", fit_u), ("v", fit_v)):
                error = f[f"{axis}_px"][k].astype(np.float64) - _affine(fit, x[None, :], y[:, None])
                error = error[np.isfinite(error)]
                errors[f"mean_{axis}_px"] = float(np.mean(error))
                errors[f"rms_{axis}_px"] = float(np.sqrt(np.mean(error ** 2)))
            per_frame.append({"dice_frame": S12_REPLICA_FRAMES[k - 1], **errors})
    return {**run, "frames": per_frame}


def star(name: str, method: str, work: Path) -> dict:
    folder, names, period_of = STARS[name]
    frames = frames_folder(folder, names, work / name)
    out = work / f"{name}_{method}"
    import cv2

    height, width = cv2.imread(str(folder / names[0]), cv2.IMREAD_UNCHANGED).shape
    run = track(frames, method, f"10,10,{width - 20},{height - 20}", out)
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        x, y = f["x_px"][()], f["y_px"][()]
        v = f["v_px"][1].astype(np.float64)
        # The per-pixel uncertainty against the errors where the period is over 100 px (the
        # resolution's shortfall is small there; what is left is noise and the estimator's own).
        period = period_of(x)
        truth = 0.5 * np.cos(2 * np.pi * (y[:, None] - 250) / period[None, :])
        sigmas = pixel_sigma(f, 1, f["u_px"][1], v - truth, where=((y >= 40) & (y <= 460))[:, None]
                             & (period > 100)[None, :])
    rows = (y >= 40) & (y <= 460)
    v, y = v[rows], y[rows]
    shape = np.cos(2 * np.pi * (y[:, None] - 250) / period[None, :])
    ok = np.isfinite(v)
    amplitude = np.nansum(np.where(ok, v * shape, 0), axis=0) / np.sum(np.where(ok, shape**2, 0), axis=0)
    smooth = np.convolve(amplitude, np.ones(41) / 41, mode="same")
    ratio = smooth / 0.5
    resolution = float("nan")
    for k in np.argsort(-period):
        if not (20 <= k < len(x) - 20):
            continue
        if abs(ratio[k] - 1) > WITHIN:
            break
        resolution = float(period[k])
    long = period > 100
    residual = v[:, long] - amplitude[None, long] * shape[:, long]
    inner = np.arange(20, len(x) - 20, STAR_CURVE_STEP)  # the running mean's full columns
    return {**run, **sigmas, "resolution_px": resolution, "noise_px": float(np.nanstd(residual)),
            "amplitude_long_px": float(np.nanmedian(amplitude[long])),
            "curve_period_px": [round(float(p), 3) for p in period[inner]],
            "curve_amplitude_px": [round(float(a), 5) for a in smooth[inner]]}


def table(results: dict, methods: list[str]) -> str:
    lines: list[str] = []
    if results.get("sample14") or results.get("sample3"):
        lines += _table_s14_s3(results, methods)
    stars = results.get("stars", {})
    if stars:
        lines += ["", "| method | " + " | ".join(f"{s} resolution px / noise px" for s in STARS) + " |",
                  "| --- | " + " | ".join("---" for _ in STARS) + " |"]
        for method in methods:
            cells = []
            for name in STARS:
                r = stars.get(name, {}).get(method)
                if not r or "error" in r:
                    cells.append("-")
                    continue
                resolution = r["resolution_px"]
                resolution = "none" if not np.isfinite(resolution) else f"{resolution:.0f}"  # never within 10 %
                cells.append(f"{resolution} / {r['noise_px']:.4f}")
            lines.append(f"| {method} | {' | '.join(cells)} |")
    if results.get("sample12"):
        lines += [""] * bool(lines) + _table_s12(results["sample12"], methods)
    if results.get("sample12_replica"):
        lines += [""] * bool(lines) + _table_s12_replica(results["sample12_replica"], methods)
    lines += _table_pixel_sigma(results, methods)
    return "\n".join(lines)


def _table_pixel_sigma(results: dict, methods: list[str]) -> list[str]:
    """Per method with a per-pixel uncertainty: each known field's error over it, u / v."""
    cases = [("sample14", None, level) for level in S14_LEVELS] + [("stars", name, None) for name in STARS]
    lines = []
    for method in methods:
        cells = []
        for key, name, level in cases:
            r = results.get(key, {})
            r = (r.get(name, {}) if name else r).get(method) or {}
            r = r.get(level, {}) if level else r
            cells.append(f"{r['pixel_z_rms_u']:.2f} / {r['pixel_z_rms_v']:.2f}, "
                         f"{100 * r['pixel_within_2sigma_u']:.0f} / {100 * r['pixel_within_2sigma_v']:.0f} %"
                         if "pixel_z_rms_u" in r else "-")
        if any(cell != "-" for cell in cells):
            lines.append(f"| {method} | {' | '.join(cells)} |")
    if not lines:
        return []
    header = ["S14 " + level for level in S14_LEVELS] + [f"{name} (periods > 100 px)" for name in STARS]
    return ["", "| method (per-pixel sigma: error / sigma RMS u / v, share within 2 sigma) | "
            + " | ".join(header) + " |", "| --- | " + " | ".join("---" for _ in header) + " |", *lines]


def _method_rows(per_method: dict, methods: list[str], columns: int,
                 cells: Callable[[dict], list[str]]) -> list[str]:
    """One table row per method that has a result: its ``cells``, or its error and ``columns - 1``
    dashes."""
    rows = []
    for method in methods:
        r = per_method.get(method)
        if not r:
            continue
        shown = [r["error"]] + ["-"] * (columns - 1) if "error" in r else cells(r)
        rows.append(f"| {method} | {' | '.join(shown)} |")
    return rows


def _table_s12(s12: dict, methods: list[str]) -> list[str]:
    def cells(r: dict) -> list[str]:
        frames = r["frames"]
        out = []
        for stat, pick in (("rms", lambda a: np.sqrt(np.mean(np.square(a)))), ("rms", np.max),
                           ("mean", lambda a: a[np.argmax(np.abs(a))])):
            u, v = (np.array([f[f"{stat}_{axis}_px"] for f in frames]) for axis in "uv")
            out.append(f"{pick(u):+.4f} / {pick(v):+.4f}" if stat == "mean" else f"{pick(u):.4f} / {pick(v):.4f}")
        return [*out, f"{min(f['read'] for f in frames)} of {frames[0]['points']}", f"{r['wall_s']:.0f}"]

    return ["| method | field - DICe's solution, RMS u / v px (11 frames) | worst frame's RMS u / v | "
            "largest mean u / v | DICe's points read | s per run |",
            "| --- | --- | --- | --- | --- | --- |", *_method_rows(s12, methods, 5, cells)]


def _table_s12_replica(replica: dict, methods: list[str]) -> list[str]:
    def cells(r: dict) -> list[str]:
        rms = [np.mean([f[f"rms_{axis}_px"] for f in r["frames"]]) for axis in "uv"]
        mean = [max((f[f"mean_{axis}_px"] for f in r["frames"]), key=abs) for axis in "uv"]
        return [f"{rms[0]:.4f} / {rms[1]:.4f}", f"{mean[0]:+.4f} / {mean[1]:+.4f}", f"{r['wall_s']:.0f}"]

    frames = ", ".join(str(f) for f in S12_REPLICA_FRAMES)
    return [f"| method | Sample 12 replica (known affine fields of DICe's frames {frames}): error RMS u / v px, "
            "mean over the frames | largest mean error u / v | s per run |", "| --- | --- | --- | --- |",
            *_method_rows(replica, methods, 3, cells)]


def _table_s14_s3(results: dict, methods: list[str]) -> list[str]:
    lines = ["| method | S14 L1 RMSE px / gain / 10 % period px | L3 | L5 | S3 bias RMS / max px | s per run (S14) |",
             "| --- | --- | --- | --- | --- | --- |"]
    for method in methods:
        s14, s3 = results.get("sample14", {}).get(method), results.get("sample3", {}).get(method)
        cells = []
        for level in S14_LEVELS:
            if not s14 or "error" in s14:
                cells.append(s14["error"] if s14 and level == "L1" else "-")
                continue
            r = s14[level]
            period = r["shortest_period_px"]
            period = "none" if not np.isfinite(period) else f"{period:.0f}"  # never within 10 %
            cells.append(f"{r['rmse_px']:.4f} / {r['gain']:.3f} / {period}")
        s3_cell = f"{s3['bias_rms_px']:.4f} / {s3['bias_max_px']:.4f}" if s3 and "error" not in s3 else "-"
        wall = f"{s14['wall_s']:.0f}" if s14 and "wall_s" in s14 else "-"
        lines.append(f"| {method} | {' | '.join(cells)} | {s3_cell} | {wall} |")
    return lines


def figure(results: dict, methods: list[str], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    command = np.loadtxt(S14 / "command.csv", delimiter=",")
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), sharex=True, layout="constrained")
    for ax, (level, column) in zip(axes, (("L1", 1), ("L3", 3), ("L5", 5)), strict=True):
        ax.plot(command[:, 0], command[:, column], color="black", lw=2, label="command")
        for method in methods:
            r = results.get("sample14", {}).get(method)
            if r and "error" not in r:
                ax.plot(r["x_px"], r[level]["column_mean_u_px"], lw=0.9,
                        label=f"{method} ({r[level]['rmse_px']:.4f} px)")
        ax.set_ylabel(f"{level}: u (px)")
        ax.legend(fontsize=7, ncols=2, loc="lower left")
    axes[-1].set_xlabel("column x (px)")
    fig.suptitle("DIC Challenge Sample 14: column means of u over rows 100-488 (RMSE against the command)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure_stars(results: dict, methods: list[str], path: Path) -> None:
    """Each Star's amplitude read (41-column running mean, over 0.5 px) against the period,
    per method, with the 10 % band that defines the spatial resolution."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import matplotlib.ticker

    stars = results.get("stars", {})
    names = [name for name in STARS if stars.get(name)]
    fig, axes = plt.subplots(1, len(names), figsize=(4.2 * len(names), 3.8), sharey=True, layout="constrained",
                             squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        for method in methods:
            r = stars[name].get(method)
            if r and "curve_period_px" in r:
                ax.plot(r["curve_period_px"], np.asarray(r["curve_amplitude_px"]) / 0.5, lw=1,
                        label=f"{method} ({r['resolution_px']:.0f} px)" if np.isfinite(r["resolution_px"])
                        else f"{method} (none)")
        ax.axhspan(1 - WITHIN, 1 + WITHIN, color="grey", alpha=0.15)
        ax.axhline(1.0, color="black", lw=0.8)
        ax.set_xscale("log")
        longest = max((r["curve_period_px"][-1] for r in stars[name].values() if "curve_period_px" in r), default=300)
        ticks = [t for t in (10, 20, 50, 100, 200, 300) if t <= longest]
        ax.set_xticks(ticks, [str(t) for t in ticks])
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xlabel("period of the cosine (px)")
        ax.set_title(name)
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7, loc="lower right")
    axes[0][0].set_ylabel("amplitude read / 0.5 px")
    fig.suptitle("DIC Challenge 2.0 Stars: amplitude read against the period (grey: within 10 %; "
                 "the legend's resolution: from there on)")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def figure12(results: dict, methods: list[str], path: Path) -> None:
    """Per frame, each method's RMS difference from DICe's solution on Sample 12, u and v."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True, layout="constrained")
    for ax, axis in zip(axes, "uv", strict=True):
        for method in methods:
            r = results.get("sample12", {}).get(method)
            if r and "error" not in r:
                frames = np.arange(1, len(r["frames"]) + 1)
                ax.plot(frames, [f[f"rms_{axis}_px"] for f in r["frames"]], marker="o", ms=3, label=method)
        ax.set_xlabel("frame (against frame 0; the load grows, v up to 12 px)")
        ax.set_title(f"{axis}: RMS of the field - DICe's at its 230 points")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("px")
    axes[0].legend(fontsize=8)
    fig.suptitle("DIC Challenge Sample 12 (real images, no truth): agreement with DICe's solution")
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--methods", default=",".join(DENSE))
    parser.add_argument("--stars", action="store_true", help="also Star 1, 2 and 5 (slow for the numba methods)")
    parser.add_argument("--samples", default="sample14,sample3,sample12,sample12_replica",
                        help="which of sample14, sample3, sample12, sample12_replica to run (default: all)")
    parser.add_argument("--figure12", default=str(ROOT / "results" / "figures" / "dic_challenge_sample12.png"))
    parser.add_argument("--figure-stars", default=str(ROOT / "results" / "figures" / "dic_challenge_stars.png"))
    parser.add_argument("--json", default=str(ROOT / "results" / "bench_dic_challenge.json"))
    parser.add_argument("--figure", default=str(ROOT / "results" / "figures" / "dic_challenge_sample14.png"))
    parser.add_argument("--out", default=str(ROOT / "results" / "bench_dic_challenge.md"), help="the table")
    parser.add_argument("--again", action="store_true", help="rerun what the JSON holds already")
    parser.add_argument("--jobs", type=int, help="refflow track's --jobs (default: its own); the numbers do not "
                        "depend on it, the seconds per run do")
    args = parser.parse_args()
    global JOBS
    JOBS = args.jobs
    methods = [m for m in args.methods.split(",") if m]
    store = Path(args.json)
    results = json.loads(store.read_text()) if store.is_file() else {}
    samples = {"sample14": sample14, "sample3": sample3, "sample12": sample12, "sample12_replica": sample12_replica}
    chosen = [s for s in args.samples.split(",") if s]
    unknown = sorted(set(chosen) - set(samples))
    if unknown:
        parser.error(f"unknown sample(s) {', '.join(unknown)}: choose from {', '.join(samples)}")
    jobs = [(key, None, samples[key]) for key in chosen]
    if args.stars:
        jobs += [("stars", name, lambda m, w, n=name: star(n, m, w)) for name in STARS if STARS[name][0].is_dir()]
    with tempfile.TemporaryDirectory(prefix="dic_") as tmp:
        work = Path(tmp)
        for method in methods:
            for key, name, measure in jobs:
                holder = results.setdefault(key, {})
                holder = holder.setdefault(name, {}) if name else holder
                if method in holder and not args.again:
                    continue
                print(f"{key} {name or ''} {method} ...", file=sys.stderr, flush=True)
                try:
                    holder[method] = measure(method, work)
                except RuntimeError as err:
                    holder[method] = {"error": str(err)}
                store.parent.mkdir(parents=True, exist_ok=True)
                store.write_text(json.dumps(results, indent=1))
    shown = [m for m in (*DENSE, *(m for m in methods if m not in DENSE))
             if any(m in results.get(key, {}) for key in samples)]
    text = table(results, shown)
    print(text)
    Path(args.out).write_text(text + "\n")
    if results.get("sample14"):
        figure(results, shown, Path(args.figure))
    if results.get("sample12"):
        figure12(results, shown, Path(args.figure12))
    if any(results.get("stars", {}).values()):
        figure_stars(results, shown, Path(args.figure_stars))


if __name__ == "__main__":
    main()
