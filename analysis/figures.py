"""Figures in the style of the paper's Fig. 6-10 (PNG + SVG, one question each).

* ``fig6_poi_vs_corners``: mask POIs vs the corners KLT tracked (its ``--raw-tracks`` file) on
  the first frame, drawn as ``refflow pois`` draws it (PNG only).
* ``fig7_gradient_magnitude``: Sobel gradient magnitude of the first frame.
* ``fig8_time_histories``: each method against the reference, and the errors.
* ``fig9_psd``: Welch PSDs (log scale) with the model's modes and their aliases.
* ``fig10_occlusion``: displacement around the occlusion, occluded span shaded.
* ``fig11_klt_features``: what each KLT feature reads (its gain against the truth), and
  how the static background corners among them scale KLT's mean about the reference frame.
"""

from __future__ import annotations

import json
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from refflow.figures import poi_figure  # noqa: E402
from refflow.io import atomic_path  # noqa: E402

from .metrics import DEFAULTS, MIN_COMPARED_FRAMES, occlusion_spans  # noqa: E402
from .readers import model_modes_hz, read_json, read_sensor, read_track, read_truth, track_mm  # noqa: E402
from .spectra import alias_frequency, welch_psd  # noqa: E402
from .sync import align, datum_offset, lowpass  # noqa: E402

REF_STYLE = {"color": "black", "lw": 1.0, "label": "reference (laser, 30 Hz low-pass)"}


def save(fig: plt.Figure, out_dir: Path, name: str) -> list[Path]:
    """Write ``name.png`` and ``name.svg`` atomically; close the figure."""
    paths = []
    for ext in ("png", "svg"):
        path = out_dir / f"{name}.{ext}"
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=150, bbox_inches="tight", format=ext)
        paths.append(path)
    plt.close(fig)
    return paths


def _shade(ax, time_s: np.ndarray, occluded: np.ndarray, label: bool = False) -> None:
    for i, (a, b) in enumerate(occlusion_spans(occluded)):
        end = time_s[b] if b < time_s.size else time_s[-1]
        ax.axvspan(time_s[a], end, color="0.85", zorder=0, label="occluded" if label and i == 0 else None)


def fig_time_histories(runs: list[dict[str, Any]], truth: dict[str, np.ndarray], out_dir: Path) -> list[Path]:
    n = len(runs)
    fig, axes = plt.subplots(n + 1, 1, figsize=(10, 2.6 * (n + 1)), sharex=True)
    axes = np.atleast_1d(axes)
    for ax, run in zip(axes[:-1], runs, strict=False):
        _shade(ax, run["t"], run["occluded"])
        ax.plot(run["t"], run["ref"], **REF_STYLE)
        ax.plot(run["t"], run["meas"], lw=0.9, color=run["color"], label=f"{run['name']} (camera)")
        ax.set_ylabel("displacement x (mm)")
        ax.set_title(f"Reference vs {run['name']}: RMSE {run['rmse_mm']:.4f} mm")
        ax.legend(loc="upper right", fontsize=8)
    ax = axes[-1]
    for run in runs:
        ax.plot(run["t"], run["meas"] - run["ref"], lw=0.9, color=run["color"], label=run["name"])
    _shade(ax, runs[0]["t"], runs[0]["occluded"])
    ax.axhline(0, color="0.5", lw=0.5)
    ax.set_ylabel("error (mm)\nmeasured - reference")
    ax.set_xlabel("camera time (s)")
    ax.set_title("Displacement error")
    ax.legend(loc="upper right", fontsize=8)
    fig.tight_layout()
    return save(fig, out_dir, "fig8_time_histories")


