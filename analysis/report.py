"""Summary table over scenarios x methods (CSV + Markdown)."""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from typing import Any

from refflow.io import atomic_path

from .readers import read_json

SUMMARY_COLUMNS = (
    "scenario", "method", "group", "seed", "rmse_mm", "rmse_px", "rmse_pct_of_max_ref", "max_disp_meas_mm",
    "max_disp_ref_mm", "max_disp_ref_1khz_mm", "max_disp_error_pct", "p2p_first_cycles_error_pct", "max_error_mm", "bias_mm", "drift_mm_per_s",
    "lowfreq_power_ratio", "mode1_amplitude_ratio", "mode1_meas_peak_hz", "mode3_expected_hz",
    "mode3_meas_peak_hz", "sync_lag_s", "sync_lag_error_ms", "valid_frac", "rmse_vs_truth_mm", "rmse_unoccluded_mm",
    "occlusion_rmse_mm", "post_occlusion_offset_mm", "post_occlusion_error_mm", "post_occlusion_rmse_mm", "recovery_time_s",
    "occluded_flagged_invalid_frac",
)


def load_metrics(paths: Sequence[str | os.PathLike[str]]) -> list[dict[str, Any]]:
    """Read metrics JSONs; each must name its ``scenario`` and ``method``."""
    rows = []
    for path in paths:
        data = read_json(path)
        for key in ("scenario", "method"):
            if key not in data:
                raise ValueError(f"{path}: missing key {key!r} (write it with `python -m analysis evaluate`)")
        data["_path"] = str(path)
        rows.append(data)
    rows.sort(key=lambda r: (str(r["scenario"]), str(r["method"])))
    return rows


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(int(value))
    if isinstance(value, float):
        return "" if not math.isfinite(value) else f"{value:.{digits}g}"
    return str(value)


def _unmeasured(row: dict[str, Any]) -> str:
    """The RMSE cell of a run without enough valid frames to compare."""
    return "every frame flagged" if not row.get("valid_frac") else "unmeasured (too few valid frames)"


def write_summary_csv(rows: list[dict[str, Any]], out: str | os.PathLike[str]) -> None:
    with atomic_path(out) as tmp, tmp.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(SUMMARY_COLUMNS)
        for row in rows:
            writer.writerow([_fmt(row.get(c), 6) for c in SUMMARY_COLUMNS])


# What the seed-replicate block reports per method: (label, key, digits).
SEED_COLUMNS = (
    ("RMSE (mm)", "rmse_mm", 3),
    ("RMSE / max. reference (%)", "rmse_pct_of_max_ref", 3),
    ("Max. displacement error (%)", "max_disp_error_pct", 2),
    ("First cycles p2p error (%)", "p2p_first_cycles_error_pct", 2),
    ("Valid share", "valid_frac", 3),
)


def _spread(values: list[float], digits: int) -> str:
    finite = [v for v in values if isinstance(v, (int, float)) and math.isfinite(v)]
    if not finite:
        return ""
    mean = sum(finite) / len(finite)
    if len(finite) == 1:
        return _fmt(float(mean), digits)
    return f"{_fmt(float(mean), digits)} [{_fmt(float(min(finite)), digits)}, {_fmt(float(max(finite)), digits)}]"


def seed_groups(rows: list[dict[str, Any]]) -> dict[str, dict[str, list[dict[str, Any]]]]:
    """``{group: {method: [rows]}}`` for the groups run with more than one seed."""
    groups: dict[str, dict[str, list[dict[str, Any]]]] = {}
    for row in rows:
        group = str(row.get("group") or row["scenario"])
        groups.setdefault(group, {}).setdefault(str(row["method"]), []).append(row)
    return {g: methods for g, methods in groups.items()
            if len({str(r["scenario"]) for rs in methods.values() for r in rs}) > 1}


def separated(rows_a: list[dict[str, Any]], rows_b: list[dict[str, Any]], key: str = "rmse_mm") -> bool:
    """True when every seed of ``a`` has a lower ``key`` than every seed of ``b`` (ranges apart)."""
    a = [r.get(key) for r in rows_a]
    b = [r.get(key) for r in rows_b]
    if not a or not b or any(not isinstance(v, (int, float)) or not math.isfinite(v) for v in a + b):
        return False
    return max(a) < min(b)


