"""Ground-truth outputs written frame by frame: ``truth.csv`` and ``poi_truth.npz``.

The per-POI truth of a clip is (frames x POIs) numbers; holding it in memory
would make the renderer's memory grow with the clip, so each frame's row is
appended to a raw temporary file next to the output and the ``.npz`` is
assembled from those files in chunks at the end (the format of ``np.savez``:
a zip of ``.npy`` members, readable with ``np.load``).

``truth.csv`` columns (one row per frame; see ``render.json['truth_convention']``):
``frame, time_s, dx_px, dy_px, dx_mm, dy_mm, occluded`` as before, then
``occluded_frac`` (fraction of the POIs behind the sheet during the exposure),
``cam_dx_px, cam_dy_px`` (apparent image shift of a static point at the
measurement point's rest position caused by camera shake and drift; 0 with a
still camera), ``light_rel`` (relative light intensity over the measurement
row's exposure; 1 undisturbed) and ``gain`` (auto-exposure analog gain).

``poi_truth.npz``: ``dx_px, dy_px`` (F, P) float32, ``x_px, y_px`` (P,) float32
window coordinates of the POIs, and per frame (F,) float64 ``occluded_frac,
gain, cam_dx_px, cam_dy_px, light_rel``.
"""

from __future__ import annotations

import csv
import shutil
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from sim.codec import StreamWriter

CSV_COLUMNS = ("frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded",
               "occluded_frac", "cam_dx_px", "cam_dy_px", "light_rel", "gain")
_INTEGER_COLUMNS = ("frame", "occluded")
# npz member -> (key of a frame's truth dict, dtype)
_PER_FRAME = {"dx_px": ("poi_dx_px", np.float32), "dy_px": ("poi_dy_px", np.float32),
              "occluded_frac": ("occluded_frac", np.float64), "gain": ("gain", np.float64),
              "cam_dx_px": ("cam_dx_px", np.float64), "cam_dy_px": ("cam_dy_px", np.float64),
              "light_rel": ("light_rel", np.float64)}


def write_npz_streamed(path: str | Path, arrays: dict[str, np.ndarray],
                       raw: dict[str, tuple[Path, np.dtype, tuple[int, ...]]]) -> None:
    """Write an ``np.load``-able ``.npz``: ``arrays`` from memory, ``raw`` members
    copied in chunks from C-order raw files (name -> (file, dtype, shape))."""
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_DEFLATED, allowZip64=True) as zf:
        for name, array in arrays.items():
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fh:
                np.lib.format.write_array(fh, np.asarray(array))
        for name, (source, dtype, shape) in raw.items():
            expected = int(np.prod(shape)) * np.dtype(dtype).itemsize
            if source.stat().st_size != expected:
                raise RuntimeError(f"{source}: {source.stat().st_size} bytes, expected {expected} "
                                   f"for {name} {shape} {np.dtype(dtype)}")
            header = {"descr": np.lib.format.dtype_to_descr(np.dtype(dtype)),
                      "fortran_order": False, "shape": tuple(int(n) for n in shape)}
            with zf.open(f"{name}.npy", "w", force_zip64=True) as fh, source.open("rb") as src:
                np.lib.format.write_array_header_2_0(fh, header)
                shutil.copyfileobj(src, fh, 1 << 20)


class TruthWriter(StreamWriter):
    """``with TruthWriter(csv, npz, poi_x_px=..., poi_y_px=...) as w: w.write(truth, gain)``.

    Rows go to the CSV and to raw temporaries as they come; :meth:`close`
    assembles the ``.npz``. Memory stays flat in the clip length.
    """

    def __init__(self, csv_path: str | Path, npz_path: str | Path, *, poi_x_px: np.ndarray,
                 poi_y_px: np.ndarray):
        self.npz_path = Path(npz_path)
        self.poi_x_px = np.asarray(poi_x_px, np.float32)
        self.poi_y_px = np.asarray(poi_y_px, np.float32)
        self.frames = 0
        self._tmp = Path(tempfile.mkdtemp(prefix=".truth.", dir=self.npz_path.parent))
        self._streams = {member: (self._tmp / member).open("wb") for member in _PER_FRAME}
        self._csv_file = Path(csv_path).open("w", newline="")
        self._csv = csv.writer(self._csv_file, lineterminator="\n")
        self._csv.writerow(CSV_COLUMNS)

    def write(self, truth: dict[str, np.ndarray | float], gain: float) -> None:
        row = {**truth, "gain": gain}
        self._csv.writerow([int(row[c]) if c in _INTEGER_COLUMNS else f"{float(row[c]):.6f}"
                            for c in CSV_COLUMNS])
        for member, (key, dtype) in _PER_FRAME.items():
            self._streams[member].write(np.ascontiguousarray(row[key], dtype).tobytes())
        self.frames += 1

    def _close_files(self) -> None:
        for stream in self._streams.values():
            stream.close()
        self._csv_file.close()

    def close(self) -> None:
        self._close_files()
        n_poi = self.poi_x_px.size
        raw = {member: (self._tmp / member, dtype,
                        (self.frames, n_poi) if key.startswith("poi_") else (self.frames,))
               for member, (key, dtype) in _PER_FRAME.items()}
        try:
            write_npz_streamed(self.npz_path, {"x_px": self.poi_x_px, "y_px": self.poi_y_px}, raw)
        finally:
            shutil.rmtree(self._tmp, ignore_errors=True)

    def abort(self) -> None:
        self._close_files()
        shutil.rmtree(self._tmp, ignore_errors=True)
