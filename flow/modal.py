"""``refflow modal``: natural frequencies, damping ratios and mode shapes of a user's measurement.

Each ``refflow track`` CSV is one measurement point (e.g. several members or regions of
one video, measured in separate runs with their own masks); the points must share their
frame times. Each point's displacement is taken along its dominant direction (or ``dx`` /
``dy``), put on the uniform clock with invalid frames bridged linearly (as for the
spectrum: :func:`flow.figures.resample_uniform`), and the points together go to the
output-only identification of :func:`refflow.modal.identify` (FDD peaks + SSI-cov over
model orders). Written, all or nothing: a JSON of the modes and two PNG figures, a
stabilisation diagram and the mode shapes; where the points' positions are known (the sidecar's
centroids) and the run's video can be read again, also each mode drawn over the run's reference
frame (a PNG) and animated, exaggerated, as a GIF per mode (as pyidi offers).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from flow.figures import dominant_frequency, read_measurements, resample_uniform
from flow.io.errors import InputError
from flow.outputs import check_outputs
from refflow.io import atomic_paths, finite_or_none, json_text, versions

# refflow.modal (scipy.signal, a second to import) is imported where it is used: the parser of
# every `refflow` command is built from this module's add_parser.

DIRECTIONS = ("auto", "dx", "dy")
FIGURE_SUFFIXES = ("_stabilisation.png", "_shapes.png")
FRAME_SUFFIX = "_shapes_frame.png"
# The animation: one cycle of the mode in this many frames, shown in this many ms each, the
# largest point's swing this fraction of the backdrop's larger side (a mode shape has no
# physical amplitude: it is exaggerated to be seen), the backdrop at most this wide.
ANIMATION_FRAMES = 24
ANIMATION_FRAME_MS = 60
SWING_FRACTION = 0.08
ANIMATION_MAX_WIDTH = 640
# A point whose frames are bridged beyond this share is measured mostly by interpolation.
_BRIDGED_WARN_FRAC = 0.2


def figure_paths(out_json: str | Path, out_prefix: str | Path | None = None) -> tuple[Path, Path]:
    """The stabilisation diagram and mode-shape PNGs: ``PREFIX_stabilisation.png`` and
    ``PREFIX_shapes.png``, the prefix defaulting to the JSON's path without its suffix."""
    prefix = str(out_prefix) if out_prefix is not None else str(Path(out_json).with_suffix(""))
    return Path(prefix + FIGURE_SUFFIXES[0]), Path(prefix + FIGURE_SUFFIXES[1])


def run_modal(csv_paths: list[str | Path], *, out_json: str | Path, out_prefix: str | Path | None = None,
              n_modes: int = 2, band_hz: tuple[float, float] | None = None,
              direction: str = "auto") -> dict[str, Any]:
    """Identify ``n_modes`` modes from the measurement points ``csv_paths`` and write the results.

    Parameters
    ----------
    csv_paths : list of path
        ``refflow track`` CSVs, one per point, sharing their frame times; the order of
        the points is the order of the shape vectors.
    out_json : path
        The modes (``docs/formats.md``: frequencies in Hz, damping ratios, shapes as real vectors
        normalised to max ``|.|`` = 1, the points with their names and, where their
        sidecar records a POI centroid (``poi.centroid_px``), positions).
    out_prefix : path, optional
        Figures ``<prefix>_stabilisation.png`` and ``<prefix>_shapes.png`` (default: the
        JSON's path without its suffix).
    n_modes : int
        Modes wanted (the most prominent peaks of the FDD curve in the band).
    band_hz : (float, float), optional
        Frequency band searched (default 0.5 Hz to 0.4 x the frame rate).
    direction : {"auto", "dx", "dy"}
        ``auto``: each point's principal direction of motion, its sign set to agree with
        the principal direction of all points together (so that a shape's signs compare).

    Returns
    -------
    dict
        What the JSON holds, plus ``outputs``: the paths written.

    Raises
    ------
    InputError
        Unreadable or too short CSVs, CSVs whose frame times differ, a bad option, an
        output that is an input or cannot be written. Nothing is written then.
    """
    paths = [Path(p) for p in csv_paths]
    _check_options(paths, n_modes, band_hz, direction)
    figures = figure_paths(out_json, out_prefix)
    inputs = [(what, path) for csv_path in paths for what, path in (
        (f"the CSV {csv_path}", csv_path), (f"{csv_path}'s sidecar", csv_path.with_suffix(".json")))]
    check_outputs([*figures, Path(out_json)], inputs, option="--out or --figures")
    point_paths, measured, where = _read_points(paths)
    units = "mm" if all(m["has_mm"] for m in measured) else "px"
    record = _common_record(where, measured, units, direction)
    modes, diagnostics = _identify(record, n_modes, band_hz)
    regions = [data["region"] for data in measured]
    result = _result(record, modes, diagnostics, _points(point_paths, regions, record), units=units,
                     direction=direction, n_modes=n_modes)
    below = _below_band(record, diagnostics["band_hz"])
    if below:
        result["notes"].append(below)
    backdrop, why_not = reference_backdrop(paths[0], result["points"])
    pictures: list[Path] = []
    if backdrop is None:
        result["notes"].append(f"mode shapes not drawn over the video: {why_not}")
    elif result["modes"]:
        prefix = str(figures[0])[: -len(FIGURE_SUFFIXES[0])]
        pictures = [Path(prefix + FRAME_SUFFIX)] + [Path(f"{prefix}_mode{m['mode']}.gif") for m in result["modes"]]
        check_outputs(pictures, inputs, option="--out or --figures")
    outputs = [*figures, *pictures, Path(out_json)]  # the JSON last: it is what other tools look for
    _write(result, diagnostics, modes, backdrop, outputs, units=units, pictures=bool(pictures))
    return {**result, "outputs": [str(p) for p in outputs]}


