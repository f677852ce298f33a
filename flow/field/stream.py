"""The whole displacement field of a run (``refflow track --field FIELD.h5``): every mask
pixel's displacement in every frame, not only the regions' averages, as one HDF5 file.

The file is written while the frames are measured, one frame at a time, to a temporary file
beside the output (:class:`FieldStream`); memory holds one frame's box, never the clip. The
POI filtering (paper eq. 10-12) needs the whole run, so when the run ends
:meth:`FieldStream.finish` passes over the file once more, frame by frame: it removes each
pixel's reference offset (as the averages do), adds the filter's verdicts and the scale, and
the set of outputs renames it with the CSV (all or nothing).

The values at the POIs are exactly the per-POI readings the CSV averages (camera motion
removed, offset removed), so a region's mean over its kept pixels (``kept``) is the region's
``dx_px``, ``dy_px`` in the CSV (eq. 12, ``--filter paper``). Layout: ``docs/formats.md``;
the reader: :func:`read_field`.
"""

from __future__ import annotations

import json
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from flow.io.errors import InputError

FORMAT = "refflow-field/1"
#: Chunk edge (rows and columns) of the per-frame datasets: one frame is one chunk row, so
#: writing and reading a frame touch that frame's chunks only.
CHUNK_PX = 256
#: gzip level: 1 is several times faster than the default and NaN outside the mask (the
#: bulk of a box around a slanted member) compresses at any level.
GZIP_LEVEL = 1
SUFFIXES = (".h5", ".hdf5")

_UNITS = {"u_px": "px", "v_px": "px", "u_mm": "mm", "v_mm": "mm", "x_px": "px", "y_px": "px", "time_s": "s",
          "sigma_dx_px": "px", "sigma_dy_px": "px", "sigma_px": "px", "offset_u_px": "px", "offset_v_px": "px",
          "sigma_u_px": "px", "sigma_v_px": "px"}
_DESCRIPTION = {
    "u_px": "displacement along x (right), image pixels, reference offset and camera motion removed; "
            "NaN outside the mask and where the frame was not measured",
    "v_px": "displacement along y (down), image pixels, like u_px",
    "u_mm": "u_px times mm_per_px", "v_mm": "v_px times mm_per_px",
    "valid": "1 where the pixel is a POI kept by eq. 10-11, its value is finite and its region's frame is valid",
    "kept": "1 at the POIs eq. 10-11 kept (a region's mean over them is its CSV reading)",
    "region_map": "each pixel's region label (0: not in the mask)",
    "frame_valid": "the CSV's valid flag per frame and region",
    "sigma_dx_px": "the CSV's standard uncertainty of the region's mean dx",
    "sigma_dy_px": "the same for dy", "sigma_px": "sqrt(sigma_dx_px^2 + sigma_dy_px^2)",
    "sigma_u_px": "standard uncertainty from the images' noise of the pixel's reading in u_px (not of the "
                  "reference offset or camera motion removed), where the method measured the pixel on its own "
                  "(deepflow: a deforming region's windowed step); NaN elsewhere",
    "sigma_v_px": "the same for v_px",
    "offset_u_px": "the reference's own reading removed from u_px (eq. 10-12's offset)",
    "offset_v_px": "the same for v_px",
    "x_px": "full-frame column of each pixel (undistorted pixels with a calibration)",
    "y_px": "full-frame row of each pixel", "frame": "frame index in the video", "time_s": "frame time",
    "reference": "the reference image over the box (grey levels as measured)",
}


@dataclass(frozen=True)
class Box:
    """The mask's bounding box in ROI pixels: rows ``top:bottom``, columns ``left:right``."""

    top: int
    bottom: int
    left: int
    right: int

    @classmethod
    def of(cls, mask: np.ndarray) -> Box:
        rows, cols = np.nonzero(mask)
        if rows.size == 0:
            raise InputError("the mask is empty: the field has no pixel to write")
        return cls(int(rows.min()), int(rows.max()) + 1, int(cols.min()), int(cols.max()) + 1)

    @property
    def shape(self) -> tuple[int, int]:
        return self.bottom - self.top, self.right - self.left

    @property
    def slices(self) -> tuple[slice, slice]:
        return slice(self.top, self.bottom), slice(self.left, self.right)


def _temporary_beside(final: Path, what: str) -> Path:
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".{what}{final.suffix}", dir=final.parent)
    os.close(fd)
    return Path(name)


