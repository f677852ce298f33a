"""Whether a frame shows the scene at all.

Something in front of the whole view (the paper's sheet of paper, a hand, a lens cap) or the
light gone leaves a frame that holds nothing of the reference's structure: no method can read
a displacement from it, and a dense flow solved on it is the occluder's noise (on the bench's
`occlusion` clip, a white sheet over the view for 0.8 s, the dense readings there were up to
9 px off, every one flagged invalid, and their solves half the clip's time). The default
(:class:`flow.methods.deepflow.method.DeepFlow`) only glimpses such a frame instead (a coarse
dense flow, kept) and tells the driver, which flags it (``Tracks.hidden``).

A frame is hidden only where both hold, each of which a visible frame can fail alone:

* its texture is gone: the mean squared grey-level gradient over the window (a Gaussian of
  :data:`BLUR_PX` first, so single-pixel noise counts little) is below :data:`ENERGY_RATIO` of the
  reference's (a frame whose light dropped to a fifth fails this alone; the bench's visible
  frames hold 0.81-1.07 of it, the sheet 0.006);
* the reference's structure is not found in it: the best zero-normalised correlation of the
  reference's window (smoothed by :data:`MATCH_BLUR_PX`, at half resolution, less a border of
  :data:`SEARCH_PX` full-resolution pixels, or a quarter of a narrower window's side) over the
  shifts that border allows is below :data:`MATCH_FLOOR` (a
  darkened or defocused view still correlates; the bench's visible frames 0.61-1.00 where the
  motion stays within the search, the sheet at most 0.22).

What it cannot tell: a reference that itself holds something passing (a hand, a cable swinging
through) in an otherwise plain view makes the frames without it look hidden (flagged, read
coarsely); a frame that shows the scene's texture but not the reference's structure (a
textured occluder) is measured in full and flagged, if at all, by its mismatch.
"""

from __future__ import annotations

import cv2
import numpy as np

BLUR_PX = 1.0
ENERGY_RATIO = 0.05
MATCH_BLUR_PX = 2.0
MATCH_FLOOR = 0.5
SEARCH_PX = 64


def _energy(image: np.ndarray) -> float:
    smooth = cv2.GaussianBlur(image, (0, 0), BLUR_PX)
    gx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0)
    gy = cv2.Sobel(smooth, cv2.CV_32F, 0, 1)
    return float(np.mean(gx * gx + gy * gy))


def _coarse(image: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(cv2.GaussianBlur(image, (0, 0), MATCH_BLUR_PX)[::2, ::2])


class SceneCheck:
    """Tells the frames that show nothing of ``reference`` (see the module's notes), over
    ``window`` (rows, columns slices; None: the whole frame) of frames of the reference's shape."""

    def __init__(self, reference: np.ndarray, window: tuple[slice, slice] | None = None) -> None:
        self._window = window if window is not None else (slice(None), slice(None))
        ref = np.asarray(reference[self._window], np.float32)
        self._energy = _energy(ref)
        coarse = _coarse(ref)
        h, w = coarse.shape
        r = min(SEARCH_PX // 2, h // 4, w // 4)
        self._template = np.ascontiguousarray(coarse[r:h - r, r:w - r]) if r > 0 else None

    def hidden(self, current: np.ndarray) -> bool:
        """Whether ``current`` shows neither the reference's texture nor its structure."""
        if self._template is None or not self._energy > 0:
            return False
        cur = np.asarray(current[self._window], np.float32)
        energy = _energy(cur)
        if not energy < ENERGY_RATIO * self._energy:
            return False
        if energy == 0.0:
            return True  # one grey level throughout (a lens cap, a saturated frame)
        # (OpenCV's normalised correlation is finite: 0 where the frame's patch is flat.)
        found = cv2.matchTemplate(_coarse(cur), self._template, cv2.TM_CCOEFF_NORMED)
        return float(found.max()) < MATCH_FLOOR
