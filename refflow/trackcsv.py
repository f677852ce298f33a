"""The track CSV of ``refflow track`` and ``refflow merge`` (docs/formats.md), defined once:
its columns in order with their units, the ``region`` column of a run of several regions,
the writer, and the one reader that ``flow`` (plot, modal, export, the GUI) and
``analysis`` (evaluate, figures) share.
"""

from __future__ import annotations

import csv
import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from refflow.csvtable import read_rows

# The columns in the file's order, each with the unit and meaning the sidecar's ``units``
# gives it (None: the sidecar gives none).
COLUMNS: dict[str, str | None] = {
    "frame": None,
    "time_s": "s",
    # Every frame keeps its reading, flagged or not: valid = 0 qualifies the number (the
    # readers of plot, modal, export, the GUI and analysis use valid frames only).
    "dx_px": "px, + = image right",
    "dy_px": "px, + = image down",
    "dx_mm": "mm",
    "dy_mm": "mm",
    "valid": "1: a reading the tool vouches for; 0: flagged, the reading kept beside the flag",
    "sigma_dx_px": "px, standard uncertainty of dx_px",
    "sigma_dy_px": "px, standard uncertainty of dy_px",
    "sigma_px": "px, standard uncertainty of the displacement vector, sqrt(sigma_dx_px^2 + sigma_dy_px^2)",
    "poi_kept_frac": "fraction of kept POIs measured and consistent with the frame's median",
    "residual": "grey levels (0-255)",
    "flow_spread_px": "px (1.4826 MAD over kept POIs)",
    "camera_dx_px": "px, the camera's image motion at the POIs (removed from dx_px); NaN without --background-mask",
    "camera_dy_px": None,
}
# What every track CSV holds (a reader refuses a file without them); the other columns are
# read where present.
REQUIRED = ("frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid")
# A run of several regions: this column follows ``time_s`` and holds the row's region label
# (1..N); rows go frame by frame, the regions of a frame in label order. A run of one region
# has no such column.
REGION = "region"
REGION_UNIT = "label of the mask region the row measures (1..N)"
_ALWAYS_FINITE = ("frame", "time_s", "valid")


class TrackCsvError(ValueError):
    """A file that is not a readable track CSV; the message names the file and the problem."""


def columns(*, regions: bool) -> list[str]:
    """The header of a run of one region (``regions`` False) or of several."""
    names = list(COLUMNS)
    if regions:
        names.insert(names.index("time_s") + 1, REGION)
    return names


def units(*, regions: bool) -> dict[str, str]:
    """Unit and meaning of the columns that have one (the sidecar's ``units``)."""
    found = {name: unit for name, unit in COLUMNS.items() if unit is not None}
    return {**found, REGION: REGION_UNIT} if regions else found


def write(handle: TextIO, series: Sequence[tuple[int, Iterable[Mapping[str, Any]]]]) -> None:
    """Write each region's rows, ``[(label, rows), ...]`` in label order, to an open text file.

    A row maps the :data:`COLUMNS` to values; floats are written with 9 significant digits.
    One region: no ``region`` column. Several: the label in a ``region`` column, one row
    per frame and region, frame by frame (every region has a row for every frame).
    """
    several = len(series) > 1
    writer = csv.DictWriter(handle, fieldnames=columns(regions=several))
    writer.writeheader()
    labels = [label for label, _ in series]
    for rows in zip(*(rows for _, rows in series), strict=True):
        for label, row in zip(labels, rows, strict=True):
            values = {**row, REGION: int(label)} if several else row
            writer.writerow({k: (f"{v:.9g}" if isinstance(v, float) else v) for k, v in values.items()})


def read(path: str | os.PathLike[str]) -> dict[int | None, dict[str, np.ndarray]]:
    """Every column of a track CSV as float arrays, per region.

    Returns ``{None: columns}`` for a run of one region (no ``region`` column), else
    ``{label: columns}`` in label order (the ``region`` column itself left out). Empty
    cells read as NaN.

    Raises
    ------
    TrackCsvError
        If the file is missing, lacks one of the :data:`REQUIRED` columns or any row, holds
        a cell that is not a number in a required column (elsewhere such a cell is NaN) or
        NaN in ``frame``, ``time_s`` or ``valid``, or a region that is no label 1..N.
    """
    path = Path(path)
    if not path.is_file():
        raise TrackCsvError(f"{path}: does not exist: pass the --out CSV of `refflow track`")
    header, rows = read_rows(path, REQUIRED, error=TrackCsvError, describe_missing=lambda missing, found: (
        f"not a `refflow track` CSV: no {', '.join(missing)} column (found {','.join(found) or 'no header'})"))
    cells = {name: [row[j].strip() if j < len(row) else "" for row in rows] for j, name in enumerate(header)}
    found = {name: _numbers(path, name, values) for name, values in cells.items() if name != REGION}
    for name in _ALWAYS_FINITE:
        bad = ~np.isfinite(found[name])
        if bad.any():
            raise TrackCsvError(f"{path}: column {name!r} has {int(bad.sum())} NaN/inf value(s), "
                                f"first at data row {int(np.flatnonzero(bad)[0]) + 1}")
    if REGION not in cells:
        return {None: found}
    labels = _labels(path, cells[REGION])
    return {int(label): {name: values[labels == label] for name, values in found.items()}
            for label in np.unique(labels)}


def _numbers(path: Path, name: str, cells: list[str]) -> np.ndarray:
    values = np.empty(len(cells))
    for i, cell in enumerate(cells):
        try:
            values[i] = float(cell) if cell != "" else np.nan
        except ValueError:
            if name in REQUIRED:
                raise TrackCsvError(f"{path}: column {name!r} row {i + 2} is not a number: {cell!r}") from None
            values[i] = np.nan
    return values


def _labels(path: Path, cells: list[str]) -> np.ndarray:
    labels = np.empty(len(cells), np.int64)
    for i, cell in enumerate(cells):
        try:
            labels[i] = int(cell)
        except ValueError:
            labels[i] = 0
        if labels[i] < 1:
            raise TrackCsvError(f"{path}: region {cell!r} in row {i + 2} is not a label (1..N)")
    return labels
