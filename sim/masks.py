"""What a user would paint on the video: the POI mask, the background mask and the labelled
regions mask, all on a :class:`sim.view.View`'s window; and the POIs of the POI mask (their
pixels, lines of sight and material points on the beam), which the ground truth follows.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.view import View

POI_EDGE_PX = 3  # POIs stay this far in from the face's side edges (1.07 mm at 4K)
POI_CROP_MARGIN_PX = 20  # ... and this far inside the crop's top and bottom rows


def face_inset_mm(view: View) -> float:
    """How far the POIs stay in from the beam's edges: ``POI_EDGE_PX``, at most a quarter
    of the thickness."""
    return min(POI_EDGE_PX * view.mm_per_px, 0.25 * view.scene_cfg.beam_thickness_mm)


def face_rows(view: View) -> tuple[np.ndarray, np.ndarray]:
    """Window-sized ``(inside, z_mm)``: the pixels of the beam's edge face 3 px in from its
    side edges, within the crop's rows minus 20 px, and the rest height each pixel sees."""
    w = view.window
    crop = view.crop_window
    # only the crop's rows can hold POIs: back-project just those pixels
    y0 = max(w.y, crop.y + POI_CROP_MARGIN_PX)
    y1 = min(w.y + w.height, crop.y + crop.height - POI_CROP_MARGIN_PX)
    x0, x1 = max(w.x, crop.x), min(w.x + w.width, crop.x + crop.width)
    inside = np.zeros((w.height, w.width), bool)
    z_mm = np.full((w.height, w.width), np.nan)
    if y1 > y0 and x1 > x0:
        vv, uu = np.mgrid[y0:y1, x0:x1].astype(np.float64)
        pts = view.camera.backproject_to_plane_y(uu, vv, view.face_y_mm)
        inside[y0 - w.y:y1 - w.y, x0 - w.x:x1 - w.x] = (
            np.abs(pts[..., 0]) <= view.scene_cfg.beam_thickness_mm / 2 - face_inset_mm(view))
        z_mm[y0 - w.y:y1 - w.y, x0 - w.x:x1 - w.x] = pts[..., 2]
    return inside, z_mm


def poi_mask(view: View) -> np.ndarray:
    """POIs a user would paint: the beam's edge face, 3 px in from its
    edges, over the crop height around the measurement point minus 20 px."""
    inside, _ = face_rows(view)
    if not inside.any():
        raise ValueError(f"the beam face is too narrow for a POI mask at {view.mm_per_px:.3f} "
                         f"mm/px: raise camera.fx_px or lower camera.distance_mm")
    return inside.astype(np.uint8) * 255


def background_mask(view: View, margin_px: float = 12.0) -> np.ndarray:
    """Static scene a user would mark for camera-motion compensation: every
    pixel of the window whose line of sight stays ``margin_px`` clear of the
    band the beam and its logo sweep during the clip (the wall and its fixtures)."""
    w = view.window
    vv, uu = np.mgrid[w.y:w.y + w.height, w.x:w.x + w.width].astype(np.float64)
    x_ray, _ = view.camera.pixel_rays(uu, vv)
    clear = np.abs(x_ray) > view.beam_reach() + margin_px / view.camera.fx
    return clear.astype(np.uint8) * 255


