"""Figures of the measurement tool.

POI versus corner figure (paper Fig. 6): what the mask selects and what KLT
would track; time history and spectrum of measured CSVs (``refflow plot``),
with each series' dominant frequency.
"""

from __future__ import annotations

import json
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np

from flow.io.errors import InputError
from flow.io.frames import as_uint8
from refflow import trackcsv
from refflow.figures import poi_figure as draw_poi_figure
from refflow.figures import region_colour  # noqa: F401  (flow.modal's figures)
from refflow.io import atomic_path
from refflow.spectra import pick_peaks


def poi_figure(reference: np.ndarray, poi_xy: np.ndarray, corners_xy: np.ndarray,
               path: str | Path, *, scale: int | None = None, region: np.ndarray | None = None) -> None:
    """:func:`refflow.figures.poi_figure` (paper Fig. 6, shared with ``analysis``) of a reference
    in any dtype (rounded and clipped to uint8, as KLT's corner detection sees it)."""
    draw_poi_figure(as_uint8(reference), poi_xy, corners_xy, path, scale=scale, region=region)


def read_measurements(path: str | Path) -> list[dict[str, Any]]:
    """Columns of a ``refflow track`` CSV (read by :func:`refflow.trackcsv.read`), invalid
    frames as NaN, and its method (from the sidecar): one dict per region (one for a run of
    one region), in label order.

    Each holds ``time_s``, ``dx_px``, ``dy_px``, ``dx_mm``, ``dy_mm`` arrays, ``has_mm`` (a
    scale was given), ``label`` (the method; "method region K" in a run of several),
    ``region`` (the label K, None for a run of one region) and ``flagged``: the readings the
    flagged frames keep (``valid=0``), the same columns NaN elsewhere, for a figure to show
    apart; nothing else here uses them.
    """
    path = Path(path)
    try:
        regions = trackcsv.read(path)
    except trackcsv.TrackCsvError as err:
        raise InputError(str(err)) from None
    method = path.stem
    sidecar = path.with_suffix(".json")
    if sidecar.is_file():
        try:
            method = json.loads(sidecar.read_text()).get("method", method)
        except (OSError, ValueError, AttributeError):
            pass  # the label is cosmetic; the CSV itself was read
    out = []
    for key, columns in regions.items():
        if len(columns["time_s"]) < 4:
            where = "" if key is None else f" in region {key}"
            raise InputError(f"{str(path)!r} has {len(columns['time_s'])} frames{where}: a spectrum needs at least 4")
        valid = columns["valid"] != 0
        data: dict[str, Any] = {name: columns[name] if name == "time_s" else np.where(valid, columns[name], np.nan)
                                for name in ("time_s", "dx_px", "dy_px", "dx_mm", "dy_mm")}
        data["flagged"] = {name: np.where(valid, np.nan, columns[name]) for name in ("dx_px", "dy_px", "dx_mm", "dy_mm")}
        data["has_mm"] = bool(np.isfinite(data["dx_mm"]).any() or np.isfinite(data["flagged"]["dx_mm"]).any())
        data["label"] = method if key is None else f"{method} region {key}"
        data["region"] = key
        out.append(data)
    return out


def read_measurement(path: str | Path) -> dict[str, Any]:
    """:func:`read_measurements` of a CSV of one region (refused for several: name a region)."""
    found = read_measurements(path)
    if len(found) > 1:
        raise InputError(f"{str(path)!r} holds {len(found)} regions: this command reads one measurement point")
    return found[0]