def seeds_markdown(rows: list[dict[str, Any]]) -> list[str]:
    """One block per scenario run with several seeds: each method's mean [min, max] over the
    seeds, and which method beats which (by RMSE, only where the seeds' ranges do not overlap)."""
    lines: list[str] = []
    for group, methods in seed_groups(rows).items():
        seeds = sorted({r.get("seed") for rs in methods.values() for r in rs}, key=lambda v: (v is None, v))
        lines += [f"## {group}: {len(seeds)} seeds ({', '.join(str(s) for s in seeds)}), mean [min, max]", "",
                  "| Method | Seeds | " + " | ".join(label for label, _, _ in SEED_COLUMNS) + " |",
                  "|---|---|" + "---|" * len(SEED_COLUMNS)]
        for method, group_rows in methods.items():
            cells = [_spread([r.get(key) for r in group_rows], digits) for _, key, digits in SEED_COLUMNS]
            lines.append(f"| {method} | {len(group_rows)} | " + " | ".join(cells) + " |")
        names = sorted(methods, key=lambda m: sum(r.get("rmse_mm") or math.inf for r in methods[m]))
        wins, ties = [], []
        for i, a in enumerate(names):
            for b in names[i + 1:]:
                (wins if separated(methods[a], methods[b]) else ties).append((a, b))
        lines.append("")
        if wins:
            lines.append("Beats (RMSE lower on every seed than the other's best): "
                         + "; ".join(f"{a} < {b}" for a, b in wins) + ".")
        if ties:
            lines.append("Ranges overlap, no winner: " + "; ".join(f"{a} ~ {b}" for a, b in ties) + ".")
        lines.append("")
    return lines


def summary_markdown(rows: list[dict[str, Any]]) -> str:
    """Table-1 style Markdown: one block per scenario, the reference sensor last."""
    cutoffs = sorted({_fmt((row.get("params") or {}).get("lowpass_hz"), 3) for row in rows} - {""})
    lowpass = " / ".join(cutoffs) or "30"
    lines = ["# Displacement accuracy (simulated)", "",
             f"Error = measured - reference (laser sensor, {lowpass} Hz zero-phase Butterworth, "
             "synchronised). Maximum displacement: the largest excursion after the release, "
             "about the rest position (analysis.metrics); errors are over the valid frames "
             "(Valid share: the frames the method did not flag).", ""]
    lines += seeds_markdown(rows)
    scenarios: dict[str, list[dict[str, Any]]] = {}
    for row in rows:
        scenarios.setdefault(str(row["scenario"]), []).append(row)
    for scenario, group in scenarios.items():
        lines += [f"## {scenario}", "",
                  "| Method | Maximum displacement (mm) | Max. displacement error (%) | First cycles p2p error (%) "
                  "| RMSE (mm) | RMSE (px) | Valid share | RMSE / max. reference (%) | Drift (mm/s) "
                  "| Post-occlusion offset (mm) | Recovery time (s) |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for row in group:
            lines.append("| " + " | ".join([
                str(row["method"]), _fmt(row.get("max_disp_meas_mm")), _fmt(row.get("max_disp_error_pct"), 3),
                _fmt(row.get("p2p_first_cycles_error_pct"), 3),
                _unmeasured(row) if "unmeasured" in row else _fmt(row.get("rmse_mm")),
                _fmt(row.get("rmse_px"), 3), _fmt(row.get("valid_frac"), 3),
                _fmt(row.get("rmse_pct_of_max_ref"), 3),
                _fmt(row.get("drift_mm_per_s"), 3), _fmt(row.get("post_occlusion_offset_mm"), 3) or "-",
                _fmt(row.get("recovery_time_s"), 3) or "-"]) + " |")
        ref = next((row["max_disp_ref_mm"] for row in group if row.get("max_disp_ref_mm") is not None), None)
        lines.append(f"| Reference displacement sensor | {_fmt(ref)} | - | - | - | - | - | - | - | - | - |")
        lines.append("")
    return "\n".join(lines)


def modal_markdown(results: list[dict[str, Any]]) -> str:
    """One table per scenario measured as regions: the modes `refflow modal` identified from
    the video against the model and against the modes of the simulated laser at the same heights
    (``analysis modal-video`` JSONs)."""
    lines = []
    for result in sorted(results, key=lambda r: str(r.get("scenario"))):
        heights = ", ".join(_fmt(float(h), 4) for h in result.get("heights_mm", []))
        lines += [f"## {result.get('scenario')}: modes from the video ({heights} mm as regions of one run)", "",
                  "| Mode | Frequency (Hz) | Model (Hz) | Error (%) | Laser-identified (Hz) | Damping ratio "
                  "| Model damping | MAC vs model | MAC vs laser-identified |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for i in range(1, int(result.get("n_modes") or 0) + 1):
            mode = {key[len(f"mode{i}_"):]: value for key, value in result.items() if key.startswith(f"mode{i}_")}
            get = mode.get
            lines.append("| " + " | ".join([
                f"{i} (model mode {get('model_index')})", _fmt(get("freq_hz"), 5), _fmt(get("freq_model_hz"), 5),
                _fmt(get("freq_error_pct"), 3), _fmt(get("freq_sensor_hz"), 5), _fmt(get("damping_ratio"), 3),
                _fmt(get("damping_model_ratio"), 3), _fmt(get("mac"), 4), _fmt(get("mac_vs_sensor"), 4)]) + " |")
        lines.append("")
    return "\n".join(lines)


def write_text(path: str | os.PathLike[str], text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