def _read_points(paths: list[Path]) -> tuple[list[Path], list[dict[str, Any]], list[str]]:
    """Every region of every CSV as a measurement point: its CSV, its measurement and how
    messages name it; refuses points that do not share their frame times."""
    found = [(path, data) for path in paths for data in read_measurements(path)]
    point_paths = [path for path, _ in found]
    measured = [data for _, data in found]
    where = [str(path) if data["region"] is None else f"{path} region {data['region']}" for path, data in found]
    _check_shared_times(where, measured)
    return point_paths, measured, where


def _identify(record: dict[str, Any], n_modes: int,
              band_hz: tuple[float, float] | None) -> tuple[list[dict[str, Any]], dict[str, Any]]:
    """The modes of the common record and the identification's diagnostics; notes a shortfall."""
    from refflow.modal import identify_with_diagnostics

    rate_hz = record["rate_hz"]
    if band_hz is not None and band_hz[1] > 0.5 * rate_hz:
        raise InputError(f"--band {band_hz[0]:g},{band_hz[1]:g}: {band_hz[1]:g} Hz is above the Nyquist "
                         f"frequency ({0.5 * rate_hz:.6g} Hz) of the {rate_hz:.6g} fps measurement: "
                         "lower the upper limit")
    try:
        modes, diagnostics = identify_with_diagnostics(record["series"], rate_hz, n_modes=n_modes,
                                                       band_hz=band_hz)
    except ValueError as err:
        samples, seconds = record["series"].shape[1], record["series"].shape[1] / rate_hz
        raise InputError(f"modal identification of the common record ({samples} samples, {seconds:.3g} s) "
                         f"failed: {err}: measure a longer record or widen --band") from None
    return modes, diagnostics


def _below_band(record: dict[str, Any], band_hz: tuple[float, float]) -> str | None:
    """A note where the record's strongest motion (the amplitude spectrum's peak, as `refflow
    plot` finds it) lies below the band searched, else None.

    The band's default floor (0.5 Hz) stays: below it a short record holds too few cycles
    for FDD and SSI to tell a mode from drift (a mode needs several cycles in the record;
    Tacoma's deck swings 2.4 times in 8.3 s). But the strongest motion of the record is
    never left out silently: the note names it and the --band that would search it.
    """
    series, rate_hz = record["series"], record["rate_hz"]
    strongest = series[int(np.argmax(np.std(series, axis=1)))]
    peak, _, _ = dominant_frequency(np.arange(strongest.size) / rate_hz, strongest)
    low, high = band_hz
    if peak is None or peak >= low:
        return None
    seconds = strongest.size / rate_hz
    lower = math.floor(8.0 * peak) / 10.0  # a fifth below the peak, to one decimal
    return (f"the record's strongest motion is at {peak:.3g} Hz ({peak * seconds:.1f} cycles in {seconds:.3g} s), "
            f"below the band searched ({low:g}-{high:g} Hz): not identified as a mode; pass --band {lower:g},{high:g} "
            "to search it (a longer record resolves it better)")


