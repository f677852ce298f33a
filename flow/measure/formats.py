"""The files a run writes besides its sidecar: the rows of its track CSV (the format, its
columns, units and region column: :mod:`refflow.trackcsv`) and the raw-tracks parts of
``refflow track --raw-tracks``, which ``refflow merge`` joins into the tracks of one run.
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flow.io.errors import InputError
from flow.measure.filtering import block_rows
from flow.measure.storage import PoiStore, write_npz
from flow.measure.tracks import NOT_ADDITIVE_TIMINGS, Measurement, Tracks


def iter_rows(result: Measurement, mm_per_px: float) -> Iterable[dict[str, Any]]:
    """The track CSV's rows of one region (:func:`refflow.trackcsv.write` adds the region
    column). Every frame keeps its reading and uncertainty, flagged or not: ``valid`` qualifies
    the number, the reader decides (NaN only where nothing was measured)."""
    tr = result.tracks
    for i in range(len(tr.frame)):
        dx, dy = float(result.filtered.dx[i]), float(result.filtered.dy[i])
        sx = float(result.sigma_dx[i]) if result.sigma_dx is not None else float("nan")
        sy = float(result.sigma_dy[i]) if result.sigma_dy is not None else float("nan")
        yield {"frame": int(tr.frame[i]), "time_s": float(tr.time_s[i]), "dx_px": dx, "dy_px": dy,
               "dx_mm": dx * mm_per_px, "dy_mm": dy * mm_per_px, "valid": int(bool(result.valid[i])),
               "sigma_dx_px": sx, "sigma_dy_px": sy, "sigma_px": float(np.hypot(sx, sy)),
               "poi_kept_frac": float(result.poi_kept_frac[i]), "residual": float(tr.residual[i]),
               "flow_spread_px": float(result.flow_spread_px[i]),
               "camera_dx_px": float(tr.camera_dx[i]) if tr.camera_dx is not None else float("nan"),
               "camera_dy_px": float(tr.camera_dy[i]) if tr.camera_dy is not None else float("nan")}


RAW_FORMAT = "refflow-raw-tracks/1"


def save_raw_tracks(path: str | Path, tracks: Tracks, meta: dict[str, Any]) -> None:
    """Write the unfiltered tracks of a run or a range of frames (``track --raw-tracks``).

    ``meta`` must hold an ``identity`` dict (method, parameters, reference,
    ROI, calibration, POIs ...) that parts of one run share; :func:`load_raw_tracks`
    checks it. The per-POI matrices are streamed into the file (uncompressed).
    """
    camera = ({} if tracks.camera_dx is None
              else {"camera_dx_px": tracks.camera_dx, "camera_dy_px": tracks.camera_dy})
    if tracks.sigma_dx is not None:
        camera.update({"sigma_dx_px": tracks.sigma_dx, "sigma_dy_px": tracks.sigma_dy})
    if tracks.sigma_holds_reference is not None:
        camera["sigma_holds_reference"] = tracks.sigma_holds_reference
    if tracks.region is not None:
        camera["region"] = tracks.region
    if tracks.hidden is not None:
        camera["hidden"] = tracks.hidden
    write_npz(path, {"format": np.array(RAW_FORMAT), "meta": np.array(json.dumps(meta, sort_keys=True)),
                     "frame": tracks.frame, "time_s": tracks.time_s, "residual": tracks.residual,
                     "x_px": tracks.x_px, "y_px": tracks.y_px, "offset_dx_px": tracks.offset_dx,
                     "offset_dy_px": tracks.offset_dy, **camera, "dx_px": tracks.dx, "dy_px": tracks.dy})


@dataclass
class _Part:
    path: Path
    meta: dict[str, Any]
    small: dict[str, np.ndarray]


def _open_part(path: Path) -> _Part:
    if not path.is_file():
        raise InputError(f"part {str(path)!r} does not exist: pass the files `refflow track --raw-tracks` wrote")
    # Anything but a zip archive (a video, a CSV, a .npy) is no .npz: said here, before numpy
    # reads it as a pickle and suggests loading it unsafely.
    if not zipfile.is_zipfile(path):
        raise InputError(f"{str(path)!r} is not a .npz archive: pass the raw-tracks files that "
                         f"`refflow track --raw-tracks` wrote ({RAW_FORMAT})")
    try:
        with np.load(path, allow_pickle=False) as data:
            if "format" not in data.files or str(data["format"]) != RAW_FORMAT:
                raise InputError(f"{str(path)!r} is not a raw-tracks file of `refflow track --raw-tracks` "
                                 f"({RAW_FORMAT})")
            small = {k: data[k] for k in data.files if k not in ("dx_px", "dy_px", "meta", "format")}
            meta = json.loads(str(data["meta"]))
    except (OSError, ValueError, zipfile.BadZipFile) as err:
        if isinstance(err, InputError):
            raise
        raise InputError(f"{str(path)!r} is not a readable .npz raw-tracks file ({err})") from None
    return _Part(path, meta, small)


def _rows_of(path: Path, name: str, n_points: int) -> Iterator[np.ndarray]:
    """Blocks of rows of an ``(F, n_points)`` float32 member, read without loading it whole."""
    with zipfile.ZipFile(path) as archive, archive.open(f"{name}.npy") as member:
        version = np.lib.format.read_magic(member)
        read_header = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                       else np.lib.format.read_array_header_2_0)
        shape, fortran, dtype = read_header(member)
        if fortran or dtype != np.float32 or len(shape) != 2 or shape[1] != n_points:
            raise InputError(f"{path}: {name} is not a float32 (frames, {n_points}) matrix")
        for rows in block_rows(shape[0], n_points):
            count = rows.stop - rows.start
            yield np.frombuffer(member.read(count * n_points * 4), np.float32).reshape(count, n_points)


def load_raw_tracks(paths: Iterable[str | Path], *,
                    store_dir: str | Path | None = None) -> tuple[Tracks, list[dict[str, Any]]]:
    """Concatenate raw-tracks parts of one run into :class:`Tracks` (in frame order).

    The parts must share their ``identity`` (same video, reference frame,
    ROI, calibration, POIs, method and parameters) and cover contiguous,
    non-overlapping frame ranges. Returns the tracks and the parts' ``meta``
    in frame order. Memory stays bounded: rows go through a :class:`PoiStore`.
    """
    parts = [_open_part(Path(p)) for p in paths]
    if not parts:
        raise InputError("no part given: pass the .npz files of `refflow track --raw-tracks`")
    first = parts[0]
    for part in parts[1:]:
        for key in sorted(set(first.meta["identity"]) | set(part.meta["identity"])):
            mine, theirs = first.meta["identity"].get(key), part.meta["identity"].get(key)
            if mine != theirs:
                raise InputError(f"{part.path.name} and {first.path.name} differ in {key} ({theirs!r} vs "
                                 f"{mine!r}): merge only parts of one run (same video, reference, ROI, "
                                 "POIs, method and parameters)")
        if not (np.array_equal(part.small["x_px"], first.small["x_px"])
                and np.array_equal(part.small["y_px"], first.small["y_px"])
                and np.array_equal(part.small.get("region", []), first.small.get("region", []))):
            raise InputError(f"{part.path.name} and {first.path.name} track different POIs: "
                             "use the same mask, --grid-step and --roi for every part")
    parts.sort(key=lambda part: int(part.small["frame"][0]) if part.small["frame"].size else -1)
    for before, after in zip(parts, parts[1:], strict=False):
        end, begin = int(before.small["frame"][-1]) + 1, int(after.small["frame"][0])
        if begin < end:
            raise InputError(f"{after.path.name} (from frame {begin}) overlaps {before.path.name} "
                             f"(to frame {end - 1}): give non-overlapping --frames ranges")
        if begin > end:
            raise InputError(f"frames {end}:{begin} are missing between {before.path.name} and "
                             f"{after.path.name}: track that range too (--frames {end}:{begin})")
    n_points = len(first.small["x_px"])
    store = PoiStore(n_points, directory=store_dir)
    for part in parts:
        for block_x, block_y in zip(_rows_of(part.path, "dx_px", n_points),
                                    _rows_of(part.path, "dy_px", n_points), strict=True):
            store.extend(block_x, block_y)
    dx, dy = store.arrays()
    reference_frame = int(first.meta["identity"]["reference_frame"])
    # The reference frame's own row gives the offset where a part holds it (as in a whole run).
    holder = next((p for p in parts if reference_frame in p.small["frame"]), parts[0])
    if len({"hidden" in p.small for p in parts}) > 1:
        raise InputError("the parts come from different refflow versions (some record the frames that "
                         "showed nothing of the scene, some do not): track every part with one version")
    per_frame = ("frame", "time_s", "residual") + (("camera_dx_px", "camera_dy_px")
                                                   if "camera_dx_px" in first.small else ()) \
        + (("sigma_dx_px", "sigma_dy_px") if all("sigma_dx_px" in p.small for p in parts) else ()) \
        + (("hidden",) if "hidden" in first.small else ())
    concat = {key: np.concatenate([p.small[key] for p in parts]) for key in per_frame}
    if "sigma_dx_px" in concat and any("sigma_holds_reference" in p.small for p in parts):
        # A part from before the flag: none of its frames' sigma held the reference's error.
        concat["sigma_holds_reference"] = np.concatenate([
            p.small.get("sigma_holds_reference", np.zeros(np.shape(p.small["residual"]), bool)) for p in parts])
    additive = [key for key in first.meta.get("timings", {}) if key not in NOT_ADDITIVE_TIMINGS]
    # Counts and seconds add up over the parts; a length (a key ending in _px, e.g. the codec
    # floor each part measures alike) is the largest of theirs, as over a run's jobs.
    timings = {key: (max if key.endswith("_px") else sum)(p.meta.get("timings", {}).get(key, 0.0) for p in parts)
               for key in dict.fromkeys(["setup_s", "frames_s", *additive])}
    timings["frames_per_s"] = len(concat["frame"]) / max(timings["frames_s"], 1e-9)
    tracks = Tracks(frame=concat["frame"], time_s=concat["time_s"], dx=dx, dy=dy, residual=concat["residual"],
                    x_px=first.small["x_px"], y_px=first.small["y_px"], reference_frame=reference_frame,
                    reference_average=int(first.meta["identity"].get("reference_average", 1)),
                    offset_dx=holder.small["offset_dx_px"].astype(np.float64),
                    offset_dy=holder.small["offset_dy_px"].astype(np.float64),
                    timings_s=timings, truncated=any(p.meta["input"]["truncated"] for p in parts),
                    header_frames=int(first.meta["input"]["header_frames"]),
                    reference_digest=first.meta["identity"]["reference_digest"],
                    camera_dx=concat.get("camera_dx_px"), camera_dy=concat.get("camera_dy_px"),
                    sigma_dx=concat.get("sigma_dx_px"), sigma_dy=concat.get("sigma_dy_px"),
                    sigma_holds_reference=(None if "sigma_holds_reference" not in concat
                                           else concat["sigma_holds_reference"].astype(bool)),
                    region=first.small.get("region"),
                    hidden=None if "hidden" not in concat else concat["hidden"].astype(bool))
    return tracks, [p.meta for p in parts]
