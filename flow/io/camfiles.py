"""What the high-speed camera readers share: :class:`CameraFile` (a recording read one frame at
a time from disk), the suffixes they open, the files beside a header that hold its frames,
and the unpacking of 10 and 12-bit packed pixels.

The readers, one per format, are clean-room, written from public descriptions of the formats
(no vendor SDK code): :mod:`flow.io.photron` (``.cih``/``.cihx`` + ``.mraw``) and
:mod:`flow.io.phantom` (``.cine``); :func:`flow.io.camera.open_camera_file` picks one by the
suffix. Opening a file parses its header only; :meth:`CameraFile.read` then seeks to ONE
frame and reads just that frame's bytes, so memory stays constant whatever the size of the
recording. Colour recordings are refused with an :class:`~flow.io.errors.InputError` (the
readers return grey frames only), as is every malformed file, with a message naming the
problem and what to do.
"""

from __future__ import annotations

import operator
import os
from pathlib import Path
from typing import Literal

import numpy as np

from flow.io.errors import InputError

__all__ = ["CAMERA_SUFFIXES", "CameraFile", "companion_files", "unpack_bits"]

CAMERA_SUFFIXES = (".cih", ".cihx", ".cine")


_MRAW_SUFFIXES = (".mraw", ".MRAW", ".Mraw")


def companion_files(path: str | os.PathLike[str]) -> list[Path]:
    """The files beside ``path`` that its recording reads: a Photron header's ``.mraw``."""
    p = Path(path)
    if p.suffix.lower() not in (".cih", ".cihx"):
        return []
    return [c for c in (p.with_suffix(suffix) for suffix in _MRAW_SUFFIXES) if c.is_file()][:1]