def _frame_dataset(handle: Any, name: str, shape: tuple[int, int], dtype: Any, fill: Any) -> Any:
    height, width = shape
    return handle.create_dataset(name, shape=(0, height, width), maxshape=(None, height, width), dtype=dtype,
                                 chunks=(1, min(height, CHUNK_PX), min(width, CHUNK_PX)), fillvalue=fill,
                                 compression="gzip", compression_opts=GZIP_LEVEL, shuffle=True)


def _describe(dataset: Any, name: str) -> None:
    if name in _UNITS:
        dataset.attrs["units"] = _UNITS[name]
    if name in _DESCRIPTION:
        dataset.attrs["long_name"] = _DESCRIPTION[name]


class FieldStream:
    """A run's per-frame fields, appended in frame order to a temporary HDF5 file.

    Parameters
    ----------
    final : path
        The output the file becomes (its temporary lies beside it).
    labels : ndarray (H, W) int or bool
        The POI mask over the ROI (region labels; 0 / False: no POI): the field covers its
        bounding box, NaN outside it.
    poi_xy : ndarray (P, 2) int
        The POIs ``(x, y)`` in ROI pixels, in the driver's order.
    reference_frame : int
        The frame whose reading is each pixel's offset (unless :meth:`set_reference` gives it).
    origin_px : (x, y)
        The ROI's top-left pixel in the full frame.
    background : flow.measure.background.Background, optional
        The camera motion fitted to its points is removed from every pixel, as from the POIs'.
    """

    def __init__(self, final: str | Path, labels: np.ndarray, poi_xy: np.ndarray, *, reference_frame: int,
                 origin_px: tuple[int, int] = (0, 0), background: Any = None) -> None:
        import h5py

        from flow.outputs import check_suffix

        check_suffix(Path(final), SUFFIXES, option="--field")
        labels = np.asarray(labels)
        self.box = Box.of(labels != 0)
        inside = labels[self.box.slices]
        self._inside = inside != 0
        self._rows, self._cols = np.nonzero(self._inside)  # the box's mask pixels, in raster order
        # Where each POI sits among the mask pixels: its value is the POI's reading exactly.
        self._order = np.full(inside.shape, -1, np.intp)
        self._order[self._rows, self._cols] = np.arange(self._rows.size)
        self._poi_at = self._at(np.asarray(poi_xy[:, 0]), np.asarray(poi_xy[:, 1]))
        self.origin_px = (int(origin_px[0]) + self.box.left, int(origin_px[1]) + self.box.top)
        self._background = background
        self._grid_xy = np.column_stack([self._cols + self.box.left, self._rows + self.box.top]).astype(np.float64)
        self.reference_frame = int(reference_frame)
        # Where a method's flow starts in the ROI: (0, 0), or the driver's work area's corner
        # (it cuts the frames to the POIs' box plus the method's widest window).
        self.flow_origin = (0, 0)
        self.offset: tuple[np.ndarray, np.ndarray] | None = None
        # The offset images the parts of a merge removed already (recorded, not removed again).
        self.removed_offset: tuple[np.ndarray, np.ndarray] | None = None
        self.frames: list[int] = []
        self.final = Path(final)
        self.path = _temporary_beside(self.final, "stream")
        self._file = h5py.File(self.path, "w")
        self._u = _frame_dataset(self._file, "u_px", inside.shape, np.float32, np.nan)
        self._v = _frame_dataset(self._file, "v_px", inside.shape, np.float32, np.nan)
        self._su = _frame_dataset(self._file, "sigma_u_px", inside.shape, np.float32, np.nan)
        self._sv = _frame_dataset(self._file, "sigma_v_px", inside.shape, np.float32, np.nan)
        self._file.create_dataset("region_map", data=np.where(self._inside, inside, 0).astype(np.int16))
        self._file.create_dataset("x_px", data=np.arange(self.box.left, self.box.right, dtype=np.float64)
                                  + origin_px[0])
        self._file.create_dataset("y_px", data=np.arange(self.box.top, self.box.bottom, dtype=np.float64)
                                  + origin_px[1])

    def _at(self, x_px: np.ndarray, y_px: np.ndarray) -> np.ndarray:
        """The mask-pixel index of each POI at ``(x_px, y_px)`` (pixels of the stream's ROI)."""
        rows = np.rint(y_px).astype(np.intp) - self.box.top
        cols = np.rint(x_px).astype(np.intp) - self.box.left
        height, width = self.box.shape
        inside = (rows >= 0) & (rows < height) & (cols >= 0) & (cols < width)
        at = np.full(rows.shape, -1, np.intp)
        at[inside] = self._order[rows[inside], cols[inside]]
        if np.any(at < 0):
            raise ValueError("a POI lies outside the mask given to the field")
        return at

    # -- called by the driver's threads (pure) and its collector (in frame order) --

    def cut(self, flow: np.ndarray, dx: np.ndarray, dy: np.ndarray,
            sigma: list[tuple[np.ndarray, ...]] | None = None
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
        """A frame's displacement at the box's mask pixels (1-D, raster order) from a method's
        ``flow``: camera motion removed, the POIs' values the readings ``dx``, ``dy`` themselves;
        and their standard uncertainty from the method's ``sigma``, ``(rows, cols, sigma_u,
        sigma_v)`` of pixels of the flow (NaN at the others; None: the method has none in this
        frame)."""
        rows = self._rows + self.box.top - self.flow_origin[1]
        cols = self._cols + self.box.left - self.flow_origin[0]
        su = sv = None
        if sigma:
            su, sv = np.full(self._rows.size, np.nan, np.float32), np.full(self._rows.size, np.nan, np.float32)
            height, width = self._order.shape
            for at_rows, at_cols, values_u, values_v in sigma:
                box_rows = np.asarray(at_rows) + self.flow_origin[1] - self.box.top
                box_cols = np.asarray(at_cols) + self.flow_origin[0] - self.box.left
                if np.any((box_rows < 0) | (box_rows >= height) | (box_cols < 0) | (box_cols >= width)):
                    raise ValueError("a pixel with an uncertainty lies outside the field's box")
                at = self._order[box_rows, box_cols]
                if np.any(at < 0):
                    raise ValueError("a pixel with an uncertainty lies outside the field's mask")
                su[at], sv[at] = values_u, values_v
        u = flow[rows, cols, 0].astype(np.float64)
        v = flow[rows, cols, 1].astype(np.float64)
        background = self._background
        if background is not None:
            mx, my = background.motion_at(flow[background.rows, background.columns, 0],
                                          flow[background.rows, background.columns, 1], self._grid_xy)
            u, v = u - mx, v - my
        u, v = u.astype(np.float32), v.astype(np.float32)
        u[self._poi_at], v[self._poi_at] = dx, dy
        return u, v, su, sv

    def set_image(self, reference: np.ndarray) -> None:
        """Keep the reference image's box (the backdrop of ``refflow field-plot``)."""
        if "reference" not in self._file:
            self._file.create_dataset("reference", data=np.asarray(reference)[self.box.slices],
                                      compression="gzip", compression_opts=GZIP_LEVEL)

    def set_reference(self, u: np.ndarray, v: np.ndarray) -> None:
        """The reference's own reading (a part without the reference frame measures it apart)."""
        self.offset = (u.astype(np.float64), v.astype(np.float64))

    def append(self, index: int, u: np.ndarray, v: np.ndarray, sigma_u: np.ndarray | None = None,
               sigma_v: np.ndarray | None = None) -> None:
        """Write frame ``index`` (frames come in order); ``sigma_u``, ``sigma_v``: the mask
        pixels' standard uncertainty (None: NaN, the method has none)."""
        row = len(self.frames)
        for dataset, values in ((self._u, u), (self._v, v), (self._su, sigma_u), (self._sv, sigma_v)):
            dataset.resize(row + 1, axis=0)
            if values is None:
                continue  # the fill value, NaN: nothing is written (nor stored, compressed)
            image = np.full(self.box.shape, np.nan, np.float32)
            image[self._rows, self._cols] = values
            dataset[row] = image
        self.frames.append(int(index))
        if index == self.reference_frame and self.offset is None:
            self.set_reference(u, v)

    def discard(self) -> None:
        """Close and remove the temporary file (a failed run leaves nothing)."""
        try:
            self._file.close()
        finally:
            self.path.unlink(missing_ok=True)

    # -- the end of the run --

    def finish(self, tracks: Any, results: list[tuple[int, Any]], mm_per_px: float | None,
               attrs: dict[str, Any], *, roi_origin_px: tuple[int, int], offset_removed: bool = False) -> Path:
        """Remove the offsets and add the verdicts (``results``: each region's
        ``(label, Measurement)``; empty for a part without a CSV), the times and the scale;
        closes the file and returns its path. ``roi_origin_px``: the full-frame pixel of the
        tracks' ROI origin (their POIs are in ROI pixels)."""
        handle = self._file
        if len(self.frames) != len(tracks.frame) or np.any(np.asarray(self.frames) != tracks.frame):
            raise ValueError("the field's frames are not the tracks' frames")
        shift_x = roi_origin_px[0] - (self.origin_px[0] - self.box.left)
        shift_y = roi_origin_px[1] - (self.origin_px[1] - self.box.top)
        poi_at = self._at(np.asarray(tracks.x_px) + shift_x, np.asarray(tracks.y_px) + shift_y)
        offset_u, offset_v = self._offsets(tracks, poi_at, offset_removed)
        region_map = handle["region_map"][()]
        labels = [label for label, _ in results] or tracks.labels()
        kept = np.zeros(self.box.shape, np.uint8)
        frame_valid = np.zeros((len(self.frames), len(labels)), np.uint8)
        sigma = np.full((len(self.frames), len(labels), 2), np.nan)
        for k, (label, result) in enumerate(results):
            where = np.arange(len(tracks.x_px)) if tracks.region is None else np.flatnonzero(tracks.region == label)
            chosen = where[np.asarray(result.filtered.kept, bool)]
            kept[self._rows[poi_at[chosen]], self._cols[poi_at[chosen]]] = 1
            frame_valid[:, k] = result.valid
            for axis, values in enumerate((result.sigma_dx, result.sigma_dy)):
                if values is not None:
                    sigma[:, k, axis] = values
        scaled = mm_per_px is not None and np.isfinite(mm_per_px)
        if results:
            valid_ds = _frame_dataset(handle, "valid", self.box.shape, np.uint8, 0)
            valid_ds.resize(len(self.frames), axis=0)
        if scaled:
            mm = [_frame_dataset(handle, name, self.box.shape, np.float32, np.nan) for name in ("u_mm", "v_mm")]
            for dataset in mm:
                dataset.resize(len(self.frames), axis=0)
        # Each pixel's column of frame_valid: its region's position among the labels.
        column = np.zeros(self.box.shape, np.intp)
        for k, label in enumerate(labels):
            column[region_map == label] = k
        for row in range(len(self.frames)):
            u = (self._u[row].astype(np.float64) - offset_u).astype(np.float32)
            v = (self._v[row].astype(np.float64) - offset_v).astype(np.float32)
            self._u[row], self._v[row] = u, v
            if results:
                ok = (kept == 1) & np.isfinite(u) & np.isfinite(v) & (frame_valid[row][column] == 1)
                valid_ds[row] = ok.astype(np.uint8)
            if scaled:
                mm[0][row] = (u * mm_per_px).astype(np.float32)
                mm[1][row] = (v * mm_per_px).astype(np.float32)
        handle.create_dataset("frame", data=np.asarray(tracks.frame, np.int64))
        handle.create_dataset("time_s", data=np.asarray(tracks.time_s, np.float64))
        handle.create_dataset("region", data=np.asarray(labels, np.int64))
        if offset_removed and self.removed_offset is not None:
            offset_u, offset_v = self.removed_offset
        handle.create_dataset("offset_u_px", data=np.where(self._inside, offset_u, np.nan).astype(np.float32))
        handle.create_dataset("offset_v_px", data=np.where(self._inside, offset_v, np.nan).astype(np.float32))
        if results:
            handle.create_dataset("kept", data=kept)
            handle.create_dataset("frame_valid", data=frame_valid)
            handle.create_dataset("sigma_dx_px", data=sigma[..., 0])
            handle.create_dataset("sigma_dy_px", data=sigma[..., 1])
            handle.create_dataset("sigma_px", data=np.hypot(sigma[..., 0], sigma[..., 1]))
        self._dimensions()
        handle.attrs["format"] = FORMAT
        handle.attrs["complete"] = int(bool(results))
        handle.attrs["mm_per_px"] = float(mm_per_px) if scaled else np.nan
        handle.attrs["reference_frame"] = self.reference_frame
        handle.attrs["meta"] = json.dumps(attrs, sort_keys=True, default=str)
        handle.close()
        return self.path

    def _offsets(self, tracks: Any, poi_at: np.ndarray, removed: bool) -> tuple[np.ndarray, np.ndarray]:
        """Each box pixel's offset (the reference's own reading; the POIs' the tracks' exactly)."""
        if removed:
            return np.zeros(self.box.shape), np.zeros(self.box.shape)
        if self.offset is None:
            raise ValueError(f"the field never saw the reference frame {self.reference_frame}")
        images = []
        for values, exact in ((self.offset[0], tracks.offset_dx), (self.offset[1], tracks.offset_dy)):
            values = values.copy()
            values[poi_at] = exact
            # A pixel without a reference reading keeps its raw value (as a POI's offset falls to 0).
            values[~np.isfinite(values)] = 0.0
            image = np.zeros(self.box.shape)
            image[self._rows, self._cols] = values
            images.append(image)
        return images[0], images[1]

    def _dimensions(self) -> None:
        """Name the axes as netCDF-4 dimension scales, so xarray (h5netcdf) opens the file."""
        handle = self._file
        for name in ("frame", "y_px", "x_px", "region"):
            handle[name].make_scale(name)
        axes = {3: ("frame", "y_px", "x_px"), 2: ("y_px", "x_px"), 1: ("frame",)}
        for name, dataset in handle.items():
            if name in ("frame", "y_px", "x_px", "region"):
                _describe(dataset, name)
                continue
            if name in ("frame_valid", "sigma_dx_px", "sigma_dy_px", "sigma_px"):
                dims = ("frame", "region")
            else:
                dims = axes[dataset.ndim]
            for axis, dim in enumerate(dims):
                dataset.dims[axis].attach_scale(handle[dim])
            _describe(dataset, name)


def merge_parts(final: str | Path, parts: list[str | Path]) -> FieldStream:
    """A :class:`FieldStream` holding the frames of the parts' field files in order (each
    written by ``track --frames ... --raw-tracks ... --field``), its offsets already removed;
    finish it with ``offset_removed=True``."""
    import h5py

    if not parts:
        raise InputError("--field needs the parts' field files: pass --part-field FILE once per part")
    opened = []
    try:
        for path in parts:
            try:
                opened.append(h5py.File(path, "r"))
            except OSError as err:
                raise InputError(f"--part-field {path}: cannot read it as HDF5 ({err})") from None
            if opened[-1].attrs.get("format") != FORMAT:
                raise InputError(f"--part-field {path} is no refflow field file (format {FORMAT})")
        first = opened[0]
        for path, handle in zip(parts[1:], opened[1:], strict=True):
            for name in ("x_px", "y_px", "region_map"):
                if not np.array_equal(handle[name][()], first[name][()]):
                    raise InputError(f"--part-field {path} covers other pixels than {parts[0]} ({name} differs): "
                                     "the parts of one run share their mask")
        region_map = first["region_map"][()]
        origin = (int(first["x_px"][0]), int(first["y_px"][0]))
        # Rebuild the stream's geometry in the box's own pixels (the box at the origin).
        rows, cols = np.nonzero(region_map)
        poi_xy = np.column_stack([cols, rows])
        stream = FieldStream(final, region_map, poi_xy, reference_frame=int(first.attrs["reference_frame"]),
                             origin_px=origin)
        stream.removed_offset = (first["offset_u_px"][()], first["offset_v_px"][()])
        if "reference" in first:
            stream.set_image(first["reference"][()])
        for handle in opened:
            for row, index in enumerate(handle["frame"][()]):
                u, v = handle["u_px"][row], handle["v_px"][row]
                # (A part written before the per-pixel uncertainty has none.)
                sigma = [handle[name][row][rows, cols] if name in handle else None
                         for name in ("sigma_u_px", "sigma_v_px")]
                stream.append(int(index), u[rows, cols], v[rows, cols], *sigma)
        return stream
    finally:
        for handle in opened:
            handle.close()


@dataclass(frozen=True)
class Field:
    """An open field file (:func:`read_field`): h5py datasets, read a frame at a time."""

    handle: Any

    def __getitem__(self, name: str) -> Any:
        return self.handle[name]

    @property
    def meta(self) -> dict[str, Any]:
        return json.loads(self.handle.attrs.get("meta", "{}"))

    @property
    def n_frames(self) -> int:
        return int(self.handle["u_px"].shape[0])

    def close(self) -> None:
        self.handle.close()

    def __enter__(self) -> Field:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def read_field(path: str | Path, *, option: str = "FIELD") -> Field:
    """Open a field file written by ``refflow track --field``; :class:`InputError` for a
    missing file or another kind of file."""
    import h5py

    path = Path(path)
    if not path.is_file():
        raise InputError(f"{option} {path} does not exist: pass the .h5 that `refflow track --field` wrote")
    try:
        handle = h5py.File(path, "r")
    except OSError:
        raise InputError(f"{option} {path} is not an HDF5 file: pass the .h5 that `refflow track --field` "
                         "wrote") from None
    if handle.attrs.get("format") != FORMAT or "u_px" not in handle:
        handle.close()
        raise InputError(f"{option} {path} is no refflow field file (format {FORMAT}): pass the .h5 that "
                         "`refflow track --field` wrote")
    return Field(handle)
