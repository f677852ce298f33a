"""Sparse KLT baselines (paper section 2.2 and 4).

``klt`` is the paper's baseline: Harris (or Shi-Tomasi) corners detected in the
ROI of the reference frame, pyramidal Lucas-Kanade from frame to frame, the
displacement of a feature being the sum of its frame-to-frame motions (so errors
accumulate: drift). ``klt-ref`` tracks the same features against the fixed
reference frame instead.

References
----------
B. D. Lucas, T. Kanade, "An iterative image registration technique with an
application to stereo vision", IJCAI 1981.
J. Shi, C. Tomasi, "Good features to track", CVPR 1994.
J.-Y. Bouguet, "Pyramidal implementation of the Lucas Kanade feature tracker", 2000.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from flow.io.frames import as_uint8
from flow.methods.base import SparseMethod, register
from flow.methods.params import Param

_KLT_DEFAULTS = dict(detector="harris", max_corners=200, quality_level=0.01, min_distance=5,
                     block_size=5, window=21, levels=3, use_mask=False)


def _check_detector(detector: str) -> None:
    if detector not in ("harris", "shi-tomasi"):
        raise ValueError(f"KLT detector {detector!r} unknown; use 'harris' or 'shi-tomasi'")


class _KLTBase(SparseMethod):
    """What ``klt`` and ``klt-ref`` share: the parameters with their defaults, corner
    detection and pyramidal Lucas-Kanade (OpenCV's, on 8-bit images)."""

    full_depth = False
    # OpenCV asserts a window of 3 px or more, a quality in (0, 1), a block of 1 px or more.
    parameters = (
        Param("detector", "choice", _KLT_DEFAULTS["detector"], "corner detector", choices=("harris", "shi-tomasi")),
        Param("max_corners", "int", _KLT_DEFAULTS["max_corners"], "most corners kept", 1, 100000),
        Param("quality_level", "float", _KLT_DEFAULTS["quality_level"],
              "weakest corner kept, as a share of the strongest", 0, 1, low_open=True, high_open=True),
        Param("min_distance", "float", _KLT_DEFAULTS["min_distance"], "least distance between corners, px", 0, 1000),
        Param("block_size", "int", _KLT_DEFAULTS["block_size"], "corner detection block side, px", 1, 63),
        Param("window", "int", _KLT_DEFAULTS["window"], "Lucas-Kanade window side, px", 3, 101),
        Param("levels", "int", _KLT_DEFAULTS["levels"], "Lucas-Kanade pyramid levels", 0, 10),
        Param("use_mask", "bool", _KLT_DEFAULTS["use_mask"], "corners only on the POI mask (default: the whole ROI)"))

    def __init__(self, **params: Any) -> None:
        unknown = set(params) - set(_KLT_DEFAULTS)
        if unknown:
            raise ValueError(f"unknown parameter(s) {sorted(unknown)}; valid: {sorted(_KLT_DEFAULTS)}")
        merged = {**_KLT_DEFAULTS, **params}
        _check_detector(merged["detector"])
        super().__init__(**merged)

    def detect(self, reference: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Feature positions ``(N, 2)`` float32 in ``reference`` (Harris or Shi-Tomasi)."""
        p = self._params
        region = None
        if p["use_mask"] and mask is not None:
            region = mask.astype(np.uint8) * 255
        corners = cv2.goodFeaturesToTrack(
            as_uint8(reference), maxCorners=p["max_corners"], qualityLevel=p["quality_level"],
            minDistance=p["min_distance"], mask=region, blockSize=p["block_size"],
            useHarrisDetector=p["detector"] == "harris", k=0.04)
        if corners is None:
            return np.zeros((0, 2), np.float32)
        return corners.reshape(-1, 2).astype(np.float32)

    def start(self, reference: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        self.reference = reference
        self.points0 = self.detect(reference, mask)
        self.previous = reference
        self.points = self.points0.copy()
        self.alive = np.ones(len(self.points0), bool)
        return self.points0

    def _lk(self, image0: np.ndarray, image1: np.ndarray, points: np.ndarray,
            guess: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        p = self._params
        win = (p["window"], p["window"])
        criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
        image0, image1 = as_uint8(image0), as_uint8(image1)  # pyramidal LK takes 8-bit images
        if guess is None:
            new, status, _ = cv2.calcOpticalFlowPyrLK(image0, image1, points.reshape(-1, 1, 2), None,
                                                      winSize=win, maxLevel=p["levels"], criteria=criteria)
        else:
            new, status, _ = cv2.calcOpticalFlowPyrLK(
                image0, image1, points.reshape(-1, 1, 2), guess.reshape(-1, 1, 2).copy(),
                winSize=win, maxLevel=p["levels"], criteria=criteria,
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
        return new.reshape(-1, 2), status.ravel().astype(bool)


@register("klt")
class KLT(_KLTBase):
    """Paper baseline: corners in the ROI, pyramidal LK frame to frame, integrated motion.

    Parameters
    ----------
    detector : {"harris", "shi-tomasi"}
    max_corners, quality_level, min_distance, block_size : corner detection settings.
    window, levels : LK window side and pyramid levels.
    use_mask : bool
        Restrict corners to the POI mask (default False: the paper's KLT sees the whole ROI).
    """

    summary = "paper baseline: Harris corners in ROI, pyramidal LK frame to frame, summed motion, plain average"

    def step(self, current: np.ndarray) -> np.ndarray:
        if current is not self.previous and self.alive.any():
            idx = np.flatnonzero(self.alive)
            new, ok = self._lk(self.previous, current, self.points[idx])
            self.points[idx] = new
            # A lost feature stays lost: the baseline cannot re-find it without a reference.
            self.alive[idx[~ok]] = False
        self.previous = current
        displacement = self.points - self.points0
        displacement[~self.alive] = np.nan
        return displacement.astype(np.float32)


@register("klt-ref")
class KLTReference(_KLTBase):
    """KLT features tracked against the fixed reference frame (no integration)."""

    summary = "KLT features (Harris) tracked against the fixed reference frame with pyramidal LK; plain average"

    def step(self, current: np.ndarray) -> np.ndarray:
        if len(self.points0) == 0:
            return np.zeros((0, 2), np.float32)
        # Start from the last good estimate; where a feature was lost, from its reference spot,
        # so tracking resumes when the view comes back.
        guess = np.where(self.alive[:, None], self.points, self.points0)
        new, ok = self._lk(self.reference, current, self.points0, guess)
        self.alive = ok
        self.points = np.where(ok[:, None], new, self.points0)
        displacement = new - self.points0
        displacement[~ok] = np.nan
        return displacement.astype(np.float32)
