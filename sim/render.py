"""Render the frames of the synthetic phone video.

One :class:`BeamRenderer` per output window (the default crop around the measurement
point, or the full sensor; a :class:`sim.view.View`). It composes the POI mask and its
POIs (``sim.masks``), the sheet's path, the sub-frames (``sim.subframes``) and the ground
truth (``sim.truth``), and owns the pyrender scene. A frame (:meth:`BeamRenderer.frame_linear`)
averages undistorted pyrender renders at the sub-frames of its exposure with each sensor
row's weights (:class:`sim.camera.SubframeSampling`), remaps them through the exact lens
model and scales each row by the light's relative intensity over its exposure;
:meth:`BeamRenderer.frame` adds the sensor (noise, the auto-exposure's analog gain, gamma,
8 bits; ``sim.camera``). The clip and its files are ``sim.clip``'s.

Speed: while the camera stands still and the sheet is away only the beam and
its logo move, so the window's background is rendered once and a sub-frame
renders just the strip of columns the beam can reach during the clip, pasted
over the background. Shake, drift and the sheet's frames render the whole
window per sub-frame.

Auto-exposure (:meth:`BeamRenderer.meter`): every frame is metered on a
low-resolution pinhole render of the whole field of view at mid-exposure (the
sheet, the beam, the camera's motion and the light included), so a crop and
the full frame get the same gains; :class:`sim.camera.AutoExposure` turns the
meters into gains with a phone-like lag.
"""

from __future__ import annotations

import time
from typing import Any

import cv2
import numpy as np

from sim.camera import AutoExposure, SubframeSampling, Window, sensor_readout, srgb8_to_linear16
from sim.masks import Pois, poi_mask
from sim.occlusion import OcclusionConfig
from sim.scene import (
    BeamMesh,
    BeamShapes,
    build_static_scene,
    offscreen_renderer,
    pyrender,
    quad_primitive,
    release_renderer,
)
from sim.subframes import SubframeTable
from sim.truth import GroundTruth
from sim.view import View

RENDER_FLAGS = pyrender.RenderFlags.FLAT  # baked lighting, see sim.scene.shading
_AWAY = np.eye(4)
_AWAY[:3, 3] = (0.0, -1e5, 0.0)  # behind the camera: culled
_EDGE_MARGIN_PX = 4  # MSAA and texture filtering reach beyond an object's edge


def distractor_layout(view: View) -> tuple[np.ndarray, np.ndarray]:
    """Centres (world x, z) and kinds of the wall fixtures: inside the
    measurement crop, clear of the beam and logo as the camera sees them."""
    sc, cam, crop = view.scene_cfg, view.camera, view.crop_window
    plane_y = sc.background_distance_mm - 1.0
    u = np.array([crop.x, crop.x + crop.width - 1] * 2, np.float64)
    v = np.array([crop.y] * 2 + [crop.y + crop.height - 1] * 2, np.float64)
    corners = cam.backproject_to_plane_y(u, v, plane_y)
    half = sc.distractor_size_mm / 2
    x_lo, x_hi = max(corners[[0, 2], 0]) + half, min(corners[[1, 3], 0]) - half
    z_lo, z_hi = max(corners[[2, 3], 2]) + half, min(corners[[0, 1], 2]) - half
    keep_out = view.beam_reach() * (plane_y - cam.camera_y_mm) + half + 3.0
    rng = np.random.default_rng([view.seed, 5])
    centres: list[tuple[float, float]] = []
    for _ in range(2000):  # rejection sampling; a crop too small simply holds fewer
        if len(centres) == sc.distractor_count or x_hi <= x_lo or z_hi <= z_lo:
            break
        x, z = rng.uniform(x_lo, x_hi), rng.uniform(z_lo, z_hi)
        if abs(x) >= keep_out and all(np.hypot(x - a, z - b) >= 1.6 * sc.distractor_size_mm
                                      for a, b in centres):
            centres.append((x, z))
    return np.array(centres, np.float64).reshape(-1, 2), np.arange(len(centres)) % 4


