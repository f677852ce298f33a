"""Camera-motion compensation from a static background (tripod shake, mount drift).

A camera that shakes or creeps moves the whole image, and a reference-frame
method reads that as motion of the structure. Points the user marks on
something that does not move (a wall, the ground, the clamp) see only the
camera's motion: the flow measured there, fitted by an affine image motion,
is evaluated at the POIs and subtracted.

An affine model covers pan and tilt (a uniform shift), roll (a rotation about
the optical axis) and the slight zoom of a camera creeping along its axis. A
translation of the camera sideways moves near and far objects by different
amounts (parallax): for that part the compensation is exact only when the
background lies at the structure's depth.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from flow.measure.robust import MAD_TO_SIGMA

MODELS = ("affine", "translation")
# An affine fit extrapolates a tilt of the background plane: below this spread (px)
# along its narrow direction the points cannot pin a tilt down, and the shift alone is used.
MIN_AFFINE_SPREAD_PX = 10.0
MAX_POINTS = 4000  # flow samples used per frame; more add time, not accuracy


@dataclass(frozen=True)
class Background:
    """Background points (``(B, 2)`` ROI pixels) and the motion model fitted to them."""

    xy: np.ndarray
    model: str

    @classmethod
    def from_mask(cls, mask: np.ndarray, *, model: str = "affine") -> Background:
        """Points of a background mask, thinned to at most :data:`MAX_POINTS`.

        ``model`` ``"affine"`` falls back to ``"translation"`` when the points
        are too narrow a strip to fix a tilt (see :data:`MIN_AFFINE_SPREAD_PX`).
        """
        if model not in MODELS:
            raise ValueError(f"background model must be one of {MODELS}, got {model!r}")
        ys, xs = np.nonzero(mask)
        if xs.size < 3:
            raise ValueError(f"the background mask has {xs.size} pixels: mark a static region of "
                             "at least a few pixels")
        # A regular stride keeps the spatial layout (and is deterministic).
        stride = int(np.ceil(xs.size / MAX_POINTS))
        xy = np.stack([xs[::stride], ys[::stride]], axis=1).astype(np.float64)
        if model == "affine":
            spread = np.sqrt(np.linalg.eigvalsh(np.cov(xy.T))[0])
            if not spread >= MIN_AFFINE_SPREAD_PX:
                model = "translation"
        return cls(xy, model)

    @property
    def columns(self) -> np.ndarray:
        return self.xy[:, 0].astype(np.intp)

    @property
    def rows(self) -> np.ndarray:
        return self.xy[:, 1].astype(np.intp)

    def motion_at(self, flow_dx: np.ndarray, flow_dy: np.ndarray, at_xy: np.ndarray,
                  *, iterations: int = 2) -> tuple[np.ndarray, np.ndarray]:
        """The camera's image motion at ``at_xy`` (``(P, 2)``) from the flow at the background points.

        The fit is robust: points whose residual exceeds ``max(3 x 1.4826 MAD, 0.05 px)``
        are dropped and the model refitted (``iterations`` times). Returns NaN where
        no finite background flow exists.
        """
        ok = np.isfinite(flow_dx) & np.isfinite(flow_dy)
        if ok.sum() < 3:
            nan = np.full(len(at_xy), np.nan)
            return nan, nan.copy()
        design = (np.column_stack([self.xy, np.ones(len(self.xy))]) if self.model == "affine"
                  else np.ones((len(self.xy), 1)))
        target = np.column_stack([flow_dx, flow_dy]).astype(np.float64)
        keep = ok.copy()
        for step in range(iterations + 1):
            coef, *_ = np.linalg.lstsq(design[keep], target[keep], rcond=None)
            if step == iterations:
                break
            resid = np.hypot(*(design @ coef - target).T)
            scale = MAD_TO_SIGMA * np.median(np.abs(resid[keep] - np.median(resid[keep])))
            trimmed = ok & (resid <= max(3.0 * scale + np.median(resid[keep]), 0.05))
            if trimmed.sum() < design.shape[1] + 1 or np.array_equal(trimmed, keep):
                break
            keep = trimmed
        at = (np.column_stack([at_xy, np.ones(len(at_xy))]) if self.model == "affine"
              else np.ones((len(at_xy), 1)))
        motion = at @ coef
        return motion[:, 0], motion[:, 1]
