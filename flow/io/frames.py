"""What every reader gives: a :class:`FrameSource` of grey ROI frames with their times, the
:class:`Roi` they are cropped to, and the grey scale (8-bit frames as they are, deeper ones
brought to it by one gain for the whole sequence).

The readers, one per kind of input (:mod:`flow.io.video`, :mod:`flow.io.folder`,
:mod:`flow.io.tiffstack`, :mod:`flow.io.camera`), subclass :class:`FrameSource` (the folder and
the stack through :class:`ImageSequence`, what images without time stamps share);
:func:`flow.io.source.open_source` picks the one for a path.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from flow.io.errors import InputError

__all__ = ["FLOAT_BITS", "FPS_RANGE", "FrameSource", "ImageSequence", "Roi", "as_uint8", "check_fps",
           "copied_share", "deep_image_gain", "significant_bits", "to_grey", "unchanged_windows"]

# Frames in lossless files can still be a lossy codec's output (a phone video exported to PNG or
# TIFF images, as many DIC tools want their input). Such a codec leaves what a camera's frames never
# show: a block it did not need to code (a still background, a structure moving less than the codec
# codes) is the frame before's, bit for bit, though the scene there has changed since the first
# frame. A window of COPY_WINDOW_PX x COPY_WINDOW_PX pixels with texture in it (a spread of at least
# COPY_MIN_RANGE grey levels: not a saturated sky or a black corner) equal to the frame before in
# every pixel and not to the first is such a copy: sensor noise never leaves one, and a scene
# without noise (a render) leaves one only where its motion stays below the grey levels' rounding
# for a frame (its still background is the first frame's too), and is then read as a lossy stream:
# mostly as well (the tests' scenes without noise: a faint panel 0.018 -> 0.014 px, a girder moving
# a few tenths of a pixel 0.0006 -> 0.0011, a textured panel and a faint texture filling the view
# within 0.0001 px), but a panel of 0.9 grey levels per pixel moving 0.3 px read 0.045 -> 0.199 px
# (slope 0.86 -> 0.12): the note names the way out, --param bias_correction=true (see
# flow.pipeline._for_source). Measured on the bench's 16 H.264 clips exported to PNG, the largest
# share over the first eight pairs of frames: 7-64 % of the textured windows (CRF 12-30; the whole
# view moving: one pair of the eight); on the DIC Challenge's images, a Phantom and a Photron
# camera file: none. (A lossy stream's texture fit leaves such windows out:
# flow.methods.deepflow.codecfloor.codec_copies.)
COPY_WINDOW_PX = 8
COPY_MIN_RANGE = 2.0
HISTORY_PAIRS = 8
HISTORY_SHARE = 0.01


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



# 16-bit images are brought to the 8-bit grey scale by one gain for the whole sequence, taken
# from the first image: its 99.9th percentile lands here, leaving headroom for brighter frames.
# They stay float32 (full depth, not rounded to 8 bits): the grey scale only keeps the methods'
# thresholds (grey levels) meaning the same as for 8-bit video.
DEEP_TARGET_LEVEL = 204.0


def deep_image_gain(image: np.ndarray) -> float:
    """The constant gain that brings a 16-bit sequence whose first image is ``image`` to the
    8-bit grey scale.

    High-speed cameras store 10-14-bit data in 16-bit words, often far below full scale: a
    fixed ``>> 8`` would leave an underexposed 10-bit clip (values 20-250) at 0-0 grey.
    """
    finite = image[np.isfinite(image)] if image.dtype.kind == "f" else image
    level = float(np.percentile(finite, 99.9)) if finite.size else 0.0
    if image.dtype.kind == "f":
        # Floating-point data has no unit (0-1 from most tools, counts from others).
        return DEEP_TARGET_LEVEL / level if level > 0 else 1.0
    return DEEP_TARGET_LEVEL / max(level, 1.0)


def significant_bits(image: np.ndarray) -> int:
    """Bits the data of ``image`` uses (a 12-bit camera's values fit in 12), at least 8."""
    top = int(image.max()) if image.size else 0
    return max(8, top.bit_length())



# second (beyond the fastest framing cameras, about 10^8). Outside them the number is a typing
# error, and index / fps may not even be finite (--fps 4e-320 gives time_s = inf).
FPS_RANGE = (1e-6, 1e10)


def unchanged_windows(current: np.ndarray, earlier: np.ndarray, side: int = COPY_WINDOW_PX) -> np.ndarray:
    """Where the ``side`` x ``side`` window about each pixel (``side // 2`` rows and columns
    before it to ``side // 2 - 1`` after) of ``current`` equals ``earlier`` in every pixel (bool,
    their shape); a window reaching past their edge does not."""
    equal = (current == earlier).view(np.uint8)
    return cv2.erode(equal, np.ones((side, side), np.uint8), borderType=cv2.BORDER_CONSTANT,
                     borderValue=0).astype(bool)


def copied_share(frames: Iterator[np.ndarray]) -> float:
    """The largest share, over the pairs of consecutive ``frames`` (grey, one shape) after the
    first, of a frame's textured windows that are the frame before's bit for bit but not the
    first frame's (see COPY_WINDOW_PX): above HISTORY_SHARE, the frames have been through a lossy
    codec. A pair equal in every pixel (a repeated frame) tells nothing and is passed over."""
    window = np.ones((COPY_WINDOW_PX, COPY_WINDOW_PX), np.uint8)
    largest, first, before = 0.0, None, None
    for frame in frames:
        if first is None:
            first = frame
        elif before is not None and not np.array_equal(before, frame):
            level = frame if frame.dtype in (np.uint8, np.float32) else frame.astype(np.float32)
            textured = (cv2.dilate(level, window).astype(np.float32) - cv2.erode(level, window)) >= COPY_MIN_RANGE
            if textured.any():
                copied = unchanged_windows(frame, before) & ~unchanged_windows(frame, first) & textured
                largest = max(largest, float(np.count_nonzero(copied) / np.count_nonzero(textured)))
        before = frame
    return largest


def check_fps(fps: float | None, name: str = "--fps") -> None:
    """Refuse a frame rate (None: not given) that is not a camera's."""
    if fps is None:
        return
    if not (math.isfinite(fps) and fps > 0):
        raise InputError(f"{name} {fps} is not a finite positive number: pass the camera frame rate in frames per second")
    if not FPS_RANGE[0] <= fps <= FPS_RANGE[1]:
        raise InputError(f"{name} {fps:g} is no camera's frame rate ({FPS_RANGE[0]:g} to {FPS_RANGE[1]:g} frames "
                         "per second): pass the camera frame rate in frames per second")



def to_grey(image: np.ndarray, gain: float | None = None) -> np.ndarray:
    """Grey view of a decoded frame (BGR, BGRA, grey, 16-bit, 32-bit or floating-point).

    8-bit frames stay uint8. ``gain``: the sequence's gain for deeper data
    (:func:`deep_image_gain`): the frame comes out float32 on the 8-bit grey scale at full
    depth (neither rounded nor clipped); None: ``>> 8`` to uint8 for 16-bit data, clipped to
    0-255 otherwise (a view for people, e.g. figures, not for measuring).
    """
    if image.dtype == np.uint16:
        if gain is None:
            image = (image >> 8).astype(np.uint8)
        else:
            image = image.astype(np.float32) * np.float32(gain)
    elif image.dtype != np.uint8 and gain is not None:  # floating-point or 32-bit images
        image = (image.astype(np.float64) * gain).astype(np.float32)
    elif image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    if image.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        image = cv2.cvtColor(image, code)
    return image


def as_uint8(image: np.ndarray) -> np.ndarray:
    """``image`` rounded and clipped to uint8 (itself when it is uint8 already): for the OpenCV
    functions that take 8-bit images only (DIS, Farneback, pyramidal LK, corner detection)."""
    if image.dtype == np.uint8:
        return image
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


class FrameSource:
    """Sequential reader of grey ROI frames with timestamps (the base of every reader; open
    one with :func:`flow.io.source.open_source`).

    Iterating yields ``(index, time_s, grey_roi)`` (uint8; float32 on the 8-bit grey scale for
    deeper data, see :func:`to_grey`); :meth:`frames` yields a range of them. ``width``,
    ``height``, ``fps`` (the rate time_s follows), ``header_fps`` and ``header_frames`` (what
    the file says), ``bit_depth`` and ``rotation_deg`` describe the input; after iterating to
    the end, ``frames_read`` holds the number of decoded frames, ``truncated`` whether the
    file is truncated, and ``notes`` what the user should know (e.g. a header frame count
    that was an estimate, as for variable-frame-rate files).

    A reader sets the size, the rates and the frame count, calls :meth:`_set_roi`, and
    yields its frames from :meth:`_frames`.
    """

    width: int
    height: int
    fps: float
    header_frames: int

    def __init__(self, path: Path, *, allow_truncated: bool = False) -> None:
        self.path = path
        self.allow_truncated = allow_truncated
        self.frames_read = 0
        self.truncated = False
        self._cut: tuple[slice, slice] | None = None  # see cut()
        self.notes: list[str] = []
        self._deep_gain: float | None = None  # deeper than 8 bits: their constant gain to the 8-bit scale
        self.bit_depth = 8  # significant bits of the data measured (16-bit images: the first's)
        self.rotation_deg = 0  # a video's display rotation, applied to its frames
        self.header_fps = float("nan")

    def _set_roi(self, roi: Roi | None) -> None:
        self.roi = roi if roi is not None else Roi(0, 0, self.width, self.height)
        self.roi.check(self.width, self.height)

    def _keep_depth(self, first: np.ndarray, bits: int, what: str) -> None:
        """Frames deeper than 8 bits: one gain to the 8-bit grey scale for the whole sequence,
        from its first frame; measured at full depth (float)."""
        self._deep_gain = deep_image_gain(first)
        self.bit_depth = bits
        self.notes.append(f"{what}: grey = value x {self._deep_gain:.6g} for every frame (the first frame's "
                          f"99.9th percentile -> {DEEP_TARGET_LEVEL:g} of 255), kept at full depth (float, "
                          f"not rounded to 8 bits; {bits}-bit data)")

    @property
    def lossless(self) -> bool:
        """Whether the frames are what the camera recorded (a lossless codec, lossless image
        files, a camera file); each reader says. False where not known."""
        return False

    def copied_share(self) -> float:
        """:func:`copied_share` of the first HISTORY_PAIRS pairs of frames: above HISTORY_SHARE,
        frames that a lossy codec made, whatever files hold them."""
        frames = self.frames(0, HISTORY_PAIRS + 1)
        try:
            return copied_share(frame for _, _, frame in frames)
        finally:
            frames.close()

    @property
    def codec_crf(self) -> float | None:
        """The constant rate factor a lossy H.264 stream says it was encoded with (x264 writes
        its settings into the stream); None where the frames are lossless or the encoder did not
        say."""
        return None

    @property
    def size(self) -> tuple[int, int]:
        """Full frame ``(width, height)``."""
        return self.width, self.height

    def _crop(self, image: np.ndarray) -> np.ndarray:
        r = self.roi
        # Crop before the colour conversion so 4K frames are never converted whole.
        image = image[r.y:r.y + r.height, r.x:r.x + r.width]
        if self._cut is not None:
            image = image[self._cut]
        return to_grey(np.ascontiguousarray(image), self._deep_gain)

    @contextlib.contextmanager
    def cut(self, area: tuple[slice, slice] | None) -> Iterator[None]:
        """Within the block, frames come out cut to ``area`` (rows, columns of the ROI), cut
        before the colour conversion: a reader that needs only part of the ROI (the driver's
        work area around a small member) never converts a 4K frame whole."""
        self._cut = area
        try:
            yield
        finally:
            self._cut = None

    def __iter__(self) -> Iterator[tuple[int, float, np.ndarray]]:
        return self.frames()

    def frames(self, start: int = 0, stop: int | None = None) -> Iterator[tuple[int, float, np.ndarray]]:
        """Frames ``start <= index < stop`` (``stop`` None: to the end).

        Frames before ``start`` are still read in order (timestamps and decoding
        need it) but are not converted; stopping early skips the truncation check.
        """
        self.frames_read = 0
        yield from self._frames(start, stop)

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        raise NotImplementedError

    def clock(self, frame: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """The time stamps of the measured frames ``frame`` (read as ``time_s``), checked, and
        what the user should know of them (for the notes and the console). Images and camera
        files have no stamps to check: their times stand (a video's: :class:`~flow.io.video.VideoSource`).
        """
        return np.asarray(time_s, np.float64), []


#: Bits a float32 grey keeps (its significand): the depth of floating-point and 32-bit data measured.
FLOAT_BITS = 24


class ImageSequence(FrameSource):
    """The part of an image-based reader (a folder of images, a TIFF stack) that is the same for
    both: images carry no time stamps (``time_s`` = index / ``fps``), one pixel type and size
    for all, deeper than 8 bits measured at full depth with one gain from the first image, and
    every image checked as it is read (size, pixel type, NaN)."""

    def _take_first(self, first: np.ndarray, fps: float | None, what: str) -> None:
        """Size, pixel type and depth from the first image (``what``: "images", "TIFF pages")."""
        self.height, self.width = first.shape[:2]
        self._dtype = first.dtype  # one gain and one grey scale for all: one pixel type for all
        self.fps = float(fps) if fps else float("nan")
        if first.dtype == np.uint16:
            self._keep_depth(first, significant_bits(first), f"16-bit {what}")
        elif first.dtype != np.uint8:
            # Floating-point (TIFF's SampleFormat 3) or 32-bit integer images, as DIC tools and
            # scientific cameras write them: one gain like 16-bit data's, measured as float32.
            kind = "floating-point" if first.dtype.kind == "f" else "integer"
            self._keep_depth(first, min(FLOAT_BITS, 8 * first.dtype.itemsize),
                             f"{8 * first.dtype.itemsize}-bit {kind} {what}")

    def _time(self, index: int) -> float:
        return index / self.fps if math.isfinite(self.fps) else float(index)

    def _checked(self, image: np.ndarray, name: str) -> np.ndarray:
        """The grey ROI crop of ``image`` (``name``: "image f1.tif", "page 3 of s.tif" in
        messages), refused where its size or pixel type is not the first's or where the area
        read holds NaN or infinite values."""
        if image.shape[:2] != (self.height, self.width):
            raise InputError(f"{name} is {image.shape[1]}x{image.shape[0]} but the first is "
                             f"{self.width}x{self.height}: all images must have the same size")
        if image.dtype != self._dtype:
            raise InputError(f"{name} holds {image.dtype} pixels but the first holds {self._dtype}: "
                             "all images must have one pixel type (convert them alike)")
        grey = self._crop(image)
        if grey.dtype == np.float32 and not np.isfinite(grey).all():
            bad = ~np.isfinite(grey)
            row, col = (int(i[0]) for i in np.nonzero(bad))
            rows, cols = self._cut if self._cut is not None else (slice(0), slice(0))
            x, y = self.roi.x + (cols.start or 0) + col, self.roi.y + (rows.start or 0) + row
            raise InputError(f"{name} holds {int(bad.sum())} NaN or infinite pixel(s) in the area read (the "
                             f"first at x={x}, y={y}): pass an --roi that leaves them out, or replace them "
                             "(e.g. from their neighbours)")
        return grey
