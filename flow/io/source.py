"""The one opener of a measurement's frames: :func:`open_source` picks the reader for a path,
one per kind of input (after imageio v3's ``imopen``).

* a folder: :class:`~flow.io.folder.ImageFolderSource` (images in name order);
* a TIFF file of several pages (a stack): :class:`~flow.io.tiffstack.TiffStackSource`;
* a Photron ``.cih``/``.cihx`` or a Phantom ``.cine``: :class:`~flow.io.camera.CameraSource`;
* anything else: :class:`~flow.io.video.VideoSource` (any video OpenCV's ffmpeg decodes).

Frames come out one at a time as grey ROI crops with their true timestamps, so memory stays
constant whatever the clip length or sensor size. A new kind of input is a new reader module
here (a :class:`~flow.io.frames.FrameSource` subclass) and one more case below.
"""

from __future__ import annotations

from pathlib import Path

from flow.io.camera import CameraSource, open_camera_file
from flow.io.errors import InputError
from flow.io.folder import ImageFolderSource
from flow.io.frames import FrameSource, Roi, check_fps
from flow.io.tiffstack import TiffStackSource, is_tiff_stack
from flow.io.video import VideoSource

__all__ = ["open_source"]


def open_source(path: str | Path, *, roi: Roi | None = None, fps: float | None = None,
                require_fps: bool = True, allow_truncated: bool = False,
                exclude: tuple[Path, ...] = ()) -> FrameSource:
    """The reader of ``path``'s frames, its header read and its first frame checked.

    Parameters
    ----------
    path : str or Path
        A video file, a folder of images (in name order), a TIFF stack or a high-speed camera
        recording.
    roi : Roi, optional
        Crop window in full-sensor pixels; the whole frame if omitted.
    fps : float, optional
        Frame rate of an image folder (required there unless ``require_fps=False``: images
        carry no timestamps); on a video, the capture rate where it differs from the file's;
        on a camera recording, a rate that overrides its header's.
    require_fps : bool
        False lets an image folder go without ``fps`` (tools that need no time, e.g.
        calibration); its ``time_s`` is then the frame index.
    allow_truncated : bool
        A video that stops decoding well before its container's duration is truncated:
        iterating to its end raises :class:`InputError` unless this is True, in which case it
        warns and the decoded frames stand.
    exclude : tuple of Path
        The run's other input files (masks): never frames of a folder that holds them.

    Raises
    ------
    InputError
        The path does not exist, ``fps`` is no camera's rate, or the input cannot be
        measured (the message says why and what to do).
    """
    path = Path(path)
    if not path.exists():
        raise InputError(f"input {str(path)!r} does not exist: check the path")
    check_fps(fps)
    if path.is_dir():
        return ImageFolderSource(path, roi=roi, fps=fps, require_fps=require_fps, exclude=exclude)
    if is_tiff_stack(path):
        return TiffStackSource(path, roi=roi, fps=fps, require_fps=require_fps)
    camera = open_camera_file(path)
    if camera is not None:
        return CameraSource(path, camera, roi=roi, fps=fps)
    return VideoSource(path, roi=roi, fps=fps, allow_truncated=allow_truncated)
