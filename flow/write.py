"""A run's outputs as one all-or-nothing set: the raw-tracks part, the per-POI tracks, the
sidecar and the CSV, each region filtered and averaged on its own.

Every file is written to a temporary name; only when all are complete are they renamed (the
CSV last), so a failure or Ctrl-C leaves none of them.
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from flow.measure.quality import MAX_SIGMA_TO_RANGE
from flow.options import FilterOptions, OutputOptions, RunInfo
from flow.outputs import check_outputs, check_sidecar, writing
from flow.scale import Scale
from refflow import trackcsv
from refflow.io import atomic_paths, finite_or_none, json_text, versions


def output_names(outputs: OutputOptions, inputs: list[tuple[str, Path]]) -> list[Path]:
    """The files a run writes, in writing order (the CSV last); checked before any work."""
    names = outputs.paths()
    option = "--out (the sidecar is <out>.json)"
    check_outputs(names, inputs, option=option)
    if outputs.csv:
        check_sidecar(Path(outputs.csv), Path(outputs.csv).with_suffix(".json"), option=option)
    return names


def measure_regions(tracks: Any, filtering: FilterOptions, sparse: bool) -> tuple[str, list[tuple[int, Any]]]:
    """The filter mode used and each region's ``(label, Measurement)``."""
    from flow.measure import quality

    mode = filtering.mode or ("none" if sparse else "paper")
    results = [(label, quality.measure(tracks.select(label), filter_enabled=mode != "none",
                                       average="median" if mode == "median" else "mean",
                                       threshold_ratio=filtering.threshold_ratio,
                                       mcr_threshold=filtering.mcr_threshold,
                                       max_typical_sigma_px=filtering.max_typical_sigma_px,
                                       # KLT mixes background and structure features by design (the
                                       # paper's baseline): their disagreement is no sign of a blocked view
                                       check_coherence=not sparse))
               for label in tracks.labels()]
    return mode, results


def unresolved_note(result: Any, filtering: FilterOptions) -> str:
    """The note (and stderr warning) of a region whose every frame was flagged for its precision."""
    motion = result.resolution
    against = (f" and {motion.ratio:.2f} of the motion's 5-95 % range on {motion.axis} ({motion.sigma_px:.2f} of "
               f"{motion.range_px:.2f} px, above {MAX_SIGMA_TO_RANGE:g})" if motion.axis else "")
    return (f"the typical frame's standard uncertainty is {result.typical_sigma_px:.2f} px, above the "
            f"{filtering.max_typical_sigma_px:g} px a sub-pixel reading needs{against} (heavy compression, noise or "
            "too little texture): every frame is flagged valid=0, its reading kept; record at a higher bit rate, or "
            "pass --max-typical-sigma 0 to vouch for the readings")


def rest_note(result: Any) -> str:
    """The note of a region whose frames averaged into the reference scatter more than their sigma
    says (see :func:`flow.measure.quality.rest_excess`)."""
    x, y = result.rest_excess_px
    return (f"the {result.tracks.reference_average} frames averaged into the reference (at rest, as "
            f"--reference-average says) read further apart than their sigma says: {x:.3f} px (x), {y:.3f} px (y) "
            "more, added to every frame's sigma (a codec that rebuilds the texture in each frame, or a "
            "structure not quite at rest)")


def write_outputs(outputs: OutputOptions, filtering: FilterOptions, inputs: list[tuple[str, Path]],
                  tracks: Any, run: RunInfo, notes: list[str], scale: Scale,
                  started: float, *, field: Any = None, field_offset_removed: bool = False) -> list[tuple[int, Any]]:
    """Filter, average and write the run's outputs as one all-or-nothing set; returns each
    region's ``(label, Measurement)`` (none without a CSV).

    A run of several regions filters and averages each on its own and writes one row per
    frame and region. ``field`` (a :class:`flow.field.stream.FieldStream`, with ``outputs.field``) is
    finished with the verdicts and joins the set (its offsets already removed in a merge:
    ``field_offset_removed``).
    """
    from flow.measure import formats

    results: list[tuple[int, Any]] = []
    sidecar_text = ""
    if outputs.csv:
        mode, results = measure_regions(tracks, filtering, run.method_kind == "sparse")
        # This measurement's own verdict: the sidecar's notes, never a raw-tracks part's (a
        # merge of parts measures again, maybe with another limit).
        def region(label: int) -> str:
            return f"region {label}: " if len(results) > 1 else ""

        flagged = [region(label) + unresolved_note(result, filtering) for label, result in results if result.unresolved]
        restless = [region(label) + rest_note(result) for label, result in results if max(result.rest_excess_px) > 0]
        for level, said in (("warning", flagged), ("note", restless)):
            for note in said:
                print(f"{run.tool}: {level}: {note}", file=sys.stderr)
        columns = trackcsv.columns(regions=tracks.region is not None)
        # Serialised first: a bad value fails before any file exists.
        described = {**sidecar(run, filtering, notes + restless + flagged, results, scale, mode, columns, started),
                     "csv": Path(outputs.csv).name}  # which output it describes (two may share it: a, a.csv)
        sidecar_text = json_text(described)
    finals = output_names(outputs, inputs)
    with atomic_paths(*finals) as temporaries:
        # Each file's temporary, with the name an error about it gives (a full disk names none).
        pending = list(zip(temporaries, finals, strict=True))
        if outputs.raw_tracks:
            tmp, final = pending.pop(0)
            with writing(final):
                formats.save_raw_tracks(tmp, tracks, run.part_meta(notes))
        if outputs.poi_tracks:
            tmp, final = pending.pop(0)
            with writing(final):
                _write_poi_tracks(tmp, tracks, results, run.roi)
        if outputs.field:
            tmp, final = pending.pop(0)
            with writing(final):
                written = field.finish(tracks, results, scale.mm_per_px, run.record(),
                                       roi_origin_px=(run.roi["x"], run.roi["y"]),
                                       offset_removed=field_offset_removed)
                os.replace(written, tmp)
        if outputs.csv:
            tmp, final = pending.pop(0)
            with writing(final):
                tmp.write_text(sidecar_text)
            tmp, final = pending.pop(0)
            with writing(final), tmp.open("w", newline="") as handle:
                trackcsv.write(handle, [(label, formats.iter_rows(result, scale.mm_per_px))
                                        for label, result in results])
    return results