def _points(point_paths: list[Path], regions: list[int | None], record: dict[str, Any]) -> list[dict[str, Any]]:
    """The JSON's ``points``: name, CSV, direction, frames bridged, region and position where known."""
    points = []
    names = _point_names(point_paths, regions)
    for i, (path, region, name) in enumerate(zip(point_paths, regions, names, strict=True)):
        point: dict[str, Any] = {"name": name, "csv": str(path), "direction_px": record["directions"][i],
                                 "frames_bridged": record["bridged"][i]}
        if region is not None:
            point["region"] = region
        position = _poi_centroid(path, region)
        if position is not None:
            point["position_px"] = position
        points.append(point)
    return points


def _result(record: dict[str, Any], modes: list[dict[str, Any]], diagnostics: dict[str, Any],
            points: list[dict[str, Any]], *, units: str, direction: str, n_modes: int) -> dict[str, Any]:
    """What the modes JSON holds (``docs/formats.md``)."""
    rate_hz = record["rate_hz"]
    notes = list(record["notes"])
    if len(modes) < n_modes:
        notes.append(f"found {len(modes)} of the {n_modes} modes asked for: the FDD curve has only "
                     f"{len(modes)} prominent peak(s) in {diagnostics['band_hz'][0]:g}-"
                     f"{diagnostics['band_hz'][1]:g} Hz (see the stabilisation diagram)")
    return {
        "tool": "refflow modal",
        "method": "FDD peaks + SSI-cov (median over model orders), refflow.modal.identify",
        "points": points,
        "direction": direction,
        "units": {"displacement": units, "freq_hz": "Hz", "damping_ratio": "fraction of critical",
                  "shape": "real, normalised to max |.| = 1 (dimensionless), one value per point in "
                           "'points' order, + along the point's direction_px (image x right, y down)",
                  "position_px": "full-frame video pixels (x, y), from the sidecar's poi.centroid_px"},
        "record": {"rate_hz": rate_hz, "samples": int(record["series"].shape[1]),
                   "start_s": record["start_s"], "duration_s": record["series"].shape[1] / rate_hz,
                   "frames_trimmed": record["trimmed"],
                   "still_samples_skipped": int(diagnostics["still_samples"]),
                   "rate_identified_hz": float(diagnostics["rate_hz"])},
        "band_hz": [float(f) for f in diagnostics["band_hz"]],
        "n_modes_requested": n_modes,
        "modes": [_mode_entry(i, mode) for i, mode in enumerate(modes, start=1)],
        "notes": notes,
        "versions": versions(),
    }


def _write(result: dict[str, Any], diagnostics: dict[str, Any], modes: list[dict[str, Any]], backdrop: Any,
           outputs: list[Path], *, units: str, pictures: bool) -> None:
    """The figures, the pictures over the video (where ``pictures``) and the JSON, all or nothing."""
    text = json_text(result)  # a bad value fails before any file exists
    with atomic_paths(*outputs) as written:
        stabilisation_figure(diagnostics, modes, written[0], units=units)
        shapes_figure(result, written[1])
        if pictures:
            shapes_over_frame(result, backdrop, written[2])
            for mode, gif in zip(result["modes"], written[3:-1], strict=True):
                mode_animation(result, mode, backdrop, gif)
        written[-1].write_text(text)


def _check_options(paths: list[Path], n_modes: int, band_hz: tuple[float, float] | None, direction: str) -> None:
    if not paths:
        raise InputError("no CSV given: pass one `refflow track` CSV per measurement point")
    if direction not in DIRECTIONS:
        raise InputError(f"--direction {direction!r} is not one of {', '.join(DIRECTIONS)}")
    if isinstance(n_modes, bool) or not isinstance(n_modes, int) or n_modes < 1:
        raise InputError(f"--modes {n_modes!r} must be an integer >= 1")
    if band_hz is not None:
        lo, hi = band_hz
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo < hi):
            raise InputError(f"--band {lo:g},{hi:g} is not LO,HI in Hz with 0 <= LO < HI")
    resolved = [p.resolve() for p in paths]
    for i, path in enumerate(resolved):
        if path in resolved[:i]:
            raise InputError(f"{paths[i]} is given twice: each point's CSV once")


