"""The ground truth of the synthetic video: where the measurement point and the POIs are on
each frame, and the scale reference a user would click.

Ground truth (:meth:`GroundTruth.frame`) is averaged over the same sub-frames and row
weights as the image (``sim.subframes``), and a POI is occluded when the sheet covers it at
one of the sub-frames its row exposes. It is the beam's motion relative to the ground, seen
by the camera in its nominal pose; camera motion is reported separately (``cam_dx_px``,
``cam_dy_px``). The files it goes to are ``sim.truth_io``'s.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from sim.masks import Pois
from sim.occlusion import SheetPath
from sim.subframes import SubframeTable
from sim.view import View

TRUTH_CONVENTION = (
    "truth.csv: displacement of the measurement point on the beam's front face from "
    "its rest (undeformed) position, relative to the ground and seen by the camera in "
    "its nominal pose, averaged over the image's sub-frames with its sensor row's "
    "weights; dx_mm/dy_mm are world displacements (dx_mm along world x, dy_mm along "
    "-z, i.e. image-down sign); time_s = frame/fps on the camera clock (sim time = "
    "time_s + camera_start_offset_s); occluded = 1 when the sheet covers any mask "
    "pixel at a sub-frame its row exposes, occluded_frac = fraction of mask pixels "
    "covered so; cam_dx_px/cam_dy_px = apparent image shift of a static point at the "
    "measurement point's rest position caused by camera shake and drift (what the "
    "image shows is about dx_px + cam_dx_px); light_rel = relative light over the "
    "measurement row's exposure; gain = auto-exposure analog gain")


class GroundTruth:
    """The truth of the frames of ``view`` at the POIs ``pois``; see the module docstring."""

    def __init__(self, view: View, pois: Pois, sheet: SheetPath, subframes: SubframeTable):
        self.view, self.pois, self.sheet, self.subframes = view, pois, sheet, subframes

    def beam_points(self, t_cam: float) -> tuple[np.ndarray, np.ndarray]:
        """World positions of the measurement point (3,) and the POIs' material points (P, 3)."""
        view = self.view
        t_sim = t_cam + view.cam_cfg.start_offset_s
        a = np.concatenate([[0.0], self.pois.a])
        z0 = np.concatenate([[view.measure_point[2]], self.pois.z0])
        if view.shapes is None:
            pts = np.stack([a, np.full_like(a, view.face_y_mm), z0], -1)
        else:
            pts = view.shapes.material_to_world(t_sim, a, view.face_y_mm, z0)
        return pts[0], pts[1:]

    def scale_points(self) -> np.ndarray:
        """Where a user clicks the beam's two edges (its thickness, the paper's scale
        reference) on frame 0 at the measurement height: ``[x1, y1, x2, y2]`` raw
        window pixels, exact (a perfect click)."""
        view = self.view
        half = view.scene_cfg.beam_thickness_mm / 2
        t_sim = 0.5 * view.cam_cfg.exposure_s + view.cam_cfg.start_offset_s
        a, z0 = np.array([-half, half]), np.full(2, view.measure_point[2])
        if view.shapes is None:
            edges = np.stack([a, np.full(2, view.face_y_mm), z0], -1)
        else:
            edges = view.shapes.material_to_world(t_sim, a, view.face_y_mm, z0)
        pixels = view.camera.project(edges) - [view.window.x, view.window.y]
        return pixels.ravel()

    def frame(self, index: int) -> dict[str, Any]:
        """Ground truth of frame ``index`` (see ``sim.truth_io`` for the columns),
        averaged over the image's own sub-frames and row weights."""
        view, pois = self.view, self.pois
        cc, cam = view.cam_cfg, view.camera
        t_frame = index / cc.fps
        smp, _, w_poi, w_measure = self.subframes.at(index)
        n_poi = pois.count
        world, pix, cam_shift = np.zeros(3), np.zeros(2), np.zeros(2)
        poi_pix, covered = np.zeros((n_poi, 2)), np.zeros(n_poi, bool)
        for k in np.flatnonzero((w_measure > 0) | (w_poi > 0).any(0)):
            t = t_frame + smp.times[k]
            m_world, p_world = self.beam_points(t)
            world += w_measure[k] * m_world
            pix += w_measure[k] * cam.project(m_world)
            poi_pix += w_poi[:, k, None] * cam.project(p_world)
            motion = view.motion.at(t)
            if motion is not None:
                cam_shift += w_measure[k] * (cam.project(view.measure_point, motion)
                                             - view.measure_px)
            if self.sheet.extent(t) is not None:
                on_sheet = self.sheet.covers(t, *view.sheet_coords(pois.rays, t))
                covered |= (w_poi[:, k] > 0) & on_sheet
        start = t_frame + float(cam.row_times(np.rint(view.measure_px[1])))
        poi_shift = poi_pix - pois.rest_px
        return {
            "frame": index, "time_s": t_frame,
            "dx_px": pix[0] - view.measure_px[0], "dy_px": pix[1] - view.measure_px[1],
            "dx_mm": world[0] - view.measure_point[0], "dy_mm": -(world[2] - view.measure_point[2]),
            "occluded": int(covered.any()), "occluded_frac": float(covered.mean()) if n_poi else 0.0,
            "cam_dx_px": cam_shift[0], "cam_dy_px": cam_shift[1],
            "light_rel": float(view.light.mean(start, start + cc.exposure_s)),
            "poi_dx_px": poi_shift[:, 0].astype(np.float32),
            "poi_dy_px": poi_shift[:, 1].astype(np.float32),
            "poi_covered": covered,
        }

    def stack(self, n_frames: int) -> dict[str, np.ndarray]:
        """Truth of frames 0..n_frames-1 stacked in memory (short clips and tests;
        :func:`sim.clip.render_clip` streams it frame by frame instead)."""
        rows = [self.frame(i) for i in range(n_frames)]
        out = {key: np.array([row[key] for row in rows]) for key in rows[0]}
        out["poi_x_px"], out["poi_y_px"] = self.pois.window_px[:, 0], self.pois.window_px[:, 1]
        return out
