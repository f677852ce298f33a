"""Export a measurement for modal-analysis software: universal file format (UFF) dataset 58.

Dataset 58 ("function at nodal DOF") is the time-history record that modal software
(e.g. the MATLAB/LMS/ME'scope importers, pyuff, OpenModal) reads. Each direction of the
measurement becomes one record: response node 1 (the POIs' mean; node K for region K of a
run of several regions), direction +X (``dx``) or +Y (``dy``), a time response (function type 1), abscissa time in s, ordinate displacement
in m (SI, the CSV's mm / 1000; a dataset 164 before them says SI), or in px where the run
had no scale (said in the record's ID lines: no physical unit). The samples are put
on a uniform clock (the median frame interval; modal software expects even spacing) and
invalid frames are bridged linearly, as for the spectrum (:func:`flow.figures.resample_uniform`);
ID line 4 says how many frames were bridged.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import numpy as np

from flow.figures import read_measurements, resample_uniform
from flow.io.errors import InputError
from flow.outputs import check_outputs
from refflow.io import atomic_path

# UFF codes: function type 1 = time response; specific data types 17 = time, 8 = displacement;
# directions +1 = +X, +2 = +Y.
_TIME_RESPONSE, _TIME, _DISPLACEMENT = 1, 17, 8
_DIRECTIONS = {"dx": 1, "dy": 2}


def uff58_records(csv_path: str | Path) -> list[dict[str, Any]]:
    """The records (pyuff's dictionaries) of a ``refflow track`` CSV: units (dataset 164),
    then one time history (dataset 58) per direction and region (node = region)."""
    found = read_measurements(csv_path)
    has_mm = all(data["has_mm"] for data in found)
    unit, column_unit, factor = ("m", "mm", 1e-3) if has_mm else ("px", "px", 1.0)
    records: list[dict[str, Any]] = [{
        "type": 164, "units_code": 1, "units_description": "SI units", "temp_mode": 2,
        "length": 1.0, "force": 1.0, "temp": 1.0, "temp_offset": 273.15}]
    for data, (column, direction) in ((d, item) for d in found for item in _DIRECTIONS.items()):
        node = 1 if data["region"] is None else int(data["region"])
        mean_of = "the POIs' mean" if data["region"] is None else f"region {node}'s POIs' mean"
        values = data[f"{column}_{column_unit}"] * factor
        grid, series = resample_uniform(data["time_s"], values)
        if grid.size < 4:
            where = "" if data["region"] is None else f" of region {node}"
            raise InputError(f"{str(csv_path)!r}: fewer than 4 valid frames in {column}{where}: nothing to export")
        bridged = int(np.count_nonzero(~np.isfinite(values)))
        step = float(grid[1] - grid[0])
        records.append({
            "type": 58, "binary": 0, "func_type": _TIME_RESPONSE,
            "id1": f"refflow {data['label']}: {column} of {mean_of}",
            "id2": f"source {Path(csv_path).name}",
            "id3": f"displacement in {unit}" + (" (CSV mm / 1000)" if unit == "m" else " (no scale: not SI)"),
            "id4": f"{bridged} invalid frames bridged linearly; uniform step {step:.9g} s",
            "id5": "NONE",
            "rsp_node": node, "rsp_dir": direction, "ref_node": 0, "ref_dir": 0,
            "rsp_ent_name": "refflow", "ref_ent_name": "NONE",
            "abscissa_spacing": 1, "abscissa_min": float(grid[0]), "abscissa_inc": step,
            "abscissa_spec_data_type": _TIME, "abscissa_axis_units_lab": "s",
            "ordinate_spec_data_type": _DISPLACEMENT, "ordinate_axis_units_lab": unit,
            "orddenom_spec_data_type": 0, "orddenom_axis_units_lab": "NONE",
            "z_axis_spec_data_type": 0, "z_axis_axis_units_lab": "NONE", "z_axis_value": 0.0,
            "load_case_id": 0, "ver_num": 0,
            **{f"{axis}_{unit_of}_unit_exp": 0 for axis in ("abscissa", "ordinate", "orddenom", "z_axis")
               for unit_of in ("len", "force", "temp")},
            "ordinate_len_unit_exp": 1 if unit == "m" else 0,  # displacement: length^1
            "data": series.astype(np.float64), "x": grid.astype(np.float64),
        })
    return records


def write_uff(csv_path: str | Path, out_path: str | Path) -> int:
    """Write the units (dataset 164) and time-history records (dataset 58) of ``csv_path`` to the
    UFF file ``out_path`` (all or nothing); returns the number of time histories."""
    import pyuff

    csv_path, out_path = Path(csv_path), Path(out_path)
    check_outputs([out_path], [(f"the CSV {csv_path}", csv_path),
                               (f"{csv_path}'s sidecar", csv_path.with_suffix(".json"))])
    records = uff58_records(csv_path)
    with atomic_path(out_path) as tmp:
        Path(tmp).unlink(missing_ok=True)  # pyuff appends to an existing file
        uff = pyuff.UFF(str(tmp))
        uff.write_sets(records, mode="add")
    return len(records) - 1


def cmd_export(args: argparse.Namespace) -> int:
    if Path(args.out).suffix.lower() not in (".uff", ".unv"):
        raise InputError(f"--out {args.out}: the export format is the universal file format: name it .uff or .unv")
    count = write_uff(args.csv, args.out)
    print(f"refflow export: {count} time histories (UFF dataset 58) -> {args.out}")
    return 0


def add_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``refflow export`` to the ``refflow`` subcommands; returns its parser."""
    p = subparsers.add_parser(
        "export", help="a measurement as universal file format (UFF 58) time histories for modal software",
        description="Write a `refflow track` CSV as a universal file format file: a units record (dataset "
                    "164, SI) and one time history (dataset 58) per direction (and per region, node = "
                    "region), in m, on a uniform clock.")
    p.add_argument("csv", help="a `refflow track` CSV")
    p.add_argument("--out", required=True, help="output file, .uff or .unv")
    p.set_defaults(func=cmd_export)
    return p