def _check_shared_times(paths: list[str], measured: list[dict[str, Any]]) -> None:
    """The points must be the same frames: identical frame times, within a thousandth of a frame."""
    first = measured[0]["time_s"]
    steps = np.diff(first[np.isfinite(first)])
    tolerance = 1e-3 * float(np.median(steps[steps > 0])) if (steps > 0).any() else 1e-9
    for path, data in zip(paths[1:], measured[1:], strict=True):
        times = data["time_s"]
        if times.shape != first.shape or not np.allclose(times, first, rtol=0.0, atol=tolerance, equal_nan=True):
            raise InputError(f"{paths[0]} and {path} do not share their frame times ({_span(first)} vs "
                             f"{_span(times)}): measure every point over the same frames of the same video "
                             "(same --frames/--max-frames and --fps)")


def _span(times: np.ndarray) -> str:
    finite = times[np.isfinite(times)]
    if not finite.size:
        return f"{times.size} frames"
    return f"{times.size} frames, {finite[0]:.6g}-{finite[-1]:.6g} s"


def _point_names(paths: list[Path], regions: list[int | None]) -> list[str]:
    """The CSVs' names without suffix (their folder too where two files share a name), and
    the region's label for a CSV of several regions."""
    files = list(dict.fromkeys(paths))
    stems = [p.stem for p in files]
    name_of = {p: f"{p.parent.name}/{p.stem}" if stems.count(p.stem) > 1 else p.stem for p in files}
    return [name_of[p] if region is None else f"{name_of[p]} region {region}"
            for p, region in zip(paths, regions, strict=True)]


