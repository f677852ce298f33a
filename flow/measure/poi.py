"""Points of interest (paper section 3.1): a binary mask selects the pixels to track."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from flow.io.errors import InputError
from flow.io.frames import Roi
from flow.io.imagefiles import exif_orientation, read_image
from flow.io.video import DISPLAY_ROTATIONS


def mask_labels(image: np.ndarray) -> np.ndarray:
    """Region labels (int32, 0 = no POI) of a mask image: an image whose non-zero grey values
    all lie in 1..127 is a labelled mask, each value a region keeping its label (1, 2, ..., N,
    or with gaps: a mask of regions 1 and 3 measures regions 1 and 3); any other image is a
    binary mask, white (> 127) = POI, one region (label 1)."""
    values = np.unique(image[image > 0])
    if values.size and values[-1] < 128:
        return image.astype(np.int32)
    return (image > 127).astype(np.int32)


def read_mask_image(path: str | Path) -> tuple[np.ndarray | None, str, bool]:
    """A mask file's grey image (None where it cannot be decoded), the decoder's complaint, and
    whether its alpha channel decided it.

    Image editors save a mask drawn on a transparent layer with an alpha channel, and the
    colour under the transparent pixels is whatever the editor keeps there (white, in some):
    read as grey alone, such a mask selected the whole frame. Transparent pixels (alpha below
    128) are therefore not part of the mask. A 16-bit grey mask whose values fit in 8 bits (a
    labelling tool's labels) is read by its values (OpenCV's grey read keeps the high byte).
    Both come from the file's pixels as stored; one whose EXIF orientation would turn them is
    refused (the grey read turns the image, the full read does not)."""
    path = Path(path)
    image, complaint = read_image(path, cv2.IMREAD_GRAYSCALE)
    if image is None:
        return None, complaint, False
    full, _ = read_image(path, cv2.IMREAD_UNCHANGED)
    labels16 = full is not None and full.ndim == 2 and full.dtype == np.uint16 and int(full.max()) <= 255
    alpha = full[..., 3] if full is not None and full.ndim == 3 and full.shape[2] == 4 else None
    if alpha is not None and alpha.dtype != np.uint8:
        alpha = (alpha >> 8).astype(np.uint8) if alpha.dtype == np.uint16 else np.clip(alpha * 255.0, 0, 255).astype(np.uint8)
    transparent = alpha is not None and bool((alpha < 128).any())
    if not (labels16 or transparent):
        return image, complaint, False
    if exif_orientation(path) != 1:
        raise InputError(f"mask {path.name} has an EXIF orientation tag as well as "
                         f"{'16-bit values' if labels16 else 'transparent pixels'}: save it turned as it "
                         "should be, without the tag")
    if labels16:
        return full.astype(np.uint8), complaint, False
    return np.where(alpha >= 128, image, 0).astype(np.uint8), complaint, True


def load_mask(path: str | Path, *, frame_size: tuple[int, int], roi: Roi, what: str = "mask",
              instead: str = "--rect/--polygon", rotation_deg: int = 0,
              notes: list[str] | None = None, labels: bool = False) -> np.ndarray:
    """Read a mask PNG (full-frame or ROI size) and return it as an ROI-sized bool array
    (``labels``: the int32 region labels of :func:`mask_labels`).

    ``what`` names the mask in messages, ``instead`` the options that can replace it.
    ``rotation_deg``: the video's display rotation (frames are measured as displayed); a
    full-frame mask drawn on the stored frames of a 90/270 degree video is rotated to match
    (said in ``notes``). A decoder's warning about a mask that decodes (libpng on a colour
    profile) goes in ``notes`` too, not on stderr.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{what} {str(path)!r} does not exist: check the path or use {instead}")
    image, complaint, transparent = read_mask_image(path)
    if image is None:
        because = f" ({complaint})" if complaint else ""
        raise InputError(f"{what} {str(path)!r} cannot be read{because}: save it as an 8-bit PNG")
    if complaint and notes is not None:
        notes.append(f"{what} {path.name} decoded with a warning: {complaint}")
    if transparent and notes is not None:
        notes.append(f"{what} {path.name} has transparent pixels (alpha below 128): they are not part of it")
    height, width = image.shape
    if rotation_deg in (90, 270) and (height, width) == tuple(frame_size) and (width, height) != tuple(frame_size):
        image = cv2.rotate(image, DISPLAY_ROTATIONS[rotation_deg])
        height, width = image.shape
        if notes is not None:
            notes.append(f"{what} {Path(path).name} is drawn on the stored (unrotated) frames: rotated by "
                         f"{rotation_deg} degrees to the displayed frames that are measured")
    if (width, height) == tuple(frame_size):
        image = image[roi.y:roi.y + roi.height, roi.x:roi.x + roi.width]
    elif (width, height) != (roi.width, roi.height):
        rotated = (f"; the video is displayed rotated by {rotation_deg} degrees and measured as displayed"
                   if rotation_deg else "")
        raise InputError(
            f"{what} is {width}x{height} but frames are {frame_size[0]}x{frame_size[1]} "
            f"(ROI {roi.width}x{roi.height}{rotated}): pass --roi or a full-size mask")
    return mask_labels(image) if labels else image > 127