class BeamRenderer:
    """Renders the frames of one sensor window; see the module docstring. ``view``, ``mask``,
    ``pois``, ``sheet``, ``subframes`` and ``truth`` are its parts, public for callers."""

    def __init__(self, config: dict[str, Any], shapes: BeamShapes | None, *,
                 full_frame: bool = False, window: Window | None = None,
                 occlusion: OcclusionConfig | None = None):
        self.view = view = View(config, shapes, full_frame=full_frame, window=window,
                                occlusion=occlusion)
        t0 = time.perf_counter()
        self.plan = view.camera.remap_plan(view.window)
        self.timings = {"remap_plan_s": time.perf_counter() - t0}
        self.mask = poi_mask(view)
        self.pois = Pois(view, self.mask)
        self.sheet = view.sheet_path(self.pois.rays, self.pois.rows)
        self.subframes = SubframeTable(view, self.pois, self.sheet)
        self.truth = GroundTruth(view, self.pois, self.sheet, self.subframes)
        self._background: np.ndarray | None = None
        self._setup_scene()

    def _setup_scene(self) -> None:
        view = self.view
        sc, cam = view.scene_cfg, view.camera
        self.distractors = distractor_layout(view) if sc.distractors else None
        self.scene, mats = build_static_scene(sc, camera_y_mm=cam.camera_y_mm,
                                              aim_z_mm=cam.aim_z_mm, seed=view.seed,
                                              distractors=self.distractors)
        # by default the logo is centred on the measurement point's line of sight
        logo_y = sc.beam_width_mm / 2 + 0.5
        logo_z = sc.logo_height_mm or (cam.aim_z_mm + (sc.measure_height_mm - cam.aim_z_mm)
                                       * (logo_y - cam.camera_y_mm) / (view.face_y_mm - cam.camera_y_mm))
        self.beam = BeamMesh(sc, mats["paint"], mats["logo"], logo_height_mm=logo_z)
        self.beam_node = self.scene.add(self.beam.mesh(view.shapes, 0.0), name="beam")
        self.sheet_node = self.scene.add(
            pyrender.Mesh([quad_primitive(self.sheet.quad_corners(), mats["paper"])]),
            name="sheet", pose=_AWAY)
        self.gl_camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=20.0, zfar=20000.0)
        self.cam_node = self.scene.add(self.gl_camera, pose=cam.pose())
        s, r = view.cam_cfg.supersample, self.plan.render
        self.renderer = offscreen_renderer(r.width * s, r.height * s)
        self.strip = self._dynamic_strip()

    def _dynamic_strip(self) -> tuple[int, int] | None:
        """Columns [c0, c1) of the render window the beam and logo can reach
        during the clip (beam at world x = 0, i.e. around column cx); None when
        that is most of the window (then render it whole)."""
        cam, r = self.view.camera, self.plan.render
        half = cam.fx * self.view.beam_reach() + _EDGE_MARGIN_PX
        c0 = int(max(0, np.floor(cam.cx - half) - r.x))
        c1 = int(min(r.width, np.ceil(cam.cx + half) + 1 - r.x))
        if c1 <= c0:
            return (0, 0)  # the beam never enters this window
        return None if 2 * (c1 - c0) > r.width else (c0, c1)

    # ------------------------------------------------------------ rendering
    def _render_view(self, t_cam: float, intrinsics: tuple[float, ...], size: tuple[int, int],
                     *, with_sheet: bool = True) -> np.ndarray:
        """sRGB8 pyrender image of the scene at camera time ``t_cam``."""
        view = self.view
        self.scene.remove_node(self.beam_node)
        self.beam_node = self.scene.add(
            self.beam.mesh(view.shapes, t_cam + view.cam_cfg.start_offset_s), name="beam")
        pose = self.sheet.pose(t_cam, view.sheet_plane_y) if with_sheet else None
        self.scene.set_pose(self.sheet_node, _AWAY if pose is None else pose)
        self.scene.set_pose(self.cam_node, view.camera.pose(view.motion.at(t_cam)))
        g = self.gl_camera
        g.fx, g.fy, g.cx, g.cy = intrinsics
        self.renderer.viewport_width, self.renderer.viewport_height = size
        return self.renderer.render(self.scene, flags=RENDER_FLAGS)[0]

    def render_window(self, win: Window, t_cam: float, *, with_sheet: bool = True) -> np.ndarray:
        """Linear 16-bit undistorted render of window ``win`` (render coordinates)."""
        s = self.view.cam_cfg.supersample
        color = self._render_view(t_cam, self.view.camera.render_intrinsics(win, s),
                                  (win.width * s, win.height * s), with_sheet=with_sheet)
        lin = srgb8_to_linear16(color)
        if s > 1:
            lin = cv2.resize(lin.astype(np.float32), (win.width, win.height),
                             interpolation=cv2.INTER_AREA)
            lin = np.rint(lin).astype(np.uint16)
        return lin

    def render_undistorted(self, t_cam: float) -> np.ndarray:
        """Linear 16-bit undistorted render of the whole plan window at ``t_cam``."""
        return self.render_window(self.plan.render, t_cam)

    def _whole_window(self, t_frame: float, smp: SubframeSampling) -> bool:
        """Render whole windows (not background + strip) for this frame?"""
        end = t_frame + smp.times.size * smp.bin_s
        return (self.strip is None or self.view.motion.active
                or self.sheet.present_during(t_frame, end))

    def _composite(self) -> np.ndarray:
        """Persistent undistorted buffer: the static background (rendered once,
        sheet away, camera still) whose strip columns each sub-frame overwrites."""
        if self._background is None:
            self._background = self.render_window(self.plan.render, 0.0, with_sheet=False)
        return self._background

    def strip_window(self) -> Window:
        """The render window's columns of the beam's strip (``strip``), as a window."""
        r, (c0, c1) = self.plan.render, self.strip
        return Window(r.x + c0, r.y, c1 - c0, r.height)

    def _undistorted(self, whole: bool, render) -> np.ndarray:
        """The undistorted window: ``render(window)`` of the whole window, or of
        the beam's strip pasted over the background."""
        if whole:
            return render(self.plan.render)
        buf = self._composite()
        c0, c1 = self.strip
        if c1 > c0:
            buf[:, c0:c1] = render(self.strip_window())
        return buf

    def _averaged(self, win: Window, times: np.ndarray, weights: np.ndarray) -> np.ndarray:
        acc = None
        for t, w in zip(times, weights, strict=True):
            img = self.render_window(win, t).astype(np.float32) * np.float32(w)
            acc = img if acc is None else cv2.add(acc, img)
        return np.rint(np.clip(acc, 0, 65535)).astype(np.uint16)

    def frame_linear(self, index: int) -> np.ndarray:
        """Irradiance (float32, H x W x 3, 1 = full well at gain 1) of frame ``index``."""
        view = self.view
        t_frame = index / view.cam_cfg.fps
        smp, weights, _, _ = self.subframes.at(index)
        active = np.flatnonzero(weights.max(0) > 0)
        times = t_frame + smp.times[active]
        whole = self._whole_window(t_frame, smp)
        scale = np.float32(1 / 65535)
        if smp.global_shutter:
            # every row sees the same sub-frames: average the undistorted renders,
            # then remap once (remap is linear)
            und = self._undistorted(whole, lambda win: self._averaged(win, times,
                                                                      weights[0, active]))
            out = self.plan.apply(und).astype(np.float32) * scale
        else:
            out = np.zeros((view.window.height, view.window.width, 3), np.float32)
            for k, t in zip(active, times, strict=True):
                und = self._undistorted(whole, lambda win, t=t: self.render_window(win, t))
                out += self.plan.apply(und).astype(np.float32) * (weights[:, k] * scale)[:, None, None]
        if view.light.active:
            out *= self.light_rows(index)[:, None, None]
        return out

    def light_rows(self, index: int) -> np.ndarray:
        """Relative light intensity (float32) over each window row's exposure."""
        view = self.view
        cc, w = view.cam_cfg, view.window
        start = index / cc.fps + view.camera.row_times(np.arange(w.y, w.y + w.height))
        return view.light.mean(start, start + cc.exposure_s).astype(np.float32)

    def frame(self, index: int, gain: float) -> np.ndarray:
        """8-bit RGB frame ``index`` of the window at analog gain ``gain``."""
        view = self.view
        return sensor_readout(self.frame_linear(index), gain, view.cam_cfg, seed=view.seed,
                              frame=index, window=view.window)

    # ------------------------------------------------------------ exposure
    def meter(self, index: int) -> float:
        """What the phone's exposure meter reads for frame ``index``: the mean
        irradiance (gain 1) of a low-resolution pinhole render of the whole
        field of view at the middle row's mid-exposure, times the light there.
        Independent of the rendered window."""
        cam, cc = self.view.camera, self.view.cam_cfg
        t = index / cc.fps + float(cam.row_times(cam.height // 2)) + 0.5 * cc.exposure_s
        scale = cc.ae_metering_width_px / cam.width
        size = (cc.ae_metering_width_px, max(2, int(round(cam.height * scale))))
        color = self._render_view(t, (cam.fx * scale, cam.fy * scale, (cam.cx + 0.5) * scale,
                                      (cam.cy + 0.5) * scale), size)
        light = float(self.view.light.mean(t - 0.5 * cc.exposure_s, t + 0.5 * cc.exposure_s))
        return float(srgb8_to_linear16(color).mean()) / 65535 * light

    def gains(self, n_frames: int) -> np.ndarray:
        """Auto-exposure gains of frames 0..n_frames-1 (see :class:`sim.camera.AutoExposure`)."""
        ae = AutoExposure(self.view.cam_cfg)
        return np.array([ae.step(self.meter(i)) for i in range(n_frames)])

    def close(self) -> None:
        release_renderer(self.renderer)
