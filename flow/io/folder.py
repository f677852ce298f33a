"""The image-folder reader: a folder of image files, one frame each, in name order (numbers in
the names compared as numbers: ``img2`` before ``img10``).

Images carry no time stamps: a frame's time is its index over the frame rate the user gives.
Every image's header and structure are checked before the first frame is measured.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from flow.io.errors import InputError
from flow.io.frames import ImageSequence, Roi
from flow.io.imagefiles import (
    ORIENTATION_DEGREES,
    SWAPPING_ORIENTATIONS,
    because,
    check_image_file,
    exif_orientation,
    oriented,
    read_image,
)

__all__ = ["IMAGE_SUFFIXES", "ImageFolderSource"]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".pgm", ".ppm", ".webp")
# Image formats that keep what the sensor recorded (WebP may be either: taken as lossy).
LOSSLESS_IMAGE_SUFFIXES = (".png", ".tif", ".tiff", ".bmp", ".pgm", ".ppm")


_DIGITS = re.compile(r"(\d+)")


def name_order(path: Path) -> tuple:
    """Sort key of an image file: its name with each run of digits compared as a number
    (``frame2.png`` before ``frame10.png``; zero-padded names keep their plain order)."""
    parts = _DIGITS.split(path.name)
    return tuple(int(part) if i % 2 else part for i, part in enumerate(parts)), path.name


def numbering_note(files: list[Path]) -> str | None:
    """What the user should know where the images' names are numbered and the numbers do not
    go up by one (frames left out, or every k-th frame exported): time_s counts one frame per
    image. None where they do, or where the names differ in more than one number."""
    split = [_DIGITS.split(p.stem) for p in files]
    if len(files) < 2 or len({len(parts) for parts in split}) != 1:
        return None
    varying = [i for i in range(1, len(split[0]), 2) if len({parts[i] for parts in split}) > 1]
    if len(varying) != 1 or any(parts[::2] != split[0][::2] for parts in split):
        return None
    numbers = np.array([int(parts[varying[0]]) for parts in split])
    steps = np.diff(numbers)
    if (steps == 1).all():
        return None
    where = f"{files[0].name}, {files[1].name}, ..., {files[-1].name}"
    if (steps == steps[0]).all() and steps[0] > 1:
        return (f"the images' numbers go up by {steps[0]} ({where}): time_s counts one frame per image at "
                f"--fps; if --fps is the camera's rate, pass it divided by {steps[0]}")
    first = files[int(np.argmax(steps != 1))].name
    missing, repeated = int(np.sum(np.maximum(steps - 1, 0))), int(np.sum(steps <= 0))
    odd = " and ".join(([f"skip {missing} value(s)"] if missing else []) + ([f"repeat {repeated} time(s)"] if repeated else []))
    return (f"the numbers in the images' names {odd} (first after {first}; {where}): time_s counts one frame "
            "per image at --fps; where frames are missing there, the times after them are early")


class ImageFolderSource(ImageSequence):
    """A folder of images (in name order, see :func:`name_order`), one frame each.

    Parameters
    ----------
    path : Path
        The folder (it exists: :func:`flow.io.source.open_source` checked).
    roi : Roi, optional
        Crop window in full-frame pixels; the whole frame if omitted.
    fps : float, optional
        The camera's frame rate (required unless ``require_fps=False``: images carry no
        timestamps).
    require_fps : bool
        False lets the folder go without ``fps`` (tools that need no time, e.g. calibration);
        its ``time_s`` is then the frame index.
    exclude : tuple of Path
        Files of the run's other inputs, not frames where the folder holds them.
    """

    def __init__(self, path: Path, *, roi: Roi | None = None, fps: float | None = None,
                 require_fps: bool = True, exclude: tuple[Path, ...] = ()) -> None:
        super().__init__(path)
        # Hidden files are never frames: macOS leaves "._NAME.png" beside every image it copies
        # to a FAT or exFAT drive (its resource forks, not images). Nor are the run's other
        # inputs (``exclude``: a mask kept beside the frames it was drawn on).
        others = {Path(p).resolve() for p in exclude}
        images = [p for p in self.path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
                  and not p.name.startswith(".") and p.is_file()]
        self._files = sorted((p for p in images if p.resolve() not in others), key=name_order)
        for left in sorted(p.name for p in images if p.resolve() in others):
            self.notes.append(f"{left} in the folder is one of the run's other inputs (a mask): not a frame")
        if not self._files:
            raise InputError(f"folder {str(self.path)!r} holds no images ({', '.join(IMAGE_SUFFIXES)})")
        if fps is None and require_fps:
            raise InputError(f"folder {str(self.path)!r} is a sequence of images without timestamps: "
                             "pass --fps (the camera frame rate)")
        check_image_file(self._files[0])
        first, complaint = read_image(self._files[0], cv2.IMREAD_UNCHANGED)
        if first is None:
            raise InputError(f"image {str(self._files[0])!r} cannot be read{because(complaint)}: "
                             "remove or replace it")
        if complaint:
            self.notes.append(f"image {self._files[0].name} (the first) decoded with a warning: {complaint}")
        # Each image as a viewer shows it (its EXIF orientation applied, as for a video's display
        # rotation): a portrait photo is stored landscape, and its mask and --rect are drawn on
        # what is shown.
        self._orientations = [exif_orientation(self._files[0])]
        first = oriented(first, self._orientations[0])
        if self._orientations[0] != 1:
            self.rotation_deg = ORIENTATION_DEGREES.get(self._orientations[0], 0)
            self.notes.append(f"image {self._files[0].name} carries the EXIF orientation {self._orientations[0]}: the "
                              "images are measured as shown; masks, --rect, --roi and --between are read on the "
                              "shown images" + (" (a mask drawn on the stored, unturned image is turned to match)"
                                                if self.rotation_deg in (90, 270) else ""))
        self._take_first(first, fps, "images")
        self._scan_folder()
        self.header_frames = len(self._files)
        numbering = numbering_note(self._files)
        if numbering:
            self.notes.append(numbering)
        self._set_roi(roi)

    @property
    def lossless(self) -> bool:
        """Every image of the folder in a lossless format (one JPEG among them: False)."""
        return all(p.suffix.lower() in LOSSLESS_IMAGE_SUFFIXES for p in self._files)

    def _scan_folder(self) -> None:
        """Check every image's header and structure (not its pixels) before the first frame is
        measured, so that a truncated or mis-sized image stops the run at once, not hours into it."""
        for file in self._files[1:]:
            size = check_image_file(file)
            self._orientations.append(exif_orientation(file))
            if self._orientations[-1] in SWAPPING_ORIENTATIONS:
                size = size[::-1]
            if size != (self.width, self.height):
                raise InputError(f"image {file.name} is {size[0]}x{size[1]} but the first is "
                                 f"{self.width}x{self.height}: all images must have the same size")

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        for index, file in enumerate(self._files[:stop]):
            self.frames_read = index + 1
            if index < start:
                continue
            image = cv2.imread(str(file), cv2.IMREAD_UNCHANGED)
            if image is None:
                raise InputError(f"image {str(file)!r} cannot be read: remove or replace it")
            image = oriented(image, self._orientations[index])
            yield index, self._time(index), self._checked(image, f"image {file.name}")