def _direction(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Unit vector of the principal axis of the motion (dx, dy) over the finite frames."""
    ok = np.isfinite(dx) & np.isfinite(dy)
    xy = np.vstack([dx[ok] - dx[ok].mean(), dy[ok] - dy[ok].mean()])
    _, vectors = np.linalg.eigh(xy @ xy.T)
    return vectors[:, -1]


def _common_record(paths: list[str], measured: list[dict[str, Any]], units: str, direction: str) -> dict[str, Any]:
    """The points' displacements along their directions, shape (points, samples), on one uniform clock.

    The record spans the frames from the first to the last that every point measured
    (earlier and later frames cannot be bridged); inside it each point's invalid frames are
    bridged linearly. All points are put on the first CSV's clock: their times agree.
    """
    time_s = measured[0]["time_s"]
    valid = [np.isfinite(m[f"dx_{units}"]) & np.isfinite(m[f"dy_{units}"]) for m in measured]
    for path, ok in zip(paths, valid, strict=True):
        if ok.sum() < 4:
            raise InputError(f"{path} has {int(ok.sum())} valid frames: modal identification needs a "
                             "measured record")
    both = np.logical_and.reduce(valid) & np.isfinite(time_s)
    if both.sum() < 4:
        raise InputError(f"the points share {int(both.sum())} valid frames ({', '.join(map(str, paths))}): "
                         "too few for modal identification")
    first, last = np.flatnonzero(both)[[0, -1]]
    if direction == "auto":
        axes = [_direction(m[f"dx_{units}"], m[f"dy_{units}"]) for m in measured]
        # One sign for every point: along the principal axis of all points' motion, itself
        # pointing to +x or +y (image right or down) where it is larger.
        pooled_cov = np.zeros((2, 2))
        for m in measured:
            ok = np.isfinite(m[f"dx_{units}"]) & np.isfinite(m[f"dy_{units}"])
            xy = np.vstack([m[f"dx_{units}"][ok], m[f"dy_{units}"][ok]])
            xy -= xy.mean(axis=1, keepdims=True)
            pooled_cov += xy @ xy.T / max(ok.sum(), 1)
        pooled = np.linalg.eigh(pooled_cov)[1][:, -1]
        pooled *= np.sign(pooled[np.argmax(np.abs(pooled))])
        axes = [axis if axis @ pooled >= 0 else -axis for axis in axes]
    else:
        axes = [np.array([1.0, 0.0]) if direction == "dx" else np.array([0.0, 1.0])] * len(measured)
    window = slice(first, last + 1)
    series, grid, notes = [], None, []
    bridged = []
    for path, m, axis, ok in zip(paths, measured, axes, valid, strict=True):
        along = axis[0] * m[f"dx_{units}"] + axis[1] * m[f"dy_{units}"]
        point_grid, samples = resample_uniform(time_s[window], along[window])
        if grid is None:
            grid = point_grid
        series.append(samples)
        gaps = int(np.count_nonzero(~ok[window]))
        bridged.append(gaps)
        if gaps > _BRIDGED_WARN_FRAC * (last + 1 - first):
            notes.append(f"{path}: {gaps} of {last + 1 - first} frames invalid and bridged linearly: "
                         "its shape values rest on interpolation")
    assert grid is not None
    if all(np.ptp(samples) == 0 for samples in series):
        raise InputError(f"{', '.join(map(str, paths))}: the displacement is constant over the valid frames "
                         "(nothing moves): no vibration to identify; check the measurement's mask and method")
    trimmed = int(first + (len(time_s) - 1 - last))
    if trimmed:
        notes.append(f"{trimmed} frames at the start or end left out: not every point measured them")
    return {"series": np.vstack(series), "rate_hz": float(1.0 / (grid[1] - grid[0])),
            "start_s": float(grid[0]), "directions": [[float(a[0]), float(a[1])] for a in axes],
            "bridged": bridged, "trimmed": trimmed, "notes": notes}


def _poi_centroid(csv_path: Path, region: int | None = None) -> list[float] | None:
    """``poi.centroid_px`` [x, y] of the CSV's sidecar (of the region's entry in
    ``poi.regions``), where it is recorded (else None)."""
    sidecar = csv_path.with_suffix(".json")
    try:
        poi = json.loads(sidecar.read_text()).get("poi", {})
        if region is not None:
            poi = next((r for r in poi.get("regions", []) if r.get("label") == region), {})
        centroid = poi.get("centroid_px")
    except (OSError, ValueError, AttributeError, TypeError):
        return None  # a position is extra information; the CSV itself was read
    if (isinstance(centroid, (list, tuple)) and len(centroid) == 2
            and all(isinstance(v, (int, float)) and math.isfinite(v) for v in centroid)):
        return [float(centroid[0]), float(centroid[1])]
    return None


def _normalised(shape: list[float]) -> list[float]:
    values = np.asarray(shape, float)
    peak = values[int(np.argmax(np.abs(values)))]
    return (values / peak).tolist() if peak != 0 else values.tolist()


def _mode_entry(index: int, mode: dict[str, Any]) -> dict[str, Any]:
    from refflow.modal import mac

    return {"mode": index, "freq_hz": mode["freq_hz"], "damping_ratio": finite_or_none(mode["damping_ratio"]),
            "shape": _normalised(mode["shape"]),
            "fdd_freq_hz": mode["fdd_freq_hz"], "fdd_shape": _normalised(mode["fdd_shape"]),
            "mac_ssi_fdd": finite_or_none(mac(mode["shape"], mode["fdd_shape"])),
            "poles_used": mode["poles_used"]}


def stabilisation_figure(diagnostics: dict[str, Any], modes: list[dict[str, Any]], path: str | Path, *,
                         units: str) -> None:
    """Poles over model order (new / stable in frequency / stable) on the FDD curve, modes marked."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from refflow.modal import stabilisation

    lo, hi = diagnostics["band_hz"]
    fig, ax = plt.subplots(figsize=(9, 5.5))
    curve = ax.twinx()
    freq, s1 = diagnostics["freq_hz"], diagnostics["s1"]
    shown = (freq >= lo) & (freq <= hi) & (s1 > 0)
    curve.semilogy(freq[shown], s1[shown], color="0.35", lw=1.2, label="FDD: first singular value")
    curve.set_ylabel(f"first singular value of the spectral matrix ({units}$^2$/Hz)")
    styles = {0: dict(marker=".", color="0.65", s=10, label="new pole"),
              1: dict(marker="o", facecolors="none", edgecolors="tab:blue", s=22, label="stable frequency"),
              2: dict(marker="o", color="tab:green", s=22, label="stable (frequency, damping, shape)")}
    classes = stabilisation(diagnostics["poles"])
    for cls, style in styles.items():
        fs, orders = [], []
        for order, pol, kind in zip(diagnostics["orders"], diagnostics["poles"], classes, strict=True):
            keep = ((kind == cls) & (pol["freq_hz"] >= lo) & (pol["freq_hz"] <= hi)
                    & (pol["damping_ratio"] > 0) & (pol["damping_ratio"] < 0.3))
            fs.extend(pol["freq_hz"][keep])
            orders.extend([order] * int(keep.sum()))
        ax.scatter(fs, orders, zorder=3, **style)
    for i, mode in enumerate(modes, start=1):
        ax.axvline(mode["freq_hz"], color="tab:red", ls="--", lw=0.9)
        zeta = mode["damping_ratio"]
        text = f"mode {i}: {mode['freq_hz']:.4g} Hz" + (f", ζ {100 * zeta:.2g} %" if math.isfinite(zeta) else "")
        ax.annotate(text, (mode["freq_hz"], 0.97 - 0.06 * (i - 1)), xycoords=("data", "axes fraction"),
                    color="tab:red", fontsize=9, xytext=(4, -8), textcoords="offset points", zorder=4,
                    bbox={"boxstyle": "round,pad=0.2", "facecolor": "white", "edgecolor": "none", "alpha": 0.8})
    ax.set_xlim(lo, hi)
    orders = diagnostics["orders"]
    if orders:
        ax.set_ylim(0, max(orders) + 2)
    ax.set_xlabel("frequency (Hz)")
    ax.set_ylabel("model order (SSI-cov)")
    ax.set_title(f"Stabilisation diagram ({diagnostics['rate_hz']:.4g} Hz after decimation, "
                 f"{diagnostics['block_rows']} block rows)")
    ax.set_zorder(curve.get_zorder() + 1)  # poles over the curve
    ax.patch.set_visible(False)
    ax.grid(alpha=0.3)
    handles = ax.get_legend_handles_labels()
    curve_handles = curve.get_legend_handles_labels()
    ax.legend(handles[0] + curve_handles[0], handles[1] + curve_handles[1], loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def shapes_figure(result: dict[str, Any], path: str | Path) -> None:
    """One panel per mode: its shape over the points (bars, in the points' order)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    modes, points = result["modes"], result["points"]
    n = max(len(modes), 1)
    fig, axes = plt.subplots(1, n, figsize=(max(4.5, 1.0 + 0.6 * len(points)) * n, 4.5), squeeze=False)
    labels = [p["name"] + (f"\n({p['position_px'][0]:.0f}, {p['position_px'][1]:.0f}) px"
                           if "position_px" in p else "") for p in points]
    where = np.arange(len(points))
    along = {"auto": "displacement along its direction of motion", "dx": "dx", "dy": "dy"}[result["direction"]]
    for ax, mode in zip(axes[0], modes, strict=False):
        shape = np.asarray(mode["shape"])
        ax.bar(where, shape, color=np.where(shape >= 0, "tab:blue", "tab:orange"), width=0.6)
        ax.plot(where, shape, color="0.3", lw=0.8, marker="o", ms=3)
        zeta = mode["damping_ratio"]
        ax.set_title(f"mode {mode['mode']}: {mode['freq_hz']:.4g} Hz"
                     + (f", ζ = {100 * zeta:.2g} %" if zeta is not None else ", ζ n/a"), fontsize=10)
        ax.set_ylim(-1.15, 1.15)
        ax.axhline(0, color="0.2", lw=0.8)
        ax.set_xticks(where, labels, rotation=30 if len(points) > 4 else 0, fontsize=8)
        ax.set_xlabel(f"measurement point ({along})")
        ax.set_ylabel("mode shape (normalised, max |.| = 1)")
        ax.grid(axis="y", alpha=0.3)
    if not modes:
        axes[0][0].text(0.5, 0.5, "no mode identified in the band", ha="center", va="center",
                        transform=axes[0][0].transAxes)
        axes[0][0].set_axis_off()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def reference_backdrop(csv_path: Path, points: list[dict[str, Any]]) -> tuple[np.ndarray | None, str]:
    """The run's reference frame (full frame, grey uint8, undistorted as the run was) to draw the
    modes over, or None and why not: a point without a position, a sidecar that names no
    readable video (moved, or a run of another machine), a calibration file gone."""
    if not points or any("position_px" not in p for p in points):
        return None, "the points' positions are not known (no poi.centroid_px in the sidecars)"
    try:
        sidecar = json.loads(csv_path.with_suffix(".json").read_text())
        video = Path(sidecar["input"]["path"])
        index = int(sidecar.get("reference_frame") or 0)
        calibration = sidecar.get("calibration")
    except (OSError, ValueError, KeyError, TypeError):
        return None, f"{csv_path.with_suffix('.json')} names no input video"
    if calibration and list(calibration.get("video_origin", [0, 0])) != [0, 0]:
        return None, "the run's video is a window of the calibrated sensor (--video-origin)"
    from flow import inputs
    from flow.io.frames import as_uint8
    from flow.options import SourceOptions

    try:
        # The whole frame, undistorted as `refflow track` undistorts it.
        options = SourceOptions(str(video), calibration=calibration["file"] if calibration else None)
        source = inputs.source_from(options, need_time=False)
        undistort, _ = inputs.undistorter(options, source)
        frame = next((grey for _, _, grey in source.frames(index, index + 1)), None)
        if frame is not None and undistort is not None:
            frame = undistort(frame)
    except (InputError, OSError, KeyError, TypeError, ValueError) as err:
        return None, f"the run's video {str(video)!r} cannot be read again ({str(err).splitlines()[0]})"
    if frame is None:
        return None, f"the run's video {str(video)!r} has no frame {index} (the reference)"
    return as_uint8(frame), ""


def _point_arrays(result: dict[str, Any], mode: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
    """Positions (P, 2) and the mode's displacement (P, 2) of the points, image x right, y down:
    the shape value along each point's direction."""
    points = result["points"]
    where = np.array([p["position_px"] for p in points], float)
    direction = np.array([p["direction_px"] for p in points], float)
    return where, np.asarray(mode["shape"], float)[:, None] * direction


def _swing_px(backdrop: np.ndarray) -> float:
    return SWING_FRACTION * max(backdrop.shape)


def _mode_title(mode: dict[str, Any]) -> str:
    zeta = mode["damping_ratio"]
    return (f"mode {mode['mode']}: {mode['freq_hz']:.4g} Hz"
            + (f", ζ = {100 * zeta:.2g} %" if zeta is not None else ", ζ n/a"))


def shapes_over_frame(result: dict[str, Any], backdrop: np.ndarray, path: str | Path) -> None:
    """One panel per mode over the reference frame: each point at its position, the mode's
    deflected shape (points moved by the exaggerated shape, joined in the points' order) in
    both phases of the cycle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from flow.figures import region_colour

    modes = result["modes"]
    height, width = backdrop.shape
    panel = 6.0 * width / max(height, width) + 1.0
    fig, axes = plt.subplots(1, len(modes), figsize=(panel * len(modes), 6.0 * height / max(height, width) + 1.0),
                             squeeze=False)
    swing = _swing_px(backdrop)
    for ax, mode in zip(axes[0], modes, strict=True):
        where, moved = _point_arrays(result, mode)
        ax.imshow(backdrop, cmap="gray", vmin=0, vmax=255)
        ax.plot(where[:, 0], where[:, 1], color="0.85", lw=1, ls=":", label="rest")
        for sign, style in ((1.0, "-"), (-1.0, "--")):
            bent = where + sign * swing * moved
            ax.plot(bent[:, 0], bent[:, 1], color="tab:red", lw=1.6, ls=style,
                    label="deflected (exaggerated)" if sign > 0 else "half a cycle later")
        for i, (point, (x, y)) in enumerate(zip(result["points"], where, strict=True)):
            colour = np.array(region_colour(point.get("region", i + 1))[::-1]) / 255.0  # BGR -> RGB
            ax.annotate("", xy=(x + swing * moved[i, 0], y + swing * moved[i, 1]), xytext=(x, y),
                        arrowprops={"arrowstyle": "->", "color": colour, "lw": 1.8})
            ax.plot([x], [y], "o", ms=5, color=colour, mec="white", mew=0.8)
            ax.annotate(point["name"], (x, y), xytext=(5, 5), textcoords="offset points", fontsize=7,
                        color="white", bbox={"boxstyle": "round,pad=0.15", "fc": "black", "alpha": 0.5, "ec": "none"})
        ax.set_title(_mode_title(mode), fontsize=10)
        ax.set_xlim(0, width)
        ax.set_ylim(height, 0)
        ax.set_axis_off()
    axes[0][0].legend(loc="lower left", fontsize=7, framealpha=0.7)
    fig.suptitle(f"Mode shapes over the reference frame (largest swing drawn as {swing:.0f} px)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def mode_animation(result: dict[str, Any], mode: dict[str, Any], backdrop: np.ndarray, path: str | Path) -> None:
    """An animated GIF of one cycle of ``mode`` over the reference frame: the points swing
    along their directions by the exaggerated shape, joined in the points' order."""
    import cv2
    from PIL import Image

    from flow.figures import region_colour

    scale = min(1.0, ANIMATION_MAX_WIDTH / backdrop.shape[1])
    base = cv2.cvtColor(cv2.resize(backdrop, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
                        if scale < 1.0 else backdrop, cv2.COLOR_GRAY2RGB)
    where, moved = _point_arrays(result, mode)
    where, swing = where * scale, _swing_px(base)
    colours = [region_colour(p.get("region", i + 1))[::-1] for i, p in enumerate(result["points"])]  # RGB
    shift = 4  # drawn with 1/16 px precision
    frames = []
    for k in range(ANIMATION_FRAMES):
        bent = where + np.sin(2 * np.pi * k / ANIMATION_FRAMES) * swing * moved
        image = base.copy()
        cv2.polylines(image, [np.round(where * (1 << shift)).astype(np.int32)], False, (200, 200, 200), 1,
                      cv2.LINE_AA, shift)
        cv2.polylines(image, [np.round(bent * (1 << shift)).astype(np.int32)], False, (230, 40, 40), 2,
                      cv2.LINE_AA, shift)
        for (x, y), colour in zip(bent, colours, strict=True):
            cv2.circle(image, (int(round(x * (1 << shift))), int(round(y * (1 << shift)))), 5 << shift,
                       colour, -1, cv2.LINE_AA, shift)
        cv2.putText(image, _mode_title(mode).replace("ζ", "zeta"), (8, 20), cv2.FONT_HERSHEY_SIMPLEX, 0.5,
                    (255, 255, 0), 1, cv2.LINE_AA)
        frames.append(Image.fromarray(image))
    # One palette for the whole cycle, no dithering: a small file whose backdrop does not flicker.
    palette = frames[0].quantize(colors=255, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    frames = [f.quantize(palette=palette, dither=Image.Dither.NONE) for f in frames]
    frames[0].save(path, format="GIF", save_all=True, append_images=frames[1:], duration=ANIMATION_FRAME_MS,
                   loop=0, optimize=False)


def _parse_band(text: str | None) -> tuple[float, float] | None:
    if text is None:
        return None
    try:
        lo, hi = (float(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--band {text!r} is not LO,HI (two frequencies in Hz, e.g. 0.5,25)") from None
    return lo, hi


def cmd_modal(args: argparse.Namespace) -> int:
    result = run_modal(args.csv, out_json=args.out, out_prefix=args.figures, n_modes=args.modes,
                       band_hz=_parse_band(args.band), direction=args.direction)
    names = [p["name"] for p in result["points"]]
    for note in result["notes"]:
        print(f"refflow modal: warning: {note}", file=sys.stderr)
    print(f"points: {', '.join(names)} ({result['units']['displacement']}, {result['record']['samples']} samples "
          f"at {result['record']['rate_hz']:.6g} Hz, band {result['band_hz'][0]:g}-{result['band_hz'][1]:g} Hz)")
    for mode in result["modes"]:
        zeta = mode["damping_ratio"]
        shape = ", ".join(f"{v:+.3f}" for v in mode["shape"])
        print(f"mode {mode['mode']}: {mode['freq_hz']:.4f} Hz, damping "
              + (f"{100 * zeta:.3g} %" if zeta is not None else "n/a (no stable pole)")
              + f", shape [{shape}]")
    print(f"-> {', '.join(result['outputs'])}")
    return 0


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``refflow modal`` to the ``refflow`` subcommands; returns its parser."""
    p = subparsers.add_parser(
        "modal", help="natural frequencies, damping and mode shapes from several measured points (FDD + SSI)",
        description="Output-only modal identification of `refflow track` CSVs, one per measurement point "
                    "or one run of several regions (same video, same frames): frequencies, damping ratios and mode shapes to a JSON, "
                    "with a stabilisation diagram and a mode-shape figure.")
    p.add_argument("csv", nargs="+", help="`refflow track` CSVs sharing their frame times: one per measurement "
                   "point, or CSVs of several regions (each region a point); the shapes list the points "
                   "in this order")
    p.add_argument("--out", required=True, help="output JSON (frequencies, damping ratios, shapes, points)")
    p.add_argument("--figures", metavar="PREFIX", help="figures PREFIX_stabilisation.png and PREFIX_shapes.png "
                   "(default: the --out path without its suffix)")
    p.add_argument("--modes", type=int, default=2, metavar="N",
                   help="number of modes: the N most prominent peaks of the FDD curve (default 2)")
    p.add_argument("--band", metavar="LO,HI", help="frequency band searched, Hz (default 0.5 Hz to 0.4 x the "
                   "frame rate)")
    p.add_argument("--direction", choices=DIRECTIONS, default="auto",
                   help="displacement used: auto (each point's principal direction of motion, signs agreeing), "
                        "dx or dy (default auto)")
    p.set_defaults(func=cmd_modal)
    return p
