"""Streaming frame input: any video OpenCV decodes, or a folder of images.

Frames come out one at a time as grey ROI crops with their true timestamps,
so memory stays constant whatever the clip length or sensor size.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp")


class InputError(ValueError):
    """Bad user input; the message names the problem and what to do."""


@dataclass(frozen=True)
class Roi:
    """Crop window in full-sensor pixels."""

    x: int
    y: int
    width: int
    height: int

    @classmethod
    def parse(cls, text: str) -> Roi:
        try:
            x, y, w, h = (int(v) for v in text.split(","))
        except ValueError:
            raise InputError(f"--roi {text!r} is not X,Y,W,H (four integers, e.g. 100,50,800,400)") from None
        return cls(x, y, w, h)

    def check(self, frame_width: int, frame_height: int) -> None:
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"ROI {self.as_text()} has non-positive size: pass --roi X,Y,W,H with W,H > 0")
        if (self.x < 0 or self.y < 0 or self.x + self.width > frame_width
                or self.y + self.height > frame_height):
            raise InputError(
                f"ROI {self.as_text()} lies outside the {frame_width}x{frame_height} frame: "
                f"pass an --roi inside 0,0,{frame_width},{frame_height}")

    def as_text(self) -> str:
        return f"{self.x},{self.y},{self.width},{self.height}"

    def as_dict(self) -> dict[str, int]:
        return {"x": self.x, "y": self.y, "width": self.width, "height": self.height}


def to_grey(image: np.ndarray) -> np.ndarray:
    """Grey uint8 view of a decoded frame (BGR, BGRA, grey or 16-bit)."""
    if image.dtype == np.uint16:
        image = (image >> 8).astype(np.uint8)
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    return image


class FrameSource:
    """Sequential reader of grey ROI frames with timestamps.

    Parameters
    ----------
    path : str or Path
        A video file or a folder of images (sorted by name).
    roi : Roi, optional
        Crop window in full-sensor pixels; the whole frame if omitted.
    fps : float, optional
        Frame rate for image folders (required there); for videos it
        overrides the header only where the decoder gives no timestamps.

    Iterating yields ``(index, time_s, grey_roi)``. After iteration,
    ``frames_read`` holds the number of decoded frames and ``truncated``
    tells whether the video delivered fewer frames than its header claims.
    """

    def __init__(self, path: str | Path, *, roi: Roi | None = None, fps: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise InputError(f"input {str(self.path)!r} does not exist: check the path")
        self.is_folder = self.path.is_dir()
        self.frames_read = 0
        self.truncated = False
        if self.is_folder:
            self._files = sorted(p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
            if not self._files:
                raise InputError(f"folder {str(self.path)!r} holds no images ({', '.join(IMAGE_SUFFIXES)})")
            first = cv2.imread(str(self._files[0]), cv2.IMREAD_UNCHANGED)
            if first is None:
                raise InputError(f"image {str(self._files[0])!r} cannot be read: is it a valid image?")
            self.height, self.width = first.shape[:2]
            if fps is not None and fps <= 0:
                raise InputError(f"--fps {fps} is not positive: pass the camera frame rate")
            self.fps = float(fps) if fps else float("nan")
            self.header_frames = len(self._files)
        else:
            cap = cv2.VideoCapture(str(self.path))
            if not cap.isOpened():
                raise InputError(
                    f"video {str(self.path)!r} cannot be opened by OpenCV: is it a video file "
                    "(MP4/MOV/MKV/AVI) or a folder of images?")
            self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
            self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
            header_fps = cap.get(cv2.CAP_PROP_FPS)
            self.fps = float(fps) if fps else (header_fps if header_fps and header_fps > 0 else float("nan"))
            self.header_frames = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)
            ok, first = cap.read()
            cap.release()
            if not ok or first is None:
                raise InputError(
                    f"video {str(self.path)!r} has no decodable frame: the file is empty, "
                    "truncated or in a codec this OpenCV build lacks")
            self.height, self.width = first.shape[:2]
        self.roi = roi if roi is not None else Roi(0, 0, self.width, self.height)
        self.roi.check(self.width, self.height)

    @property
    def size(self) -> tuple[int, int]:
        """Full frame ``(width, height)``."""
        return self.width, self.height

    def _crop(self, image: np.ndarray) -> np.ndarray:
        r = self.roi
        # Crop before the colour conversion so 4K frames are never converted whole.
        return to_grey(np.ascontiguousarray(image[r.y:r.y + r.height, r.x:r.x + r.width]))

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        self.frames_read = 0
        if self.is_folder:
            yield from self._iter_folder()
        else:
            yield from self._iter_video()

    def _iter_folder(self) -> Iterator[tuple[int, float, np.ndarray]]:
        for index, file in enumerate(self._files):
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"image {str(file)!r} cannot be read: remove or replace it")
            if image.shape[:2] != (self.height, self.width):
                raise InputError(
                    f"image {file.name} is {image.shape[1]}x{image.shape[0]} but the first is "
                    f"{self.width}x{self.height}: all images must have the same size")
            self.frames_read = index + 1
            time_s = index / self.fps if math.isfinite(self.fps) else float(index)
            yield index, time_s, self._crop(image)

    def _iter_video(self) -> Iterator[tuple[int, float, np.ndarray]]:
        cap = cv2.VideoCapture(str(self.path))
        try:
            index = 0
            while True:
                ok, image = cap.read()
                if not ok or image is None:
                    break
                msec = cap.get(cv2.CAP_PROP_POS_MSEC)
                # Decoders report the presentation time of the frame just read; some give 0
                # for every frame, so fall back to index/fps unless it advances.
                if index > 0 and msec <= 0 and math.isfinite(self.fps):
                    time_s = index / self.fps
                elif index == 0 and msec <= 0:
                    time_s = 0.0
                else:
                    time_s = msec / 1000.0
                self.frames_read = index + 1
                yield index, time_s, self._crop(image)
                index += 1
        finally:
            cap.release()
        if self.header_frames and self.frames_read < self.header_frames:
            self.truncated = True
            warnings.warn(
                f"video {self.path.name}: header says {self.header_frames} frames but only "
                f"{self.frames_read} could be decoded (truncated or damaged file); "
                f"results cover the {self.frames_read} decoded frames", stacklevel=2)
