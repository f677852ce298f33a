"""What one sensor window of the synthetic phone sees, before anything is rendered.

A :class:`View` holds the configs, the camera in its nominal pose, its motion and the
light, the measurement point, the measurement crop and the window being rendered (the crop
or the full sensor), and what follows from them alone: how far the beam reaches across the
view during the clip, how many frames the clip holds, and where the occluding sheet's plane
meets a line of sight. The masks (``sim.masks``), the ground truth (``sim.truth``) and the
frames (``sim.render``) are all computed from one view.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.camera import CameraConfig, CameraModel, Window
from sim.disturbance import CameraMotion, Illumination
from sim.occlusion import OcclusionConfig, SheetPath, exposure_gap_before
from sim.scene import BeamShapes, SceneConfig


def config_seed(config: dict[str, Any]) -> int:
    """The config's ``seed``, every random stream's root; a ``ValueError`` unless it is a
    non-negative integer."""
    seed = config.get("seed", 0)
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


class View:
    """One sensor window of the camera on the beam; see the module docstring."""

    def __init__(self, config: dict[str, Any], shapes: BeamShapes | None, *,
                 full_frame: bool = False, window: Window | None = None,
                 occlusion: OcclusionConfig | None = None):
        self.config = config
        self.seed = config_seed(config)
        self.scene_cfg = SceneConfig.from_config(config)
        self.cam_cfg = CameraConfig.from_config(config)
        self.occ_cfg = occlusion or OcclusionConfig.from_config(config)
        self.shapes = shapes
        sc, cc = self.scene_cfg, self.cam_cfg
        self.face_y_mm = -sc.beam_width_mm / 2
        self.camera = CameraModel(cc, camera_y_mm=self.face_y_mm - cc.distance_mm)
        self.motion = CameraMotion(cc, self.seed)
        self.light = Illumination(sc, self.seed)
        self.mm_per_px = self.camera.mm_per_px_at(self.face_y_mm)
        self.measure_point = np.array([0.0, self.face_y_mm, sc.measure_height_mm])
        self.measure_px = self.camera.project(self.measure_point)
        # a crop holding several heights (camera.crop_center_z_mm) centres between them
        crop_z = sc.measure_height_mm if cc.crop_center_z_mm is None else cc.crop_center_z_mm
        self.crop_window = self.camera.crop_around(*self.camera.project(
            np.array([0.0, self.face_y_mm, crop_z])))
        if window is None:
            window = self.camera.full_window() if full_frame else self.crop_window
        self.window = window
        self.sheet_plane_y = self.camera.camera_y_mm + self.occ_cfg.distance_mm

    def beam_reach(self) -> float:
        """Largest |x| / depth (the tangent of the angle off the optical axis)
        the beam's front face or its logo reach during the clip."""
        sc, cam = self.scene_cfg, self.camera
        swing, tilt = 0.0, 0.0
        if self.shapes is not None:
            swing = float(np.abs(self.shapes.x_mm).max())
            tilt = float(np.abs(self.shapes.theta_rad).max())
        spread = np.cos(tilt) + np.sin(tilt)  # a rotated half-width reaches this much further
        reach = (swing + spread * sc.beam_thickness_mm / 2) / (self.face_y_mm - cam.camera_y_mm)
        if sc.logo:
            logo_depth = sc.beam_width_mm / 2 + 0.5 - cam.camera_y_mm
            reach = max(reach, (swing + spread * sc.logo_size_mm / 2) / logo_depth)
        return reach

    def n_frames(self, duration_s: float | None = None) -> int:
        """Frames of the clip: ``duration_s`` (the config's by default) at the camera's rate,
        as many as the shapes cover with every row's exposure."""
        cc = self.cam_cfg
        duration = float(self.config.get("duration_s", 10.0) if duration_s is None else duration_s)
        n = int(np.floor(duration * cc.fps + 1e-9))
        if self.shapes is not None:
            span = float(self.camera.row_times(self.camera.height - 1)) + cc.exposure_s
            last = self.shapes.time_s[-1] - cc.start_offset_s - span
            n = min(n, int(np.floor(last * cc.fps + 1e-9)) + 1)
        if n < 1:
            raise ValueError(f"no frame fits: duration_s={duration} and shapes up to "
                             f"{self.shapes.time_s[-1] if self.shapes else 0} s")
        return n

    def sheet_coords(self, rays: tuple[np.ndarray, np.ndarray], t_cam: float | None = None):
        """Coordinates (along, across the sheet's path) on the sheet's plane of
        normalised rays ``(x, y)`` of the camera as it stands at ``t_cam``."""
        motion = None if t_cam is None else self.motion.at(t_cam)
        pts = self.camera.rays_to_plane_y(*rays, self.sheet_plane_y, motion)
        along = 0 if self.occ_cfg.direction in ("+x", "-x") else 2
        return pts[..., along], pts[..., 2 - along]

    def sheet_path(self, poi_rays: tuple[np.ndarray, np.ndarray], poi_rows: np.ndarray) -> SheetPath:
        """The sheet's path across this view, placed so that it meets the POIs (their
        rays and sensor rows) at the configured times."""
        cam, occ, cc = self.camera, self.occ_cfg, self.cam_cfg
        s_mask, _ = self.sheet_coords(poi_rays)
        corners = cam.pixel_rays(np.array([0, cam.width - 1, 0, cam.width - 1], float),
                                 np.array([0, 0, cam.height - 1, cam.height - 1], float))
        s_fov, _ = self.sheet_coords(corners)
        measure_ray = cam.pixel_rays(*self.measure_px)
        _, across = self.sheet_coords(measure_ray)
        rows = (float(cam.row_times(poi_rows.min())), float(cam.row_times(poi_rows.max())))
        gaps = tuple(exposure_gap_before(t, cc.fps, cc.exposure_s, rows)
                     for t in (occ.start_s, occ.start_s + occ.duration_s))
        focal = cam.fx if occ.direction in ("+x", "-x") else cam.fy
        return SheetPath(occ, mask_s=s_mask, fov_s=(float(s_fov.min()), float(s_fov.max())),
                         across_center=float(across), gaps_s=gaps,
                         pixel_mm=occ.distance_mm / focal)