def fig_psd(runs: list[dict[str, Any]], fps: float, modes_hz: np.ndarray | None, out_dir: Path) -> list[Path]:
    fig, ax = plt.subplots(figsize=(9, 4.5))
    run0 = runs[0]
    ok = np.isfinite(run0["ref"])
    f, p = welch_psd(run0["ref"][ok], fps, segment_s=min(20.0, run0["t"][ok][-1] - run0["t"][ok][0]))
    ax.semilogy(f, p, color="black", lw=1.2, label="reference (laser, at frame times)")
    for run in runs:
        ok = np.isfinite(run["ref"])
        good = ok & run["valid"]
        series = np.interp(run["t"][ok], run["t"][good], run["meas"][good])
        f, p = welch_psd(series, fps, segment_s=min(20.0, run["t"][ok][-1] - run["t"][ok][0]))
        ax.semilogy(f, p, lw=0.9, color=run["color"], label=run["name"])
    if modes_hz is not None:
        for i, fm in enumerate(modes_hz, start=1):
            if fm <= fps / 2:
                ax.axvline(fm, color="tab:green", ls="--", lw=0.8)
                ax.text(fm, 0.97, f" mode {i}\n {fm:.1f} Hz", transform=ax.get_xaxis_transform(),
                        va="top", fontsize=8, color="tab:green")
            else:
                fa = alias_frequency(fm, fps)
                ax.axvline(fa, color="tab:red", ls=":", lw=0.9)
                ax.text(fa, 0.80, f" mode {i} alias\n {fm:.1f} -> {fa:.1f} Hz", transform=ax.get_xaxis_transform(),
                        va="top", fontsize=8, color="tab:red")
    ax.axvspan(0, DEFAULTS["lowfreq_hz"], color="0.9", zorder=0, label="0-0.1 Hz (drift)")
    ax.set_xlim(0, fps / 2)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("PSD of displacement (mm$^2$/Hz)")
    ax.set_title(f"Welch PSD at {fps:g} fps (Nyquist {fps / 2:g} Hz)")
    ax.legend(fontsize=8, loc="lower left")
    fig.tight_layout()
    return save(fig, out_dir, "fig9_psd")


def fig_occlusion(runs: list[dict[str, Any]], out_dir: Path, *, margin_s: float = 3.0) -> list[Path]:
    spans = occlusion_spans(runs[0]["occluded"])
    if not spans:
        return []
    a, b = max(spans, key=lambda s: s[1] - s[0])
    t = runs[0]["t"]
    t0, t1 = t[a] - margin_s, t[min(b, t.size - 1)] + margin_s
    fig, axes = plt.subplots(len(runs), 1, figsize=(10, 2.8 * len(runs)), sharex=True, squeeze=False)
    for ax, run in zip(axes[:, 0], runs, strict=False):
        sel = (run["t"] >= t0) & (run["t"] <= t1)
        _shade(ax, run["t"], run["occluded"], label=True)
        ax.plot(run["t"][sel], run["ref"][sel], **REF_STYLE)
        ax.plot(run["t"][sel], run["meas"][sel], lw=0.9, color=run["color"], label=run["name"])
        bad = sel & ~run["valid"]
        if bad.any():
            ax.plot(run["t"][bad], np.zeros(bad.sum()), "|", color="tab:red", ms=8, label="flagged valid=0")
        ax.set_ylabel("displacement x (mm)")
        ax.set_title(f"{run['name']} through the occlusion")
        ax.legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel("camera time (s)")
    fig.tight_layout()
    return save(fig, out_dir, "fig10_occlusion")


def _first_frame(video: str | os.PathLike[str]) -> np.ndarray:
    import cv2
    cap = cv2.VideoCapture(str(video))
    ok, frame = cap.read()
    cap.release()
    if not ok:
        raise ValueError(f"{video}: could not read the first frame")
    return cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY) if frame.ndim == 3 else frame


def _read_mask(mask_path: str | os.PathLike[str] | None, shape: tuple[int, ...]) -> np.ndarray | None:
    import cv2
    if mask_path is None:
        return None
    mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
    if mask is None:
        raise ValueError(f"{mask_path}: could not read the mask image")
    if mask.shape != shape:
        raise ValueError(f"{mask_path}: mask is {mask.shape[1]}x{mask.shape[0]} but frames are "
                         f"{shape[1]}x{shape[0]}")
    return mask


