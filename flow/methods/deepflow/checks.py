"""Argument checks of the public numerical kernels, made before numba sees the arrays.

numba does not bounds-check: a pair of frames of different sizes, or a colour frame where
a grey one belongs, would make a kernel read memory outside the arrays instead of failing.
Every public entry point of :mod:`flow.methods.deepflow.deepmatching`, :mod:`flow.methods.deepflow.variational` and
:mod:`flow.methods.deepflow.member` therefore checks its arrays here first and raises ``ValueError`` naming
the offending shape or dtype.
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: Pixel types the kernels take: 8-bit frames as decoded, and float32 as the methods' own.
GREY_DTYPES = (np.dtype(np.uint8), np.dtype(np.float32))


def check_grey(label: str, image: Any) -> None:
    """Raise ``ValueError`` unless ``image`` is a 2-D uint8 or float32 array."""
    if not isinstance(image, np.ndarray) or image.ndim != 2:
        raise ValueError(f"{label} must be a 2-D grey image, got ndim {getattr(image, 'ndim', None)} "
                         f"(shape {getattr(image, 'shape', None)}): convert colour frames to grey first")
    if image.dtype not in GREY_DTYPES:
        raise ValueError(f"{label} must be uint8 or float32, got dtype {image.dtype}: "
                         "convert it with astype(np.float32)")


def check_shape(label: str, array: Any, reference_shape: tuple[int, ...],
                extra: tuple[int, ...] = ()) -> None:
    """Raise ``ValueError`` naming both shapes unless ``array`` has the shape
    ``reference_shape + extra`` (an array that goes with a reference image)."""
    expected = tuple(reference_shape) + tuple(extra)
    found = getattr(array, "shape", None)
    if found != expected:
        what = "pass frames of one size" if not extra else f"{label} must have shape {expected}"
        raise ValueError(f"{label} has shape {found} but the reference has shape "
                         f"{tuple(reference_shape)}: {what}")


def check_grey_pair(reference: Any, current: Any) -> None:
    """Raise ``ValueError`` unless both are 2-D uint8 or float32 images of one shape."""
    check_grey("reference", reference)
    check_grey("current", current)
    check_shape("current", current, reference.shape)