def _write_poi_tracks(path: Path, tracks: Any, results: list[tuple[int, Any]], roi: dict[str, int]) -> None:
    """The per-POI displacements with each POI's filter verdict (``--save-poi-tracks``)."""
    from flow.measure import storage

    multi = tracks.region is not None
    kept = np.zeros(len(tracks.x_px), bool)
    mcr = np.full(len(tracks.x_px), np.nan)
    for label, result in results:
        where = slice(None) if not multi else tracks.region == label
        kept[where] = result.filtered.kept
        mcr[where] = result.filtered.mcr
    valid = np.column_stack([result.valid for _, result in results])
    storage.write_npz(path, {
        "frame": tracks.frame, "time_s": tracks.time_s, "dx_px": tracks.dx, "dy_px": tracks.dy,
        "x_px": tracks.x_px + roi["x"], "y_px": tracks.y_px + roi["y"],
        "valid": valid if multi else valid[:, 0], "kept": kept, "mcr": mcr, "residual": tracks.residual,
        "offset_dx_px": tracks.offset_dx, "offset_dy_px": tracks.offset_dy,
        **({"region": tracks.region} if multi else {})}, compress=True)


def _hidden(result: Any) -> int | None:
    """Frames in which the method saw nothing of the scene (flagged; None: it does not tell)."""
    hidden = result.tracks.hidden
    return None if hidden is None else int(np.sum(hidden))


def _quality(result: Any) -> dict[str, Any]:
    n_valid = int(result.valid.sum())
    return {"frames_valid": n_valid, "frames_invalid": int(len(result.valid) - n_valid),
            "frames_hidden": _hidden(result),
            "residual_threshold": finite_or_none(result.residual_threshold),
            "consistency_band_px": finite_or_none(result.consistency_band_px),
            "typical_sigma_px": finite_or_none(result.typical_sigma_px),
            "rest_excess_px": [finite_or_none(v) for v in result.rest_excess_px],
            "motion": {"axis": result.resolution.axis or None,
                       "sigma_px": finite_or_none(result.resolution.sigma_px),
                       "range_px": finite_or_none(result.resolution.range_px),
                       "sigma_to_range": finite_or_none(result.resolution.ratio),
                       "max_sigma_to_range": MAX_SIGMA_TO_RANGE},
            "unresolved": bool(result.unresolved)}


def sidecar(run: RunInfo, filtering: FilterOptions, notes: list[str], results: list[tuple[int, Any]],
            scale: Scale, filter_mode: str, columns: list[str], started: float) -> dict[str, Any]:
    """The measurement's sidecar: the run, the scale, the filter and the quality (per region
    under ``regions`` for a run of several)."""
    multi = len(results) > 1
    first = results[0][1]
    every = np.logical_and.reduce([result.valid for _, result in results])
    data: dict[str, Any] = {
        **run.record(),
        "scale": {"mm_per_px": finite_or_none(scale.mm_per_px), "source": scale.source},
        "filter": {"mode": filter_mode, "threshold_ratio": filtering.threshold_ratio,
                   "threshold_px": None if multi else first.filtered.threshold_px,
                   "mcr_threshold": filtering.mcr_threshold,
                   "max_typical_sigma_px": filtering.max_typical_sigma_px},
        "quality": ({"frames_valid": int(every.sum()), "frames_invalid": int(len(every) - every.sum()),
                     "frames_hidden": _hidden(first),
                     "counted": "frames valid in every region (each region's own: see regions)",
                     "unresolved_regions": [int(label) for label, result in results if result.unresolved]}
                    if multi else _quality(first)),
        "units": trackcsv.units(regions=multi),
        "columns": columns,
        "notes": notes + [(f"region {label}: {note}" if multi else note)
                          for label, result in results for note in result.filtered.notes],
        "versions": versions(),
        "timings": {**run.timings, "total_s": time.perf_counter() - started},
    }
    data["poi"] = {**run.poi, "kept_after_filter": sum(int(r.filtered.kept.sum()) for _, r in results),
                   "kept_after_eq10": sum(int(r.filtered.kept_threshold.sum()) for _, r in results)}
    if multi:
        described = {entry["label"]: entry for entry in run.poi.get("regions", [])}
        data["regions"] = [
            {**described.get(label, {"label": label}), "threshold_px": result.filtered.threshold_px,
             "kept_after_filter": int(result.filtered.kept.sum()),
             "kept_after_eq10": int(result.filtered.kept_threshold.sum()), **_quality(result)}
            for label, result in results]
    return data