def klt_corners(raw_tracks: str | os.PathLike[str]) -> np.ndarray:
    """Full-frame ``(x, y)`` of the corners a sparse run tracked, from its ``--raw-tracks``
    file: what KLT detected with its own parameters (recorded in the file's ``meta``)."""
    with np.load(raw_tracks, allow_pickle=False) as data:
        xy = np.column_stack([np.asarray(data["x_px"], float), np.asarray(data["y_px"], float)])
        meta = json.loads(str(data["meta"])) if "meta" in data.files else {}
    roi = meta.get("roi") or {}
    return xy + [float(roi.get("x", 0)), float(roi.get("y", 0))]  # ROI pixels -> full frame


def fig_features(video: str | os.PathLike[str], mask_path: str | os.PathLike[str] | None,
                 out_dir: Path, *, klt_raw: str | os.PathLike[str] | None = None) -> list[Path]:
    """Fig. 6 (the mask's POIs against the corners KLT tracked, from a sparse run's
    ``--raw-tracks`` file; drawn by ``refflow pois``'s own :func:`refflow.figures.poi_figure`)
    and Fig. 7 (the gradient magnitude), both on the first frame."""
    import cv2
    gray = _first_frame(video)
    mask = _read_mask(mask_path, gray.shape)
    ys, xs = np.nonzero(mask > 127) if mask is not None else (np.zeros(0, int), np.zeros(0, int))
    corners = klt_corners(klt_raw) if klt_raw is not None else None
    fig6 = out_dir / "fig6_poi_vs_corners.png"
    poi_figure(gray, np.column_stack([xs, ys]), corners, fig6)
    written = [fig6]

    gx = cv2.Sobel(gray.astype(np.float32), cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(gray.astype(np.float32), cv2.CV_32F, 0, 1, ksize=3)
    mag = np.hypot(gx, gy)
    fig, ax = plt.subplots(figsize=(6.5, 5.5))
    im = ax.imshow(mag, cmap="magma")
    if mask is not None:
        ax.contour(mask > 127, levels=[0.5], colors="cyan", linewidths=0.8)
    fig.colorbar(im, ax=ax, label="gradient magnitude (grey levels / px, Sobel 3x3)")
    ax.set_title("Gradient magnitude (cyan: POI mask outline)")
    ax.set_xlabel("image x (px)")
    ax.set_ylabel("image y (px)")
    fig.tight_layout()
    written += save(fig, out_dir, "fig7_gradient_magnitude")
    return written


def klt_feature_gains(raw_tracks: str | os.PathLike[str], truth: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per KLT feature: its place, and the gain and offset of ``dx = gain * truth + offset``
    fitted over the frames it was tracked (a static background corner has gain 0).

    ``raw_tracks``: the ``--raw-tracks`` file of a sparse run (format in docs/formats.md).
    """
    with np.load(raw_tracks, allow_pickle=False) as data:
        frame, dx = data["frame"], np.asarray(data["dx_px"], float)
        x, y = np.asarray(data["x_px"], float), np.asarray(data["y_px"], float)
    pos = {int(f): i for i, f in enumerate(truth["frame"])}
    rows = np.array([pos.get(int(f), -1) for f in frame])
    true_px = np.where(rows >= 0, truth["dx_px"][np.maximum(rows, 0)], np.nan)
    gain, offset = np.full(x.size, np.nan), np.full(x.size, np.nan)
    for j in range(x.size):
        ok = np.isfinite(dx[:, j]) & np.isfinite(true_px)
        if ok.sum() > 10 and np.ptp(true_px[ok]) > 0:
            gain[j], offset[j] = np.polyfit(true_px[ok], dx[ok, j], 1)
    return {"frame": frame, "dx_px": dx, "x_px": x, "y_px": y, "gain": gain, "offset": offset,
            "truth_px": true_px}


def fig_klt_features(raw_tracks: str | os.PathLike[str], truth: dict[str, np.ndarray], video: str | None,
                     mask_path: str | None, mm_per_px: float, out_dir: Path, *,
                     static_gain: float = 0.2) -> list[Path]:
    """Where KLT's error comes from: the features it follows, the gain each one reads, and
    the mean with and without the static (background) corners. The mean is an unweighted
    average over features measured from the reference frame, so static corners scale it
    about the reference's position, not about the structure's rest position."""
    import cv2
    g = klt_feature_gains(raw_tracks, truth)
    static = np.abs(g["gain"]) < static_gain
    moving = np.isfinite(g["gain"]) & ~static
    with np.errstate(all="ignore"):
        import warnings
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            mean_all = np.nanmean(g["dx_px"], axis=1)
            mean_moving = np.nanmean(g["dx_px"][:, moving], axis=1) if moving.any() else mean_all * np.nan
    t = truth["time_s"][np.searchsorted(truth["frame"], g["frame"])]
    true_px = g["truth_px"]
    # Into the truth's datum (from rest) at the first 0.25 s, as Fig. 8 aligns each method.
    first = np.isfinite(true_px) & (t <= t[0] + 0.25)
    datum_all = float(np.nanmedian(true_px[first] - mean_all[first]))
    datum_moving = float(np.nanmedian(true_px[first] - mean_moving[first]))
    fig = plt.figure(figsize=(13, 8.5))
    grid = fig.add_gridspec(2, 2, width_ratios=[1.0, 1.4])
    ax_img = fig.add_subplot(grid[:, 0])
    if video:
        ax_img.imshow(_first_frame(video), cmap="gray", vmin=0, vmax=255)
    if mask_path:
        mask = cv2.imread(str(mask_path), cv2.IMREAD_GRAYSCALE)
        if mask is not None:
            ax_img.contour(mask > 127, levels=[0.5], colors="cyan", linewidths=0.8)
    sc = ax_img.scatter(g["x_px"], g["y_px"], c=g["gain"], cmap="viridis", vmin=0.0, vmax=1.1, s=40,
                        edgecolors="white", linewidths=0.6)
    ax_img.plot(g["x_px"][static], g["y_px"][static], "x", color="red", ms=9,
                label=f"static corners: {int(static.sum())} of {g['x_px'].size}")
    fig.colorbar(sc, ax=ax_img, shrink=0.6, label="feature gain (its dx / true dx)")
    ax_img.legend(fontsize=8, loc="lower right")
    ax_img.set_title("KLT features on the first frame (cyan: POI mask)")
    ax_img.set_xlabel("image x (px)")
    ax_img.set_ylabel("image y (px)")
    ax_t = fig.add_subplot(grid[0, 1])
    ax_t.plot(t, true_px * mm_per_px, color="black", lw=1.0, label="truth (image plane, from rest)")
    ax_t.plot(t, (mean_all + datum_all) * mm_per_px, color="tab:red", lw=0.9,
              label="KLT: mean of all features (as reported)")
    ax_t.plot(t, (mean_moving + datum_moving) * mm_per_px, color="tab:blue", lw=0.9, ls="--",
              label="KLT: mean without the static corners")
    ax_t.axhline(0.0, color="0.6", lw=0.6)
    ax_t.set_xlabel("camera time (s)")
    ax_t.set_ylabel("displacement x (mm)")
    ax_t.set_title("Both aligned to the truth over the first 0.25 s (the held pluck deflection)")
    ax_t.legend(fontsize=8, loc="lower right")
    ax_s = fig.add_subplot(grid[1, 1])
    ok = np.isfinite(true_px) & np.isfinite(mean_all)
    reference_px = float(np.nanmedian(true_px[first]))
    ax_s.plot(true_px[ok] - reference_px, mean_all[ok], ".", ms=2, color="tab:red", label="all features")
    ok_m = np.isfinite(true_px) & np.isfinite(mean_moving)
    ax_s.plot(true_px[ok_m] - reference_px, mean_moving[ok_m], ".", ms=2, color="tab:blue",
              label="without static corners")
    for series, okk, color in ((mean_all, ok, "tab:red"), (mean_moving, ok_m, "tab:blue")):
        if okk.sum() > 2:
            slope = float(np.polyfit(true_px[okk] - reference_px, series[okk], 1)[0])
            ax_s.plot([], [], color=color, label=f"slope {slope:.3f}")
    span = (true_px[ok] - reference_px) if ok.any() else np.array([-1.0, 1.0])
    lo, hi = float(np.min(span)), float(np.max(span))
    ax_s.plot([lo, hi], [lo, hi], color="black", lw=0.8, label="1:1")
    ax_s.axvline(-reference_px, color="0.5", lw=0.8, ls=":", label="rest position")
    ax_s.set_xlabel("true displacement from the reference frame (px)")
    ax_s.set_ylabel("KLT mean from the reference frame (px)")
    ax_s.set_title("KLT's scale error pivots on the reference frame")
    ax_s.legend(fontsize=8, loc="upper left")
    fig.tight_layout()
    return save(fig, out_dir, "fig11_klt_features")


def make_all(*, sensor: str, truth: str, tracks: Sequence[tuple[str, str]], out_dir: str | os.PathLike[str],
             sim_json: str | None = None, render_json: str | None = None, video: str | None = None,
             mask: str | None = None, params: dict[str, Any] | None = None,
             klt_raw: str | None = None) -> list[Path]:
    """Every figure the inputs allow; returns the written paths."""
    p = {**DEFAULTS, **(params or {})}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    sens = read_sensor(sensor)
    tru = read_truth(truth)
    fps = 1.0 / float(np.median(np.diff(tru["time_s"])))
    nominal = 0.0
    mm_per_px = float("nan")
    if render_json:
        rj = read_json(render_json)
        fps = float(rj.get("fps", fps))
        nominal = float(rj.get("camera_start_offset_s", 0.0) or 0.0)
        mm_per_px = float(rj.get("mm_per_px", np.nan))
    modes = model_modes_hz(read_json(sim_json), sim_json) if sim_json else None
    colors = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    runs = []
    pos = {int(f): i for i, f in enumerate(tru["frame"])}
    for k, (name, path) in enumerate(tracks):
        tr = read_track(path)
        tr["dx_mm"], _ = track_mm(tr, mm_per_px)
        rows = np.array([pos.get(int(f), -1) for f in tr["frame"]])
        occluded = np.where(rows >= 0, tru["occluded"][np.maximum(rows, 0)], 0)
        valid = (tr["valid"] != 0) & np.isfinite(tr["dx_mm"])
        usable = int((valid & (occluded == 0)).sum())
        if usable < MIN_COMPARED_FRAMES:
            print(f"figures: {name}: {usable} valid frames outside occlusions, not plotted", file=sys.stderr)
            continue
        al = align(sens.time_s, sens.dx_mm, tr["time_s"], tr["dx_mm"], valid=valid & (occluded == 0),
                   cutoff_hz=p["lowpass_hz"], order=int(p["lowpass_order"]), max_lag_s=p["max_lag_s"],
                   highpass_hz=p["sync_highpass_hz"], center_s=nominal)
        meas = tr["dx_mm"] + datum_offset(tr["time_s"], al.ref_mm, tr["dx_mm"], valid & (occluded == 0),
                                          datum_s=p["datum_s"])
        both = valid & np.isfinite(al.ref_mm)
        err = meas[both] - al.ref_mm[both]
        runs.append({"name": name, "t": tr["time_s"], "meas": meas, "ref": al.ref_mm, "valid": valid,
                     "occluded": occluded, "color": colors[(k + 1) % len(colors)],
                     "rmse_mm": float(np.sqrt(np.mean(err ** 2)))})
    written: list[Path] = []
    if runs:
        written += fig_time_histories(runs, tru, out)
        written += fig_psd(runs, fps, modes, out)
        written += fig_occlusion(runs, out)
    else:  # no tracks: still show the reference and truth
        filt = lowpass(sens.dx_mm, sens.rate_hz, cutoff_hz=p["lowpass_hz"], order=int(p["lowpass_order"]))
        fig, ax = plt.subplots(figsize=(10, 3))
        ax.plot(sens.time_s, filt, **REF_STYLE)
        ax.plot(tru["time_s"] + nominal, tru["dx_mm"], lw=0.8, label="truth (image plane)")
        ax.set_xlabel("sensor time (s)")
        ax.set_ylabel("displacement x (mm)")
        ax.legend(fontsize=8)
        written += save(fig, out, "fig8_time_histories")
    if video:
        written += fig_features(video, mask, out, klt_raw=klt_raw)
    if klt_raw:
        written += fig_klt_features(klt_raw, tru, video, mask, mm_per_px, out)
    return written