def resample_uniform(time_s: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Samples on a uniform clock (median frame interval), gaps (NaN) linearly bridged.

    Variable-frame-rate videos and invalid frames both leave the series uneven;
    an FFT needs even samples.
    """
    ok = np.isfinite(time_s) & np.isfinite(values)
    if ok.sum() < 4:
        return np.zeros(0), np.zeros(0)
    t, v = time_s[ok], values[ok]
    steps = np.diff(time_s[np.isfinite(time_s)])
    dt = float(np.median(steps[steps > 0])) if (steps > 0).any() else 1.0
    grid = np.arange(t[0], t[-1] + dt / 2, dt)
    return grid, np.interp(grid, t, v)


def dominant_frequency(time_s: np.ndarray, values: np.ndarray, *,
                       min_hz: float | None = None) -> tuple[float | None, np.ndarray, np.ndarray]:
    """Frequency (Hz) of the largest spectral peak of a displacement series.

    The series is put on a uniform clock, detrended (a linear drift such as
    KLT's would otherwise dominate the lowest bins), Hann-windowed and
    zero-padded 8x; the peak is refined by a parabola through its three bins.
    Peaks below ``min_hz`` (default: one cycle per record, which cannot be
    called periodic) are ignored. Returns ``(f_hz or None, freqs_hz, amplitude)``.
    """
    grid, samples = resample_uniform(np.asarray(time_s, float), np.asarray(values, float))
    if grid.size < 4:
        return None, np.zeros(0), np.zeros(0)
    dt = grid[1] - grid[0]
    samples = samples - np.polyval(np.polyfit(grid - grid[0], samples, 1), grid - grid[0])
    window = np.hanning(samples.size)
    n_fft = 8 * int(2 ** math.ceil(math.log2(samples.size)))
    amplitude = np.abs(np.fft.rfft(samples * window, n_fft)) * 2 / window.sum()
    freqs = np.fft.rfftfreq(n_fft, dt)
    floor = min_hz if min_hz is not None else 1.0 / (samples.size * dt)
    peaks = pick_peaks(freqs, amplitude, count=1, min_hz=floor, rel_prominence=0.0)
    return (peaks[0]["freq_hz"] if peaks else None), freqs, amplitude


def spectrum_figure(series: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], path: str | Path, *,
                    units: str = "px", title: str = "", min_hz: float | None = None,
                    flagged: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None) -> dict[str, dict[str, Any]]:
    """Time histories (dx, dy) and amplitude spectra of ``{label: (time_s, dx, dy)}``, overlaid.

    The spectra are of one axis for every series, so they compare: the axis
    along which the first series moves most (larger standard deviation). Each
    series' dominant frequency on that axis is marked. ``flagged`` (same keys) holds the
    readings of the frames flagged ``valid=0``: drawn grey in the time histories, never in
    the spectra. Returns, per label, ``{"dx": Hz, "dy": Hz, "main": "dx" | "dy"}`` (None
    where no peak).
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8))
    summary: dict[str, dict[str, Any]] = {}
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    # the first series that has a value (a run whose every frame was flagged has none)
    _, first_dx, first_dy = next((s for s in series.values() if np.isfinite(s[1]).any() or np.isfinite(s[2]).any()),
                                 next(iter(series.values())))
    with np.errstate(all="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        main = "dx" if not np.nanstd(first_dy) > np.nanstd(first_dx) else "dy"
    for i, (label, (time_s, dx, dy)) in enumerate(series.items()):
        colour = colours[i % len(colours)]
        grey = (flagged or {}).get(label)
        if grey is not None and (np.isfinite(grey[1]).any() or np.isfinite(grey[2]).any()):
            for ax, values in zip(axes[:2], grey[1:], strict=True):
                ax.plot(grey[0], values, ".", ms=2.5, color="0.6", label=f"{label}: flagged (valid=0)")
        axes[0].plot(time_s, dx, lw=1.1, color=colour, label=label)
        axes[1].plot(time_s, dy, lw=1.1, color=colour, label=label)
        peaks: dict[str, Any] = {}
        spectra = {}
        for axis, values in (("dx", dx), ("dy", dy)):
            peaks[axis], freqs, amplitude = dominant_frequency(time_s, values, min_hz=min_hz)
            spectra[axis] = (freqs, amplitude)
        peaks["main"] = main
        summary[label] = peaks
        freqs, amplitude = spectra[main]
        if freqs.size:
            axes[2].plot(freqs, amplitude, lw=1.1, color=colour, label=label)
        if peaks[main] is not None:
            axes[2].axvline(peaks[main], color=colour, ls="--", lw=0.9)
            axes[2].annotate(f"{peaks[main]:.3f} Hz", (peaks[main], 0.92 - 0.08 * i), xycoords=("data", "axes fraction"),
                             color=colour, fontsize=9, xytext=(4, 0), textcoords="offset points")
    axes[0].set_ylabel(f"dx ({units})")
    axes[1].set_ylabel(f"dy ({units})")
    axes[1].set_xlabel("time (s)")
    axes[2].set_xlabel("frequency (Hz)")
    axes[2].set_ylabel(f"{main} amplitude ({units})")
    # Show the band around the peaks rather than all the way to Nyquist, where nothing is.
    nyquist = min(0.5 / float(np.median(np.diff(t))) for t, _, _ in series.values())
    found = [p[p["main"]] for p in summary.values() if p[p["main"]] is not None]
    axes[2].set_xlim(0, min(nyquist, max(2.0, 4 * max(found))) if found else nyquist)
    for ax in axes:
        ax.grid(alpha=0.3)
        if ax.get_legend_handles_labels()[0]:  # a spectrum of only flagged readings has none
            ax.legend(loc="upper right", fontsize=8)
    if title:
        axes[0].set_title(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
    return summary
