"""The high-speed camera reader: a Photron (:mod:`flow.io.photron`) or Phantom
(:mod:`flow.io.phantom`) recording, opened by its suffix (:func:`open_camera_file`), as a
:class:`~flow.io.frames.FrameSource`: one frame read from disk at a time, timed by the file's
own clock.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from flow.io.camfiles import CameraFile
from flow.io.frames import FrameSource, Roi
from flow.io.phantom import PhantomCine
from flow.io.photron import PhotronMraw

__all__ = ["CameraSource", "open_camera_file"]


def open_camera_file(path: str | os.PathLike[str]) -> CameraFile | None:
    """Open a high-speed camera recording by its suffix.

    Parameters
    ----------
    path : str or os.PathLike
        A Photron header (``.cih`` or ``.cihx``, with its ``.mraw`` beside it)
        or a Phantom ``.cine``. The suffix is matched case-insensitively.

    Returns
    -------
    CameraFile or None
        A reader with the header parsed, or None when the suffix is none of
        :data:`~flow.io.camfiles.CAMERA_SUFFIXES` (the caller then tries other readers).

    Raises
    ------
    flow.io.errors.InputError
        The file is missing, malformed, truncated or in a variant these
        readers do not support.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in (".cih", ".cihx"):
        return PhotronMraw(p)
    if suffix == ".cine":
        return PhantomCine(p)
    return None


class CameraSource(FrameSource):
    """A high-speed camera recording: size, rate and depth from its header.

    Parameters
    ----------
    path : Path
        The file the user named (the ``.cih``/``.cihx`` or the ``.cine``).
    camera : CameraFile
        Its reader, the header parsed.
    roi : Roi, optional
        Crop window in full-frame pixels; the whole frame if omitted.
    fps : float, optional
        A rate that overrides the header's: time_s = index / fps.
    """

    def __init__(self, path: Path, camera: CameraFile, *, roi: Roi | None = None,
                 fps: float | None = None) -> None:
        super().__init__(path)
        self._camera = camera
        self._open_camera(fps)
        self._set_roi(roi)

    @property
    def lossless(self) -> bool:
        """A high-speed camera's recording: the sensor's own values."""
        return True

    def _open_camera(self, fps: float | None) -> None:
        """A high-speed camera recording (:mod:`flow.io.camfiles`): size, rate, depth from its header."""
        camera = self._camera
        self.width, self.height = camera.width, camera.height
        self.header_frames = camera.frame_count
        # The rate of the frames stored: a Photron file saved with a step keeps every n-th frame.
        self.header_fps = camera.fps / camera.frame_step
        if camera.frame_step > 1:
            self.notes.append(f"{self.path.name}: recorded at {camera.fps:g} fps, every {camera.frame_step}th "
                              f"frame saved (Save Step): frames are {1 / self.header_fps:.6g} s apart")
        if camera.timestamps_note:
            self.notes.append(f"{self.path.name}: {camera.timestamps_note}")
        self.fps = float(fps) if fps else self.header_fps
        if fps and abs(self.fps / self.header_fps - 1) > 1e-3:
            self.notes.append(f"--fps {self.fps:g} overrides the {self.header_fps:g} fps of the file's header: "
                              "time_s = index / --fps")
        if camera.dtype == np.uint16:  # the gain comes from the first frame
            self._keep_depth(camera.read(0), camera.bit_depth, f"{camera.bit_depth}-bit camera data")

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        camera = self._camera
        own_clock = math.isclose(self.fps, self.header_fps, rel_tol=1e-3)
        end = camera.frame_count if stop is None else min(stop, camera.frame_count)
        for index in range(start, end):
            self.frames_read = index + 1  # frames are read by position: none before start
            time_s = camera.time_s(index) if own_clock else index / self.fps
            yield index, time_s, self._crop(camera.read(index))