def pixels_outside_roi(path: str | Path, *, frame_size: tuple[int, int], roi: Roi) -> int:
    """How many of a full-frame mask's pixels the ROI leaves out (0 for an ROI-sized mask)."""
    image, _, _ = read_mask_image(path)
    if image is None or (image.shape[1], image.shape[0]) != tuple(frame_size):
        return 0
    labels = mask_labels(image) > 0
    return int(labels.sum() - labels[roi.y:roi.y + roi.height, roi.x:roi.x + roi.width].sum())


def rect_mask(text: str, *, roi: Roi) -> np.ndarray:
    """Mask of the rectangle ``X,Y,W,H`` given in full-frame pixels."""
    try:
        x, y, w, h = (int(v) for v in text.split(","))
    except ValueError:
        raise InputError(f"--rect {text!r} is not X,Y,W,H (four integers)") from None
    mask = np.zeros((roi.height, roi.width), bool)
    mask[max(y - roi.y, 0):max(y - roi.y + h, 0), max(x - roi.x, 0):max(x - roi.x + w, 0)] = True
    return mask


def polygon_mask(text: str, *, roi: Roi) -> np.ndarray:
    """Mask of the polygon ``X1,Y1,X2,Y2,...`` given in full-frame pixels."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        raise InputError(f"--polygon {text!r} is not X1,Y1,X2,Y2,... (numbers)") from None
    if len(values) < 6 or len(values) % 2:
        raise InputError(f"--polygon {text!r} needs at least three X,Y vertices")
    vertices = np.asarray(values).reshape(-1, 2) - [roi.x, roi.y]
    mask = np.zeros((roi.height, roi.width), np.uint8)
    cv2.fillPoly(mask, [np.round(vertices).astype(np.int32)], 255)
    return mask > 0


def poi_coordinates(mask: np.ndarray, *, grid_step: int = 1) -> np.ndarray:
    """``(P, 2)`` int32 ``(x, y)`` ROI coordinates of the mask pixels, optionally on a grid.

    Raises ``InputError`` if no POI remains.
    """
    if grid_step < 1:
        raise InputError(f"--grid-step {grid_step} must be >= 1")
    sub = np.zeros_like(mask)
    sub[::grid_step, ::grid_step] = mask[::grid_step, ::grid_step]
    ys, xs = np.nonzero(sub)
    if len(xs) == 0:
        raise InputError("the mask selects no pixel inside the ROI: draw the structure in white (255) "
                         "on black, or check --roi/--rect/--grid-step")
    return np.stack([xs, ys], axis=1).astype(np.int32)