class CameraFile:
    """A recording read one frame at a time from disk.

    Attributes
    ----------
    path : pathlib.Path
        The file the user named (the ``.cih``/``.cihx`` or the ``.cine``).
    data_path : pathlib.Path
        The file holding the frames (the ``.mraw``, or the ``.cine`` itself).
    width, height : int
        Frame size in pixels; :meth:`read` returns ``(height, width)`` arrays.
    frame_count : int
        Frames in the file.
    fps : float
        Recording rate from the header, frames per second.
    frame_step : int
        Recorded frames per stored frame (Photron's ``Save Step``: a file saved
        with step 100 keeps every 100th frame); 1 for Phantom. Consecutive
        stored frames are ``frame_step / fps`` seconds apart.
    bit_depth : int
        Bits the returned pixel values occupy: they lie in
        ``[0, 2**bit_depth - 1]``.
    dtype : numpy.dtype
        ``uint8`` or ``uint16``, the dtype :meth:`read` returns.
    first_frame_number : int
        Camera frame number of the first stored frame, the trigger frame
        being 0 (Photron ``Start Frame``, Phantom ``FirstImageNo``).
    trigger_mode : str or None
        Photron ``Trigger Mode`` (e.g. ``"Start"``); None where the header
        has none.
    trigger_time_posix : float or None
        Phantom trigger time, seconds since 1970-01-01 UTC; None for Photron.
    has_timestamps : bool
        Whether :meth:`time_s` comes from per-frame time stamps stored in the
        file (Phantom's TIME64 block) rather than from ``fps``.
    timestamps_note : str or None
        Why stored time stamps were set aside, where they were.
    header : dict
        The header fields the reader parsed, by their names in the format.
    """

    path: Path
    data_path: Path
    width: int
    height: int
    frame_count: int
    fps: float
    frame_step: int = 1
    bit_depth: int
    dtype: np.dtype
    first_frame_number: int = 0
    trigger_mode: str | None = None
    trigger_time_posix: float | None = None
    has_timestamps: bool = False
    timestamps_note: str | None = None
    header: dict[str, object]
    _times: np.ndarray | None = None  # per-frame stamps where the file has them

    def __len__(self) -> int:
        return self.frame_count

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.path)!r}: {self.frame_count} frames of "
                f"{self.width}x{self.height} px, {self.bit_depth}-bit, {self.fps:g} fps)")

    @property
    def frame_interval_s(self) -> float:
        """Nominal time between consecutive stored frames, ``frame_step / fps`` seconds."""
        return self.frame_step / self.fps

    def read(self, index: int) -> np.ndarray:
        """Read one frame from disk.

        Parameters
        ----------
        index : int
            Position of the frame in the file, 0-based; negative counts from
            the end as for a sequence.

        Returns
        -------
        numpy.ndarray
            A new ``(height, width)`` array of :attr:`dtype`, grey values in
            ``[0, 2**bit_depth - 1]``, row 0 at the top of the image.

        Raises
        ------
        IndexError
            ``index`` is outside the file's frames.
        flow.io.errors.InputError
            The frame's bytes are missing or inconsistent with the header.
        """
        return self._read_frame(self._check_index(index))

    def time_s(self, index: int) -> float:
        """Time of one frame in seconds after the first stored frame.

        Parameters
        ----------
        index : int
            Position of the frame in the file (as for :meth:`read`).

        Returns
        -------
        float
            ``index * frame_step / fps`` unless the file stores per-frame time
            stamps (Phantom's TIME64 block), which are then used.
        """
        i = self._check_index(index)
        if self._times is not None:
            return float(self._times[i])
        return i * self.frame_step / self.fps

    def timestamps_s(self) -> np.ndarray:
        """Times of all frames in seconds after the first stored frame.

        Returns
        -------
        numpy.ndarray
            ``(frame_count,)`` float64, as :meth:`time_s` gives them.
        """
        if self._times is not None:
            return self._times.copy()
        return np.arange(self.frame_count, dtype=np.float64) * (self.frame_step / self.fps)

    # -- for the readers ------------------------------------------------------------------

    def _check_index(self, index: int) -> int:
        i = operator.index(index)
        if not -self.frame_count <= i < self.frame_count:
            raise IndexError(f"frame {i} is outside {self.path.name}'s "
                             f"{self.frame_count} frames (0..{self.frame_count - 1})")
        return i % self.frame_count

    def _read_frame(self, index: int) -> np.ndarray:
        raise NotImplementedError

    def _read_bytes(self, offset: int, size: int) -> bytes:
        """Read exactly ``size`` bytes at ``offset`` of :attr:`data_path`, and no more."""
        with open(self.data_path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
        if len(data) != size:
            raise InputError(f"{self.data_path.name} ends at byte {offset + len(data)}, inside "
                             f"data the header places at bytes {offset}..{offset + size}: the "
                             "file is truncated; copy it again from the camera or its computer")
        return data


def unpack_bits(data: bytes, bits: Literal[10, 12], count: int) -> np.ndarray:
    """Unpack pixels packed back to back, most significant bit first.

    Parameters
    ----------
    data : bytes
        The packed bytes: for 12 bits, two pixels in three bytes; for 10
        bits, four pixels in five bytes.
    bits : {10, 12}
        Bits per pixel.
    count : int
        Pixels to unpack; a multiple of the pixels per group (2 or 4).

    Returns
    -------
    numpy.ndarray
        ``(count,)`` uint16 values in ``[0, 2**bits - 1]``.
    """
    per_group = {10: 4, 12: 2}[bits]
    group_bytes = per_group * bits // 8
    if count % per_group:
        raise ValueError(f"{count} pixels do not fill whole {bits}-bit groups of {per_group}")
    groups = np.frombuffer(data, np.uint8, count // per_group * group_bytes)
    groups = groups.reshape(-1, group_bytes).astype(np.uint64)
    word = np.zeros(len(groups), np.uint64)
    for column in range(group_bytes):  # the group as one big-endian integer
        word = (word << np.uint64(8)) | groups[:, column]
    shifts = np.arange(per_group - 1, -1, -1, dtype=np.uint64) * np.uint64(bits)
    pixels = (word[:, None] >> shifts[None, :]) & np.uint64((1 << bits) - 1)
    return pixels.astype(np.uint16).reshape(-1)
