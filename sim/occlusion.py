"""An A4 sheet swept between the lens and the beam (paper Sec. 4.4).

The sheet (210 x 297 mm, portrait, parallel to the sensor) is carried at
``occlusion.distance_mm`` in front of the lens along one image axis. Its path
is built from the measurement region (the mask's rays): during
``[start_s - transit_s, start_s]`` the leading edge sweeps from the sensor
border to the far side of the region, so the region is fully covered exactly
from ``start_s``; the sheet then creeps on so that its trailing edge reaches the
near side of the region exactly at ``start_s + duration_s``, and it leaves
within ``transit_s``. With ``partial`` the sheet stops with its leading edge
across the middle of the region (half of it covered) and is pulled back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from sim.scene import _build

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

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> OcclusionConfig:
        cfg = _build(cls, dict(config.get("occlusion") or {}), "occlusion")
        if cfg.direction not in _AXES:
            raise ValueError(f"occlusion.direction must be one of {', '.join(_AXES)}, "
                             f"got {cfg.direction!r}")
        for key in ("duration_s", "transit_s", "distance_mm"):
            if getattr(cfg, key) <= 0:
                raise ValueError(f"occlusion.{key} must be > 0, got {getattr(cfg, key)!r}")
        if cfg.start_s < 0:
            raise ValueError(f"occlusion.start_s must be >= 0, got {cfg.start_s!r}")
        return cfg


class SheetPath:
    """Where the sheet is at time t (camera clock), in camera-aligned plane coords.

    Coordinates on the sheet plane: ``s`` along the travel axis (mm, image x
    for ±x, image *up* for ±z, i.e. world axis) and ``q`` across it.
    """

    def __init__(self, cfg: OcclusionConfig, *, region_s: tuple[float, float], point_s: float,
                 fov_s: tuple[float, float], across_center: float):
        self.cfg = cfg
        self.axis, self.sign = _AXES[cfg.direction]
        self.length = A4_MM[self.axis]          # extent along travel: 210 (x) or 297 (z)
        self.across = A4_MM[1 - self.axis]
        self.across_center = across_center
        # work in "travel" coordinates: positions multiplied by sign, so travel is increasing
        lo, hi = sorted((self.sign * region_s[0], self.sign * region_s[1]))
        f_lo, f_hi = sorted((self.sign * fov_s[0], self.sign * fov_s[1]))
        p = 0.5 * (lo + hi)  # partial: the edge stops across the middle of the region
        t0, t1 = cfg.start_s, cfg.start_s + cfg.duration_s
        tr = cfg.transit_s
        if cfg.partial:
            lead = [(t0 - tr, f_lo), (t0, p), (t1, p), (t1 + tr, f_lo)]
        else:
            lead = [(t0 - tr, f_lo), (t0, hi), (t1, lo + self.length),
                    (t1 + tr, f_hi + self.length)]
        self.knots_t = np.array([k[0] for k in lead])
        self.knots_lead = np.array([k[1] for k in lead])
        self.region = (lo, hi)

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

    def covers(self, t: float, s: np.ndarray) -> np.ndarray:
        """Which plane positions ``s`` (signed, along the travel axis) are behind the sheet."""
        ext = self.extent(t)
        s = np.asarray(s, np.float64)
        if ext is None:
            return np.zeros(s.shape, bool)
        return (s >= ext[0]) & (s <= ext[1])
