"""Read the stage files documented in ``docs/formats.md`` with clear errors.

``analysis`` only reads files: it never imports ``sim`` or ``flow``. Every
reader checks that the documented columns exist and hold finite numbers, and
raises ``ValueError`` naming the file and the column otherwise (the CLI turns
that into exit code 2).
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from refflow import trackcsv
from refflow.csvtable import read_rows

SENSOR_COLUMNS = ("time_s", "dx_mm")
TRUTH_COLUMNS = ("frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded")
# A frame's reading and its uncertainty: NaN on flagged frames for analysis (see read_track).
DISPLACEMENT_COLUMNS = ("dx_px", "dy_px", "dx_mm", "dy_mm", "sigma_dx_px", "sigma_dy_px", "sigma_px")
_HEIGHT_COLUMN = re.compile(r"^dx_mm_z(\d{4})$")


def read_csv_columns(path: str | os.PathLike[str], required: tuple[str, ...],
                     *, finite: tuple[str, ...] | None = None) -> dict[str, np.ndarray]:
    """Read a numeric CSV with a header into ``{column: float array}``.

    Parameters
    ----------
    path : path-like
        CSV file with one header line.
    required : tuple of str
        Columns that must be present.
    finite : tuple of str, optional
        Columns that must not contain NaN/inf (default: all ``required``).

    Raises
    ------
    ValueError
        If the file is missing, empty, lacks a required column, holds a
        non-numeric cell, or a ``finite`` column holds NaN/inf.
    """
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    header, rows = read_rows(path, required)
    columns: dict[str, np.ndarray] = {}
    for j, name in enumerate(header):
        values = np.empty(len(rows))
        for i, row in enumerate(rows):
            cell = row[j].strip() if j < len(row) else ""
            try:
                values[i] = float(cell) if cell != "" else np.nan
            except ValueError:
                if name in required:
                    raise ValueError(f"{path}: column {name!r} row {i + 2} is not a number: "
                                     f"{cell!r}") from None
                values[i] = np.nan
        columns[name] = values
    for name in (required if finite is None else finite):
        bad = ~np.isfinite(columns[name])
        if bad.any():
            first = int(np.flatnonzero(bad)[0])
            raise ValueError(f"{path}: column {name!r} has {int(bad.sum())} NaN/inf value(s), "
                             f"first at data row {first + 1}")
    if "time_s" in columns and np.any(np.diff(columns["time_s"]) <= 0):
        raise ValueError(f"{path}: column 'time_s' is not strictly increasing")
    return columns


def read_json(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Read a JSON sidecar; ``ValueError`` naming the file if absent or broken."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"{path}: file not found")
    try:
        return json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: not valid JSON ({exc})") from None


@dataclass
class Sensor:
    """Laser-sensor reference: ``time_s`` (sensor clock) and ``dx_mm`` (world x)."""

    time_s: np.ndarray
    dx_mm: np.ndarray
    heights: dict[float, np.ndarray]  # extra heights in mm -> dx_mm series

    @property
    def rate_hz(self) -> float:
        return float(1.0 / np.median(np.diff(self.time_s)))


def read_sensor(path: str | os.PathLike[str]) -> Sensor:
    cols = read_csv_columns(path, SENSOR_COLUMNS)
    heights = {}
    for name, values in cols.items():
        match = _HEIGHT_COLUMN.match(name)
        if match:
            if not np.all(np.isfinite(values)):
                raise ValueError(f"{path}: column {name!r} has NaN/inf values")
            heights[float(match.group(1))] = values
    return Sensor(cols["time_s"], cols["dx_mm"], heights)


def read_truth(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    return read_csv_columns(path, TRUTH_COLUMNS)


def read_track(path: str | os.PathLike[str]) -> dict[str, np.ndarray]:
    """Track CSV of one measurement point (format and reader: :mod:`refflow.trackcsv`), times
    strictly increasing; displacement cells may be NaN only on frames flagged ``valid=0``.

    A method is judged on the frames it vouches for: the readings that a flagged frame keeps in
    the file (``valid=0``) are NaN here, so no metric, alignment or figure uses them.

    A ``dx_mm`` column that is NaN throughout (flow run without a scale) is
    accepted: callers then convert ``dx_px`` with the render's ``mm_per_px``
    (see :func:`track_mm`).
    """
    regions = trackcsv.read(path)
    if len(regions) > 1:
        raise ValueError(f"{path}: holds {len(regions)} regions (a region column): evaluate one "
                         "measurement point, the CSV of a run of one region")
    (cols,) = regions.values()
    if np.any(np.diff(cols["time_s"]) <= 0):
        raise ValueError(f"{path}: column 'time_s' is not strictly increasing")
    valid = cols["valid"] != 0
    names = ("dx_px",) if np.all(np.isnan(cols["dx_mm"])) else ("dx_px", "dx_mm")
    for name in names:
        bad = valid & ~np.isfinite(cols[name])
        if bad.any():
            raise ValueError(f"{path}: column {name!r} has {int(bad.sum())} NaN/inf value(s) "
                             "on frames flagged valid=1 (flag them valid=0 or fill them)")
    for name in DISPLACEMENT_COLUMNS:
        if name in cols:
            cols[name] = np.where(valid, cols[name], np.nan)
    return cols


def track_mm(track: dict[str, np.ndarray], mm_per_px: float) -> tuple[np.ndarray, bool]:
    """``dx_mm`` of a track, from ``dx_px * mm_per_px`` when the tracker had no scale."""
    if np.all(np.isnan(track["dx_mm"])):
        return track["dx_px"] * mm_per_px, True
    return track["dx_mm"], False


def model_modes_hz(sim_json: dict[str, Any], source: str = "sim.json") -> np.ndarray:
    """The model's natural frequencies (``model_hz``) as a float array."""
    if "model_hz" not in sim_json:
        raise ValueError(f"{source}: missing key 'model_hz' (modal table of the model)")
    raw = sim_json["model_hz"]
    if isinstance(raw, dict):  # tolerate {"1": f1, ...}
        raw = [raw[k] for k in sorted(raw, key=lambda k: int(re.sub(r"\D", "", str(k)) or 0))]
    values = np.asarray(raw, dtype=float).ravel()
    if values.size == 0 or not np.all(np.isfinite(values)):
        raise ValueError(f"{source}: 'model_hz' must be a non-empty list of finite numbers")
    return values


def release_time_s(sim_json: dict[str, Any]) -> float:
    """When a pluck lets the beam go (simulation time, s); 0.0 without a pluck.

    sim.json's ``parameters.excitation`` lists each component as ``{"type", "params":
    [[key, value], ...]}`` (sim/beam.py); before the pluck's ``start_s`` the beam is held.
    """
    parameters = sim_json.get("parameters")
    components = parameters.get("excitation", []) if isinstance(parameters, dict) else []
    for component in components or []:
        if isinstance(component, dict) and component.get("type") == "pluck":
            params = dict(component.get("params") or [])
            start = params.get("start_s", 0.0)
            return float(start) if start is not None else 0.0
    return 0.0


def render_scale(render_json: dict[str, Any], source: str = "render.json") -> tuple[float, float]:
    """``(mm_per_px, fps)`` from the render sidecar."""
    for key in ("mm_per_px", "fps"):
        if key not in render_json:
            raise ValueError(f"{source}: missing key {key!r}")
    mm_per_px, fps = float(render_json["mm_per_px"]), float(render_json["fps"])
    if not (mm_per_px > 0 and fps > 0):
        raise ValueError(f"{source}: mm_per_px={mm_per_px} and fps={fps} must be positive")
    return mm_per_px, fps