def regions_mask(view: View, heights_mm, half_height_mm: float) -> np.ndarray:
    """Labelled mask of several measurement points, as a user paints them for
    ``refflow track --mask``: region ``k`` (1-based, heights sorted) is the POI mask's face
    within ``half_height_mm`` of the ``k``-th height, moved down to stay on the beam (the
    tip's region is the top ``2 * half_height_mm`` below a 3 px inset from the free end)."""
    heights = np.sort(np.asarray(heights_mm, float))
    if heights.size == 0 or not half_height_mm > 0:
        raise ValueError(f"regions need heights and half_height_mm > 0, got {heights.tolist()} "
                         f"and {half_height_mm!r}")
    if heights.size > 255:
        raise ValueError(f"{heights.size} regions do not fit an 8-bit labelled PNG (at most 255)")
    inside, z_mm = face_rows(view)
    top = view.scene_cfg.beam_length_mm - face_inset_mm(view)
    labels = np.zeros(inside.shape, np.uint8)
    for k, height in enumerate(heights, start=1):
        z1 = min(height + half_height_mm, top)
        z0 = z1 - 2 * half_height_mm
        if z0 <= 0:
            raise ValueError(f"region {k} at {height:g} mm reaches below the clamp: lower "
                             f"regions.half_height_mm ({half_height_mm:g})")
        rows = np.flatnonzero(np.any(inside & (z_mm >= z0) & (z_mm <= z1), axis=1))
        expected = (z1 - z0) / view.mm_per_px
        if rows.size < 0.9 * expected:
            raise ValueError(f"region {k} ({z0:g}-{z1:g} mm) shows on {rows.size} of its ~{expected:.0f} "
                             f"rows in the {view.window.width}x{view.window.height} window: raise "
                             "camera.crop_height_px or set camera.crop_center_z_mm between the heights")
        if (labels[inside & (z_mm >= z0) & (z_mm <= z1)] != 0).any():
            raise ValueError(f"region {k} at {height:g} mm overlaps region {k - 1}: lower "
                             f"regions.half_height_mm ({half_height_mm:g})")
        labels[inside & (z_mm >= z0) & (z_mm <= z1)] = k
    return labels


class Pois:
    """The POIs of a mask on ``view``'s window: their window pixels (``window_px``, P x 2
    float32), sensor rows, normalised rays, material points (across the face ``a``, rest
    height ``z0``) and rest projections (``rest_px``, global pixels)."""

    def __init__(self, view: View, mask: np.ndarray):
        vv, uu = np.nonzero(mask)
        self.window_px = np.stack([uu, vv], -1).astype(np.float32)
        u, v = uu + float(view.window.x), vv + float(view.window.y)
        self.rows = vv + view.window.y
        self.rays = view.camera.pixel_rays(u, v)
        rest = view.camera.rays_to_plane_y(*self.rays, view.face_y_mm)
        self.a, self.z0 = rest[:, 0], rest[:, 2]
        self.rest_px = view.camera.project(rest)

    @property
    def count(self) -> int:
        return int(self.a.size)


def region_heights(config: dict[str, Any]) -> tuple[np.ndarray, float]:
    """The sensor's heights (``sensor.height_mm`` and ``extra_heights_mm``, sorted: region
    ``k`` is the ``k``-th) and ``regions.half_height_mm`` of a config with a ``regions`` section."""
    from sim.beam import SensorParams

    sensor = SensorParams.from_dict(config.get("sensor"))
    section = config.get("regions")
    if not isinstance(section, dict):
        raise ValueError("the config has no `regions` section: add regions: {half_height_mm: 25}")
    # the other keys say how the tool measures and identifies the regions (the workflow's)
    unknown = sorted(set(section) - {"half_height_mm", "method", "modes", "band_hz"})
    if unknown:
        raise ValueError(f"regions: unknown key(s) {', '.join(unknown)}; known: half_height_mm, "
                         "method, modes, band_hz")
    heights = np.unique([sensor.height_mm, *sensor.extra_heights_mm])
    return heights, float(section.get("half_height_mm", 25.0))


def write_regions(config: dict[str, Any], out: str | Path) -> dict[str, Any]:
    """The labelled mask of the sensor's heights (grey value k = region k, 0 elsewhere) on the
    video's window, a PNG for ``refflow track --mask``; returns the heights and row spans."""
    from refflow.io import atomic_path
    heights, half = region_heights(config)
    view = View(config, None)
    labels = regions_mask(view, heights, half)
    with atomic_path(out) as tmp:
        if not cv2.imwrite(str(tmp), labels):
            raise ValueError(f"could not write {out}: give it a .png name in a writable folder")
    rows = [np.flatnonzero((labels == k).any(axis=1)) for k in range(1, heights.size + 1)]
    return {"heights_mm": heights.tolist(), "half_height_mm": half,
            "rows": [[int(r_[0]), int(r_[-1])] for r_ in rows], "window": view.window.as_dict()}
