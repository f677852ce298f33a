"""An A4 sheet swept between the lens and the beam (paper Sec. 4.4).

The sheet (210 x 297 mm, parallel to the sensor) is carried at
``occlusion.distance_mm`` in front of the lens along one world axis (``±x``:
image left/right, ``±z``: image up/down). It always travels along its short
side: 210 mm along the path, 297 mm across it (portrait for ``±x``, landscape
for ``±z``); :class:`SheetPath` is both the model (which pixels it covers) and
the drawing (its quad and pose), so the two cannot disagree.

The path is built from the measurement region (the rays of the POI mask) and
the dead times between exposures just before the frames at ``start_s`` and
``start_s + duration_s`` (the renderer passes them): the leading edge sweeps in
from the border of the field of view within ``transit_s``, reaching the
region's near side a quarter into the first dead time, and crosses the region
(a quick flick of the hand) to cover it whole three quarters into it; the
sheet then creeps on, its trailing edge crosses the region within the second
dead time, and it leaves within ``transit_s``. With ``partial`` the leading
edge crosses only to where it covers ``partial_fraction`` of the mask's pixels
and is pulled back across within the second dead time. So the frames in
``[start_s, start_s + duration_s)`` are exactly the occluded ones, and no
exposure sees a sheet edge graze the region.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.config import section_dataclass

A4_MM = (210.0, 297.0)
_AXES = {"+x": (0, 1.0), "-x": (0, -1.0), "+z": (1, 1.0), "-z": (1, -1.0)}


@dataclass(frozen=True)
class OcclusionConfig:
    enabled: bool = False
    start_s: float = 4.0
    duration_s: float = 1.0
    transit_s: float = 0.15
    distance_mm: float = 150.0   # sheet plane in front of the lens
    direction: str = "+x"        # world axis the sheet travels along (+x: enters from image left)
    partial: bool = False
    partial_fraction: float = 0.5     # partial: fraction of the POI mask the sheet stops over
    motion_blur_subframes: int = 16   # sub-frames of a frame in which the sheet moves

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> OcclusionConfig:
        cfg = section_dataclass(cls, dict(config.get("occlusion") or {}), "occlusion")
        if cfg.direction not in _AXES:
            raise ValueError(f"occlusion.direction must be one of {', '.join(_AXES)}, "
                             f"got {cfg.direction!r}")
        for key in ("duration_s", "transit_s", "distance_mm", "motion_blur_subframes"):
            if getattr(cfg, key) <= 0:
                raise ValueError(f"occlusion.{key} must be > 0, got {getattr(cfg, key)!r}")
        if cfg.start_s < 0:
            raise ValueError(f"occlusion.start_s must be >= 0, got {cfg.start_s!r}")
        if not 0 < cfg.partial_fraction < 1:
            raise ValueError(f"occlusion.partial_fraction must be in (0, 1), got "
                             f"{cfg.partial_fraction!r}")
        return cfg


def exposure_gap_before(t: float, fps: float, exposure_s: float,
                        row_starts_s: tuple[float, float]) -> tuple[float, float]:
    """The dead time between two exposures of the rows starting ``row_starts_s``
    (first, last; relative to the frame start) just before the first frame at or
    after ``t``: from the end of the previous frame's last row to the start of
    this frame's first row. Empty (a 1 us sliver at the frame start) when the
    exposures overlap (a long rolling read-out)."""
    j = np.ceil(t * fps - 1e-9)
    previous_end = (j - 1) / fps + row_starts_s[1] + exposure_s
    start = j / fps + row_starts_s[0]
    return (float(previous_end), float(start)) if start > previous_end else (start - 1e-6, start)


class SheetPath:
    """Where the sheet is at time t (camera clock), in coordinates of its plane.

    ``s`` runs along the travel axis (world x for ±x, world z for ±z, in mm),
    ``q`` across it (world z, resp. x).
    """

    def __init__(self, cfg: OcclusionConfig, *, mask_s: np.ndarray, fov_s: tuple[float, float],
                 across_center: float, gaps_s: tuple[tuple[float, float], tuple[float, float]],
                 pixel_mm: float):
        self.cfg = cfg
        self.axis, self.sign = _AXES[cfg.direction]
        self.length, self.across = A4_MM          # along / across the path
        self.across_center = across_center
        # "travel" coordinates: positions times sign, so the sheet moves to larger values
        travel = np.sort(self.sign * np.asarray(mask_s, np.float64).ravel())
        lo, hi = float(travel[0]), float(travel[-1])
        f_lo, f_hi = sorted((self.sign * fov_s[0], self.sign * fov_s[1]))
        # the middle half of each dead time: edges cross the region only there
        (a0, b0), (a1, b1) = ((a + 0.25 * (b - a), b - 0.25 * (b - a)) for a, b in gaps_s)
        tr = cfg.transit_s
        if cfg.partial:
            stop = self._partial_stop(travel, cfg.partial_fraction, pixel_mm)
            lead = [(a0 - tr, f_lo), (a0, lo), (b0, stop), (a1, stop), (b1, lo), (b1 + tr, f_lo)]
        else:
            lead = [(a0 - tr, f_lo), (a0, lo), (b0, hi), (a1, lo + self.length),
                    (b1, hi + self.length), (b1 + tr, f_hi + self.length)]
        self.knots_t = np.array([k[0] for k in lead])
        self.knots_lead = np.array([k[1] for k in lead])

    @staticmethod
    def _partial_stop(travel: np.ndarray, fraction: float, pixel_mm: float) -> float:
        """Stop position covering the fraction of mask pixels nearest ``fraction``
        with the edge between two pixel rows/columns (``pixel_mm``: one pixel's
        size along the path on the sheet's plane), not through pixel centres."""
        gaps = np.diff(travel)
        split = np.flatnonzero(gaps >= 0.5 * pixel_mm) + 1   # m pixels before the gap
        if split.size == 0:
            split = np.arange(1, travel.size)
        m = split[np.argmin(np.abs(split / travel.size - fraction))]
        return float(0.5 * (travel[m - 1] + travel[m]))

    def leading_edge(self, t: float) -> float | None:
        """Leading edge in travel coordinates, or None when the sheet is away."""
        if not self.cfg.enabled or t <= self.knots_t[0] or t >= self.knots_t[-1]:
            return None
        return float(np.interp(t, self.knots_t, self.knots_lead))

    def extent(self, t: float) -> tuple[float, float] | None:
        """Sheet interval along the travel axis in *signed* plane coordinates."""
        lead = self.leading_edge(t)
        if lead is None:
            return None
        a, b = self.sign * (lead - self.length), self.sign * lead
        return (min(a, b), max(a, b))

    def present_during(self, t0: float, t1: float) -> bool:
        return bool(self.cfg.enabled and t1 > self.knots_t[0] and t0 < self.knots_t[-1])

    def moves_during(self, t0: float, t1: float) -> bool:
        """Whether the sheet is in view and moving at some time in ``[t0, t1]``."""
        if not self.present_during(t0, t1):
            return False
        inside = self.knots_t[(self.knots_t > t0) & (self.knots_t < t1)]
        leads = {self.leading_edge(t) for t in (t0, t1, *inside)}
        return len(leads) > 1

    def covers(self, t: float, s: np.ndarray, q: np.ndarray | None = None) -> np.ndarray:
        """Which plane positions (``s`` along the path, ``q`` across) are behind the sheet."""
        ext = self.extent(t)
        s = np.asarray(s, np.float64)
        if ext is None:
            return np.zeros(s.shape, bool)
        inside = (s >= ext[0]) & (s <= ext[1])
        if q is not None:
            inside &= np.abs(np.asarray(q, np.float64) - self.across_center) <= self.across / 2
        return inside

    # ------------------------------------------------------------ drawing
    def quad_corners(self) -> np.ndarray:
        """The sheet's corners (4, 3) about its centre in the x-z plane,
        counter-clockwise seen from the camera (-y), starting bottom-left."""
        half = np.array([self.length, self.across]) / 2
        hx, hz = (half[0], half[1]) if self.axis == 0 else (half[1], half[0])
        return np.array([[-hx, 0, -hz], [hx, 0, -hz], [hx, 0, hz], [-hx, 0, hz]])

    def pose(self, t: float, plane_y_mm: float) -> np.ndarray | None:
        """Pose (4 x 4, translation only) of the quad at time ``t``, or None when away."""
        ext = self.extent(t)
        if ext is None:
            return None
        along = 0.5 * (ext[0] + ext[1])
        pose = np.eye(4)
        x, z = (along, self.across_center) if self.axis == 0 else (self.across_center, along)
        pose[:3, 3] = (x, plane_y_mm, z)
        return pose
