"""Windows cut out of a frame: the bounding box of the pixels a measurement reads, grown by a
margin and clipped to the frame (the driver's work area, a dense method's solve window)."""

from __future__ import annotations

import numpy as np

# A window covering more than this share of the frame is not worth cutting out.
CROP_MAX_SHARE = 0.8


def bounding_box(needed: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(first row, last row, first column, last column)`` of the True pixels (None: none)."""
    rows = np.flatnonzero(needed.any(axis=1))
    if rows.size == 0:
        return None
    cols = np.flatnonzero(needed.any(axis=0))
    return int(rows[0]), int(rows[-1]), int(cols[0]), int(cols[-1])


def crop_window(shape: tuple[int, int], needed: np.ndarray, margin: int) -> tuple[slice, slice] | None:
    """Rows and columns of the bounding box of ``needed`` grown by ``margin`` px and clipped to
    the frame; None where it would cover most of the frame anyway (or nothing is needed)."""
    return box_window(shape, bounding_box(needed), margin)


def box_window(shape: tuple[int, int], box: tuple[int, int, int, int] | None,
               margin: int) -> tuple[slice, slice] | None:
    """:func:`crop_window` of a bounding box (:func:`bounding_box`)."""
    if box is None:
        return None
    height, width = shape
    r0, r1 = max(box[0] - margin, 0), min(box[1] + margin + 1, height)
    c0, c1 = max(box[2] - margin, 0), min(box[3] + margin + 1, width)
    if (r1 - r0) * (c1 - c0) > CROP_MAX_SHARE * height * width:
        return None
    return slice(r0, r1), slice(c0, c1)
