"""Disk-backed per-POI tracks: a run's ``frames x POIs`` displacement matrices, appended
frame by frame to unlinked temporary files and read back a block of frames at a time, so
memory stays constant whatever the clip length; written out to ``.npz`` the same way.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from flow.measure.filtering import block_rows


class DiskMatrix:
    """A read-only ``(frames, points)`` float32 matrix in a file, read a block of rows at a time.

    Rows are read with ``pread`` rather than memory-mapped: pages of a mapped
    file count as the process's resident memory while they stay cached, so a
    mapping would look (to ``top``, to a scheduler's memory limit) as if the
    whole matrix were in memory. Indexing supports what the filters need:
    ``m[i]``, ``m[a:b]``, ``m[rows, columns]``; ``np.asarray(m)`` reads it all.
    """

    dtype = np.dtype(np.float32)
    ndim = 2

    def __init__(self, handle: Any, shape: tuple[int, int]) -> None:
        self._handle = handle
        self.shape = (int(shape[0]), int(shape[1]))

    def __len__(self) -> int:
        return self.shape[0]

    def _rows(self, start: int, stop: int) -> np.ndarray:
        n_points = self.shape[1]
        count = max(stop - start, 0)
        data = os.pread(self._handle.fileno(), count * n_points * 4, start * n_points * 4)
        return np.frombuffer(data, np.float32).reshape(count, n_points)

    def __getitem__(self, key: Any) -> np.ndarray:
        rest: tuple = ()
        if isinstance(key, tuple):
            key, rest = key[0], key[1:]
        if isinstance(key, (int, np.integer)):
            index = int(key) + (self.shape[0] if key < 0 else 0)
            if not 0 <= index < self.shape[0]:
                raise IndexError(f"row {key} out of range for {self.shape[0]} rows")
            return self._rows(index, index + 1)[(0, *rest)]
        if isinstance(key, slice):
            start, stop, step = key.indices(self.shape[0])
            return self._rows(start, max(stop, start))[(slice(None, None, step), *rest)]
        raise TypeError(f"DiskMatrix rows take an int or a slice, not {type(key).__name__}")

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = self._rows(0, self.shape[0])
        return whole if dtype is None else whole.astype(dtype)

    def __del__(self) -> None:
        handle = getattr(self, "_handle", None)
        if handle is not None:
            handle.close()



class PoiStore:
    """Per-POI displacement rows, appended frame by frame to disk, read back as :class:`DiskMatrix`.

    Two unlinked temporary files (dx, dy) hold ``float32`` rows of ``n_points``;
    the operating system deletes them when the run ends, however it ends.
    ``directory`` should be on a real disk (``/tmp`` may be memory-backed):
    the CLI puts it beside the output.
    """

    def __init__(self, n_points: int, *, directory: str | Path | None = None) -> None:
        self.n_points = int(n_points)
        self.n_frames = 0
        self._where = Path(directory) if directory is not None else Path(tempfile.gettempdir())
        self._files = [tempfile.TemporaryFile(prefix=".refflow-poi-", dir=directory) for _ in range(2)]

    def append(self, dx: np.ndarray, dy: np.ndarray) -> None:
        self.extend(np.asarray(dx)[None], np.asarray(dy)[None])

    def extend(self, dx: np.ndarray, dy: np.ndarray) -> None:
        """Append a block of rows ``(n, n_points)``."""
        with self._named():
            for handle, rows in zip(self._files, (dx, dy), strict=True):
                handle.write(np.ascontiguousarray(rows, np.float32).tobytes())
        self.n_frames += len(dx)

    @contextlib.contextmanager
    def _named(self) -> Iterator[None]:
        # A full disk says no file name, and the store's files have none: name its folder.
        try:
            yield
        except OSError as err:
            if err.filename is not None:
                raise
            raise OSError(err.errno, err.strerror or str(err),
                          f"{self._where} (the run's per-POI store, beside the output)") from err

    def arrays(self) -> tuple[DiskMatrix, DiskMatrix]:
        """Finish the store: its rows as read-only ``(n_frames, n_points)`` matrices (they own the files)."""
        with self._named():
            for handle in self._files:
                handle.flush()
        matrices = tuple(DiskMatrix(handle, (self.n_frames, self.n_points)) for handle in self._files)
        self._files = []
        return matrices  # type: ignore[return-value]

    def __del__(self) -> None:
        # A run that fails half-way drops its store unfinished.
        for handle in getattr(self, "_files", []):
            handle.close()


def write_npz(path: str | Path, arrays: dict[str, Any], *, compress: bool = False) -> None:
    """Write arrays as an ``.npz`` that ``np.load`` reads; :class:`DiskMatrix` members are streamed.

    ``np.savez`` would first read a disk matrix whole into memory.
    """
    compression = zipfile.ZIP_DEFLATED if compress else zipfile.ZIP_STORED
    with zipfile.ZipFile(path, "w", compression=compression, allowZip64=True) as archive:
        for name, value in arrays.items():
            with archive.open(f"{name}.npy", "w", force_zip64=True) as member:
                if isinstance(value, DiskMatrix):
                    header = {"descr": np.lib.format.dtype_to_descr(value.dtype), "fortran_order": False,
                              "shape": value.shape}
                    np.lib.format.write_array_header_2_0(member, header)
                    for rows in block_rows(*value.shape):
                        member.write(value[rows].tobytes())
                else:
                    np.lib.format.write_array(member, np.asanyarray(value), allow_pickle=False)
