"""Render the synthetic phone video, its ground truth and a calibration set.

One :class:`BeamRenderer` per output window (the default crop around the
measurement point, or the full sensor). A frame (:meth:`BeamRenderer.frame_linear`)
averages undistorted pyrender renders at the sub-frames of its exposure with
each sensor row's weights (:class:`sim.camera.SubframeSampling`), remaps them
through the exact lens model and scales each row by the light's relative
intensity over its exposure; :meth:`BeamRenderer.frame` adds the sensor
(noise, the auto-exposure's analog gain, gamma, 8 bits; ``sim.camera``).

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

Ground truth (:meth:`BeamRenderer.truth_frame`) is averaged over the same
sub-frames and row weights as the image, and a POI is occluded when the sheet
covers it at one of the sub-frames its row exposes. It is the beam's motion
relative to the ground, seen by the camera in its nominal pose; camera motion
is reported separately (``cam_dx_px``, ``cam_dy_px``).
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.camera import (
    AutoExposure,
    CameraConfig,
    CameraModel,
    SubframeSampling,
    Window,
    sensor_readout,
    srgb8_to_linear16,
)
from sim.codec import CodecConfig, VideoWriter, ffmpeg_version
from sim.disturbance import CameraMotion, Illumination
from sim.occlusion import OcclusionConfig, SheetPath, exposure_gap_before
from sim.scene import (
    BeamMesh,
    BeamShapes,
    SceneConfig,
    build_static_scene,
    offscreen_renderer,
    pyrender,
    quad_primitive,
    release_renderer,
)
from sim.truth_io import CSV_COLUMNS, TruthWriter

_FLAGS = pyrender.RenderFlags.FLAT  # baked lighting, see sim.scene.shading
_AWAY = np.eye(4)
_AWAY[:3, 3] = (0.0, -1e5, 0.0)  # behind the camera: culled
_EDGE_MARGIN_PX = 4  # MSAA and texture filtering reach beyond an object's edge


def _seed(config: dict[str, Any]) -> int:
    seed = config.get("seed", 0)
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


class BeamRenderer:
    """Renders frames and ground truth of one sensor window; see the module docstring."""

    def __init__(self, config: dict[str, Any], shapes: BeamShapes | None, *,
                 full_frame: bool = False, window: Window | None = None,
                 occlusion: OcclusionConfig | None = None):
        self.config = config
        self.seed = _seed(config)
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
        t0 = time.perf_counter()
        self.plan = self.camera.remap_plan(window)
        self.timings = {"remap_plan_s": time.perf_counter() - t0}
        self.mask = self._mask()
        self._setup_pois()
        self._samplings: dict[int, tuple[SubframeSampling, np.ndarray, np.ndarray, np.ndarray]] = {}
        self._background: np.ndarray | None = None
        self._setup_scene()

    # ------------------------------------------------------------ set-up
    def _mask(self) -> np.ndarray:
        """POIs a user would paint: the beam's edge face, 3 px in from its
        edges, over the crop height around the measurement point minus 20 px."""
        inside, _ = self._face_rows()
        if not inside.any():
            raise ValueError(f"the beam face is too narrow for a POI mask at {self.mm_per_px:.3f} "
                             f"mm/px: raise camera.fx_px or lower camera.distance_mm")
        return inside.astype(np.uint8) * 255

    def _face_rows(self) -> tuple[np.ndarray, np.ndarray]:
        """Window-sized ``(inside, z_mm)``: the pixels of the beam's edge face 3 px in from its
        side edges, within the crop's rows minus 20 px, and the rest height each pixel sees."""
        w = self.window
        crop = self.crop_window
        # only the crop's rows can hold POIs: back-project just those pixels
        y0, y1 = max(w.y, crop.y + 20), min(w.y + w.height, crop.y + crop.height - 20)
        x0, x1 = max(w.x, crop.x), min(w.x + w.width, crop.x + crop.width)
        inside = np.zeros((w.height, w.width), bool)
        z_mm = np.full((w.height, w.width), np.nan)
        if y1 > y0 and x1 > x0:
            vv, uu = np.mgrid[y0:y1, x0:x1].astype(np.float64)
            pts = self.camera.backproject_to_plane_y(uu, vv, self.face_y_mm)
            inside[y0 - w.y:y1 - w.y, x0 - w.x:x1 - w.x] = (
                np.abs(pts[..., 0]) <= self.scene_cfg.beam_thickness_mm / 2 - self._inset_mm())
            z_mm[y0 - w.y:y1 - w.y, x0 - w.x:x1 - w.x] = pts[..., 2]
        return inside, z_mm

    def _inset_mm(self) -> float:
        # 3 px in from the edges (1.07 mm at 4K), at most a quarter of the thickness
        return min(3 * self.mm_per_px, 0.25 * self.scene_cfg.beam_thickness_mm)

    def regions_mask(self, heights_mm, half_height_mm: float) -> np.ndarray:
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
        inside, z_mm = self._face_rows()
        top = self.scene_cfg.beam_length_mm - self._inset_mm()
        labels = np.zeros(inside.shape, np.uint8)
        for k, height in enumerate(heights, start=1):
            z1 = min(height + half_height_mm, top)
            z0 = z1 - 2 * half_height_mm
            if z0 <= 0:
                raise ValueError(f"region {k} at {height:g} mm reaches below the clamp: lower "
                                 f"regions.half_height_mm ({half_height_mm:g})")
            rows = np.flatnonzero(np.any(inside & (z_mm >= z0) & (z_mm <= z1), axis=1))
            expected = (z1 - z0) / self.mm_per_px
            if rows.size < 0.9 * expected:
                raise ValueError(f"region {k} ({z0:g}-{z1:g} mm) shows on {rows.size} of its ~{expected:.0f} "
                                 f"rows in the {self.window.width}x{self.window.height} window: raise "
                                 "camera.crop_height_px or set camera.crop_center_z_mm between the heights")
            if (labels[inside & (z_mm >= z0) & (z_mm <= z1)] != 0).any():
                raise ValueError(f"region {k} at {height:g} mm overlaps region {k - 1}: lower "
                                 f"regions.half_height_mm ({half_height_mm:g})")
            labels[inside & (z_mm >= z0) & (z_mm <= z1)] = k
        return labels

    def _setup_pois(self) -> None:
        """The POIs' global pixels, rays, material points and rest projections."""
        vv, uu = np.nonzero(self.mask)
        self.poi_window_px = np.stack([uu, vv], -1).astype(np.float32)
        u, v = uu + float(self.window.x), vv + float(self.window.y)
        self.poi_rows = vv + self.window.y
        self.poi_rays = self.camera.pixel_rays(u, v)
        rest = self.camera.rays_to_plane_y(*self.poi_rays, self.face_y_mm)
        self.poi_a, self.poi_z0 = rest[:, 0], rest[:, 2]
        self.poi_rest_px = self.camera.project(rest)

    def _beam_reach(self) -> float:
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

    def background_mask(self, margin_px: float = 12.0) -> np.ndarray:
        """Static scene a user would mark for camera-motion compensation: every
        pixel of the window whose line of sight stays ``margin_px`` clear of the
        band the beam and its logo sweep during the clip (the wall and its fixtures)."""
        w = self.window
        vv, uu = np.mgrid[w.y:w.y + w.height, w.x:w.x + w.width].astype(np.float64)
        x_ray, _ = self.camera.pixel_rays(uu, vv)
        clear = np.abs(x_ray) > self._beam_reach() + margin_px / self.camera.fx
        return clear.astype(np.uint8) * 255

    def _distractor_layout(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres (world x, z) and kinds of the wall fixtures: inside the
        measurement crop, clear of the beam and logo as the camera sees them."""
        sc, cam, crop = self.scene_cfg, self.camera, self.crop_window
        plane_y = sc.background_distance_mm - 1.0
        u = np.array([crop.x, crop.x + crop.width - 1] * 2, np.float64)
        v = np.array([crop.y] * 2 + [crop.y + crop.height - 1] * 2, np.float64)
        corners = cam.backproject_to_plane_y(u, v, plane_y)
        half = sc.distractor_size_mm / 2
        x_lo, x_hi = max(corners[[0, 2], 0]) + half, min(corners[[1, 3], 0]) - half
        z_lo, z_hi = max(corners[[2, 3], 2]) + half, min(corners[[0, 1], 2]) - half
        keep_out = self._beam_reach() * (plane_y - cam.camera_y_mm) + half + 3.0
        rng = np.random.default_rng([self.seed, 5])
        centres: list[tuple[float, float]] = []
        for _ in range(2000):  # rejection sampling; a crop too small simply holds fewer
            if len(centres) == sc.distractor_count or x_hi <= x_lo or z_hi <= z_lo:
                break
            x, z = rng.uniform(x_lo, x_hi), rng.uniform(z_lo, z_hi)
            if abs(x) >= keep_out and all(np.hypot(x - a, z - b) >= 1.6 * sc.distractor_size_mm
                                          for a, b in centres):
                centres.append((x, z))
        return np.array(centres, np.float64).reshape(-1, 2), np.arange(len(centres)) % 4

    def _setup_scene(self) -> None:
        sc, cam = self.scene_cfg, self.camera
        self.distractors = self._distractor_layout() if sc.distractors else None
        self.scene, mats = build_static_scene(sc, camera_y_mm=cam.camera_y_mm,
                                              aim_z_mm=cam.aim_z_mm, seed=self.seed,
                                              distractors=self.distractors)
        # by default the logo is centred on the measurement point's line of sight
        logo_y = sc.beam_width_mm / 2 + 0.5
        logo_z = sc.logo_height_mm or (cam.aim_z_mm + (sc.measure_height_mm - cam.aim_z_mm)
                                       * (logo_y - cam.camera_y_mm) / (self.face_y_mm - cam.camera_y_mm))
        self.beam = BeamMesh(sc, mats["paint"], mats["logo"], logo_height_mm=logo_z)
        self.beam_node = self.scene.add(self.beam.mesh(self.shapes, 0.0), name="beam")
        self._setup_sheet()
        self.sheet_node = self.scene.add(
            pyrender.Mesh([quad_primitive(self.sheet.quad_corners(), mats["paper"])]),
            name="sheet", pose=_AWAY)
        self.gl_camera = pyrender.IntrinsicsCamera(1.0, 1.0, 0.0, 0.0, znear=20.0, zfar=20000.0)
        self.cam_node = self.scene.add(self.gl_camera, pose=cam.pose())
        s, r = self.cam_cfg.supersample, self.plan.render
        self.renderer = offscreen_renderer(r.width * s, r.height * s)
        self.strip = self._dynamic_strip()

    def sheet_coords(self, rays: tuple[np.ndarray, np.ndarray], t_cam: float | None = None):
        """Coordinates (along, across the sheet's path) on the sheet's plane of
        normalised rays ``(x, y)`` of the camera as it stands at ``t_cam``."""
        motion = None if t_cam is None else self.motion.at(t_cam)
        pts = self.camera.rays_to_plane_y(*rays, self.sheet_plane_y, motion)
        along = 0 if self.occ_cfg.direction in ("+x", "-x") else 2
        return pts[..., along], pts[..., 2 - along]

    def _setup_sheet(self) -> None:
        cam, occ, cc = self.camera, self.occ_cfg, self.cam_cfg
        self.sheet_plane_y = cam.camera_y_mm + occ.distance_mm
        s_mask, _ = self.sheet_coords(self.poi_rays)
        corners = cam.pixel_rays(np.array([0, cam.width - 1, 0, cam.width - 1], float),
                                 np.array([0, 0, cam.height - 1, cam.height - 1], float))
        s_fov, _ = self.sheet_coords(corners)
        measure_ray = cam.pixel_rays(*self.measure_px)
        _, across = self.sheet_coords(measure_ray)
        rows = (float(cam.row_times(self.poi_rows.min())), float(cam.row_times(self.poi_rows.max())))
        gaps = tuple(exposure_gap_before(t, cc.fps, cc.exposure_s, rows)
                     for t in (occ.start_s, occ.start_s + occ.duration_s))
        focal = cam.fx if occ.direction in ("+x", "-x") else cam.fy
        self.sheet = SheetPath(occ, mask_s=s_mask, fov_s=(float(s_fov.min()), float(s_fov.max())),
                               across_center=float(across), gaps_s=gaps,
                               pixel_mm=occ.distance_mm / focal)

    def _dynamic_strip(self) -> tuple[int, int] | None:
        """Columns [c0, c1) of the render window the beam and logo can reach
        during the clip (beam at world x = 0, i.e. around column cx); None when
        that is most of the window (then render it whole)."""
        cam, r = self.camera, self.plan.render
        half = cam.fx * self._beam_reach() + _EDGE_MARGIN_PX
        c0 = int(max(0, np.floor(cam.cx - half) - r.x))
        c1 = int(min(r.width, np.ceil(cam.cx + half) + 1 - r.x))
        if c1 <= c0:
            return (0, 0)  # the beam never enters this window
        return None if 2 * (c1 - c0) > r.width else (c0, c1)

    # ------------------------------------------------------------ sub-frames
    def sampling(self, index: int) -> SubframeSampling:
        """The sub-frames of frame ``index``: ``camera.motion_blur_subframes`` bins
        per exposure, ``occlusion.motion_blur_subframes`` while the sheet moves
        (its edge sweeps ~100 px per exposure at 4K). The choice depends on the
        whole sensor's read-out, never on the window."""
        return self._sampling_entry(index)[0]

    def _sampling_entry(self, index: int):
        cc = self.cam_cfg
        t = index / cc.fps
        span = float(self.camera.row_times(self.camera.height - 1)) + cc.exposure_s
        n = cc.motion_blur_subframes
        if self.sheet.moves_during(t, t + span):
            n = max(n, self.occ_cfg.motion_blur_subframes)
        if n not in self._samplings:
            smp = self.camera.sampling(n)
            rows = np.arange(self.window.y, self.window.y + self.window.height)
            self._samplings[n] = (smp, smp.weights(rows).astype(np.float32),
                                  smp.weights(self.poi_rows),
                                  smp.weights(np.rint(self.measure_px[1:]))[0])
        return self._samplings[n]

    # ------------------------------------------------------------ rendering
    def _render_view(self, t_cam: float, intrinsics: tuple[float, ...], size: tuple[int, int],
                     *, with_sheet: bool = True) -> np.ndarray:
        """sRGB8 pyrender image of the scene at camera time ``t_cam``."""
        self.scene.remove_node(self.beam_node)
        self.beam_node = self.scene.add(
            self.beam.mesh(self.shapes, t_cam + self.cam_cfg.start_offset_s), name="beam")
        pose = self.sheet.pose(t_cam, self.sheet_plane_y) if with_sheet else None
        self.scene.set_pose(self.sheet_node, _AWAY if pose is None else pose)
        self.scene.set_pose(self.cam_node, self.camera.pose(self.motion.at(t_cam)))
        g = self.gl_camera
        g.fx, g.fy, g.cx, g.cy = intrinsics
        self.renderer.viewport_width, self.renderer.viewport_height = size
        return self.renderer.render(self.scene, flags=_FLAGS)[0]

    def _render_window(self, win: Window, t_cam: float, *, with_sheet: bool = True) -> np.ndarray:
        """Linear 16-bit undistorted render of window ``win`` (render coordinates)."""
        s = self.cam_cfg.supersample
        color = self._render_view(t_cam, self.camera.render_intrinsics(win, s),
                                  (win.width * s, win.height * s), with_sheet=with_sheet)
        lin = srgb8_to_linear16(color)
        if s > 1:
            lin = cv2.resize(lin.astype(np.float32), (win.width, win.height),
                             interpolation=cv2.INTER_AREA)
            lin = np.rint(lin).astype(np.uint16)
        return lin

    def render_undistorted(self, t_cam: float) -> np.ndarray:
        """Linear 16-bit undistorted render of the whole plan window at ``t_cam``."""
        return self._render_window(self.plan.render, t_cam)

    def _whole_window(self, t_frame: float, smp: SubframeSampling) -> bool:
        """Render whole windows (not background + strip) for this frame?"""
        end = t_frame + smp.times.size * smp.bin_s
        return (self.strip is None or self.motion.active
                or self.sheet.present_during(t_frame, end))

    def _composite(self) -> np.ndarray:
        """Persistent undistorted buffer: the static background (rendered once,
        sheet away, camera still) whose strip columns each sub-frame overwrites."""
        if self._background is None:
            self._background = self._render_window(self.plan.render, 0.0, with_sheet=False)
        return self._background

    def _strip_window(self) -> Window:
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
            buf[:, c0:c1] = render(self._strip_window())
        return buf

    def _averaged(self, win: Window, times: np.ndarray, weights: np.ndarray) -> np.ndarray:
        acc = None
        for t, w in zip(times, weights, strict=True):
            img = self._render_window(win, t).astype(np.float32) * np.float32(w)
            acc = img if acc is None else cv2.add(acc, img)
        return np.rint(np.clip(acc, 0, 65535)).astype(np.uint16)

    def frame_linear(self, index: int) -> np.ndarray:
        """Irradiance (float32, H x W x 3, 1 = full well at gain 1) of frame ``index``."""
        cc = self.cam_cfg
        t_frame = index / cc.fps
        smp, weights, _, _ = self._sampling_entry(index)
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
            out = np.zeros((self.window.height, self.window.width, 3), np.float32)
            for k, t in zip(active, times, strict=True):
                und = self._undistorted(whole, lambda win, t=t: self._render_window(win, t))
                out += self.plan.apply(und).astype(np.float32) * (weights[:, k] * scale)[:, None, None]
        if self.light.active:
            out *= self.light_rows(index)[:, None, None]
        return out

    def light_rows(self, index: int) -> np.ndarray:
        """Relative light intensity (float32) over each window row's exposure."""
        cc = self.cam_cfg
        start = index / cc.fps + self.camera.row_times(
            np.arange(self.window.y, self.window.y + self.window.height))
        return self.light.mean(start, start + cc.exposure_s).astype(np.float32)

    def frame(self, index: int, gain: float) -> np.ndarray:
        """8-bit RGB frame ``index`` of the window at analog gain ``gain``."""
        return sensor_readout(self.frame_linear(index), gain, self.cam_cfg, seed=self.seed,
                              frame=index, window=self.window)

    # ------------------------------------------------------------ exposure
    def meter(self, index: int) -> float:
        """What the phone's exposure meter reads for frame ``index``: the mean
        irradiance (gain 1) of a low-resolution pinhole render of the whole
        field of view at the middle row's mid-exposure, times the light there.
        Independent of the rendered window."""
        cam, cc = self.camera, self.cam_cfg
        t = index / cc.fps + float(cam.row_times(cam.height // 2)) + 0.5 * cc.exposure_s
        scale = cc.ae_metering_width_px / cam.width
        size = (cc.ae_metering_width_px, max(2, int(round(cam.height * scale))))
        color = self._render_view(t, (cam.fx * scale, cam.fy * scale, (cam.cx + 0.5) * scale,
                                      (cam.cy + 0.5) * scale), size)
        light = float(self.light.mean(t - 0.5 * cc.exposure_s, t + 0.5 * cc.exposure_s))
        return float(srgb8_to_linear16(color).mean()) / 65535 * light

    def gains(self, n_frames: int) -> np.ndarray:
        """Auto-exposure gains of frames 0..n_frames-1 (see :class:`sim.camera.AutoExposure`)."""
        ae = AutoExposure(self.cam_cfg)
        return np.array([ae.step(self.meter(i)) for i in range(n_frames)])

    def close(self) -> None:
        release_renderer(self.renderer)

    # ------------------------------------------------------------ truth
    def n_frames(self, duration_s: float | None = None) -> int:
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

    def _beam_points(self, t_cam: float) -> tuple[np.ndarray, np.ndarray]:
        """World positions of the measurement point (3,) and the POIs' material points (P, 3)."""
        t_sim = t_cam + self.cam_cfg.start_offset_s
        a = np.concatenate([[0.0], self.poi_a])
        z0 = np.concatenate([[self.measure_point[2]], self.poi_z0])
        if self.shapes is None:
            pts = np.stack([a, np.full_like(a, self.face_y_mm), z0], -1)
        else:
            pts = self.shapes.material_to_world(t_sim, a, self.face_y_mm, z0)
        return pts[0], pts[1:]

    def scale_points(self) -> np.ndarray:
        """Where a user clicks the beam's two edges (its thickness, the paper's scale
        reference) on frame 0 at the measurement height: ``[x1, y1, x2, y2]`` raw
        window pixels, exact (a perfect click)."""
        half = self.scene_cfg.beam_thickness_mm / 2
        t_sim = 0.5 * self.cam_cfg.exposure_s + self.cam_cfg.start_offset_s
        a, z0 = np.array([-half, half]), np.full(2, self.measure_point[2])
        if self.shapes is None:
            edges = np.stack([a, np.full(2, self.face_y_mm), z0], -1)
        else:
            edges = self.shapes.material_to_world(t_sim, a, self.face_y_mm, z0)
        pixels = self.camera.project(edges) - [self.window.x, self.window.y]
        return pixels.ravel()

    def truth_frame(self, index: int) -> dict[str, Any]:
        """Ground truth of frame ``index`` (see ``sim.truth_io`` for the columns),
        averaged over the image's own sub-frames and row weights."""
        cc, cam = self.cam_cfg, self.camera
        t_frame = index / cc.fps
        smp, _, w_poi, w_measure = self._sampling_entry(index)
        n_poi = self.poi_a.size
        world, pix, cam_shift = np.zeros(3), np.zeros(2), np.zeros(2)
        poi_pix, covered = np.zeros((n_poi, 2)), np.zeros(n_poi, bool)
        for k in np.flatnonzero((w_measure > 0) | (w_poi > 0).any(0)):
            t = t_frame + smp.times[k]
            m_world, p_world = self._beam_points(t)
            world += w_measure[k] * m_world
            pix += w_measure[k] * cam.project(m_world)
            poi_pix += w_poi[:, k, None] * cam.project(p_world)
            motion = self.motion.at(t)
            if motion is not None:
                cam_shift += w_measure[k] * (cam.project(self.measure_point, motion)
                                             - self.measure_px)
            if self.sheet.extent(t) is not None:
                on_sheet = self.sheet.covers(t, *self.sheet_coords(self.poi_rays, t))
                covered |= (w_poi[:, k] > 0) & on_sheet
        start = t_frame + float(cam.row_times(np.rint(self.measure_px[1])))
        poi_shift = poi_pix - self.poi_rest_px
        return {
            "frame": index, "time_s": t_frame,
            "dx_px": pix[0] - self.measure_px[0], "dy_px": pix[1] - self.measure_px[1],
            "dx_mm": world[0] - self.measure_point[0], "dy_mm": -(world[2] - self.measure_point[2]),
            "occluded": int(covered.any()), "occluded_frac": float(covered.mean()) if n_poi else 0.0,
            "cam_dx_px": cam_shift[0], "cam_dy_px": cam_shift[1],
            "light_rel": float(self.light.mean(start, start + cc.exposure_s)),
            "poi_dx_px": poi_shift[:, 0].astype(np.float32),
            "poi_dy_px": poi_shift[:, 1].astype(np.float32),
            "poi_covered": covered,
        }

    def truth(self, n_frames: int) -> dict[str, np.ndarray]:
        """Truth of frames 0..n_frames-1 stacked in memory (short clips and tests;
        :func:`render_clip` streams it frame by frame instead)."""
        rows = [self.truth_frame(i) for i in range(n_frames)]
        out = {key: np.array([row[key] for row in rows]) for key in rows[0]}
        out["poi_x_px"], out["poi_y_px"] = self.poi_window_px[:, 0], self.poi_window_px[:, 1]
        return out

    def metadata(self) -> dict[str, Any]:
        cam, cc = self.camera, self.cam_cfg
        return {
            "mm_per_px": self.mm_per_px, "fps": cc.fps, "crop": self.window.as_dict(),
            "sensor": {"width": cam.width, "height": cam.height},
            "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                           "K": cam.K.tolist()},
            "distortion": {"k1": cam.k1, "k2": cam.k2, "p1": cam.p1, "p2": cam.p2,
                           "model": "Brown-Conrady, OpenCV order (k1, k2, p1, p2, k3=0)"},
            "camera_start_offset_s": cc.start_offset_s,
            "camera_position_mm": [0.0, cam.camera_y_mm, cam.aim_z_mm],
            "camera_looks_along": "+y (world x = image right, world z = image up)",
            "measurement_point_mm": self.measure_point.tolist(),
            "measurement_point_px": self.measure_px.tolist(),
            "exposure_s": cc.exposure_s,
            "rolling_shutter_s": cc.rolling_shutter_s,
            "subframes": {"camera": cc.motion_blur_subframes,
                          "sheet_moving": self.occ_cfg.motion_blur_subframes,
                          "rule": "bins of exposure/n on a grid shared by all rows, rendered at "
                                  "their centres; a row weighs each bin by its exposure overlap"},
            "truth_columns": list(CSV_COLUMNS),
            "truth_convention": (
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
                "measurement row's exposure; gain = auto-exposure analog gain"),
            "disturbances": {"camera_shake": cc.shake, "camera_drift": cc.drift,
                             "flicker": self.scene_cfg.flicker, "clouds": self.scene_cfg.clouds,
                             "light_drift": self.scene_cfg.light_drift},
            "distractors_mm": ([] if self.distractors is None
                               else self.distractors[0].tolist()),
            "config": {"camera": asdict(cc), "scene": asdict(self.scene_cfg),
                       "occlusion": asdict(self.occ_cfg)},
        }


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
    r = BeamRenderer(config, None)
    try:
        labels = r.regions_mask(heights, half)
    finally:
        r.close()
    with atomic_path(out) as tmp:
        if not cv2.imwrite(str(tmp), labels):
            raise ValueError(f"could not write {out}: give it a .png name in a writable folder")
    rows = [np.flatnonzero((labels == k).any(axis=1)) for k in range(1, heights.size + 1)]
    return {"heights_mm": heights.tolist(), "half_height_mm": half,
            "rows": [[int(r_[0]), int(r_[-1])] for r_ in rows], "window": r.window.as_dict()}


# ----------------------------------------------------------------- clips
def render_clip(config: dict[str, Any], shapes: BeamShapes, out_dir: str | Path, *,
                full_frame: bool = False, max_frames: int | None = None,
                progress: bool = True) -> dict[str, Any]:
    """Render the video and its ground truth into ``out_dir`` (see docs/formats.md).

    Frames go straight to the encoder and the truth to its files frame by
    frame (``sim.truth_io``): memory does not grow with the clip's length.
    """
    from refflow.io import atomic_paths, config_hash, json_text, versions, write_json
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    codec = CodecConfig.from_config(config)
    t_start = time.perf_counter()
    r = BeamRenderer(config, shapes, full_frame=full_frame)
    try:
        n = r.n_frames()
        if max_frames is not None:
            n = min(n, int(max_frames))
        w = r.window
        video = out_dir / f"video{codec.suffix}"
        ae = AutoExposure(r.cam_cfg)
        spent = {"meter_s": 0.0, "truth_s": 0.0}
        frame_times = []
        outputs = (video, out_dir / "mask.png", out_dir / "background.png", out_dir / "scale.json",
                   out_dir / "recording.json", out_dir / "poi_truth.npz", out_dir / "truth.csv")
        with atomic_paths(*outputs) as (tmp_video, tmp_mask, tmp_background, tmp_scale, tmp_recording,
                                        tmp_npz, tmp_csv):
            with VideoWriter(tmp_video, w.width, w.height, r.cam_cfg.fps, codec) as writer, \
                    TruthWriter(tmp_csv, tmp_npz, poi_x_px=r.poi_window_px[:, 0],
                                poi_y_px=r.poi_window_px[:, 1]) as truth_out:
                it = range(n)
                if progress:
                    from tqdm import tqdm
                    it = tqdm(it, desc=f"render {w.width}x{w.height}", unit="frame")
                for i in it:
                    t0 = time.perf_counter()
                    gain = ae.step(r.meter(i))
                    t1 = time.perf_counter()
                    writer.write(r.frame(i, gain))
                    t2 = time.perf_counter()
                    truth_out.write(r.truth_frame(i), gain)
                    spent["meter_s"] += t1 - t0
                    spent["truth_s"] += time.perf_counter() - t2
                    frame_times.append(t2 - t1)
            cv2.imwrite(str(tmp_mask), r.mask)
            cv2.imwrite(str(tmp_background), r.background_mask())
            # the scale as the paper's user takes it (refflow track --scale-file reads it)
            tmp_scale.write_text(json_text({
                "known_length_mm": r.scene_cfg.beam_thickness_mm,
                "between_px": [round(float(v), 4) for v in r.scale_points()],
                "what": "the beam's front-face edges at the measurement height on frame 0 (raw video "
                        "pixels, exact); their distance is the beam thickness"}))
            # what the recording itself tells: the video is this window of the sensor
            # (refflow track --video-origin reads it to use the full-sensor calibration)
            tmp_recording.write_text(json_text({
                "video_origin_px": [w.x, w.y], "video_size_px": [w.width, w.height],
                "sensor_size_px": [r.camera.width, r.camera.height], "fps": r.cam_cfg.fps}))
        meta = r.metadata()
        ft = np.array(frame_times) if frame_times else np.zeros(1)
        meta.update({
            "video": video.name, "frames": n, "codec": asdict(codec),
            "codec_bitrate_bps": codec.bitrate_bps(w.width, w.height, r.cam_cfg.fps),
            "ffmpeg": ffmpeg_version(), "seed": r.seed, "config_hash": config_hash(config),
            "versions": versions(), "n_pois": int(r.poi_a.size),
            "timings": {**r.timings, **spent, "frames_s": float(ft.sum()),
                        "frame_median_s": float(np.median(ft)),
                        "fps_rendered": float(n / max(ft.sum(), 1e-9)),
                        "total_s": time.perf_counter() - t_start},
            "units": {"dx_px": "px", "dx_mm": "mm", "time_s": "s", "mm_per_px": "mm/px",
                      "cam_dx_px": "px", "light_rel": "1", "gain": "1"},
        })
        write_json(out_dir / "render.json", meta)
        return meta
    finally:
        r.close()


# ----------------------------------------------------------------- calibration
def checkerboard_texture(cols: int, rows: int, px_per_square: int = 64, border: int = 1):
    """(rows+1) x (cols+1) squares -> cols x rows inner corners, white border."""
    nx, ny = cols + 1, rows + 1
    board = ((np.indices((ny, nx)).sum(0) % 2) * 255).astype(np.uint8)
    board = np.kron(255 - board, np.ones((px_per_square, px_per_square), np.uint8))
    b = border * px_per_square
    board = np.pad(board, b, constant_values=255)
    return np.repeat(board[..., None], 3, 2)


def render_calibration(config: dict[str, Any], out_dir: str | Path, *, n_images: int = 15,
                       cols: int = 9, rows: int = 6, square_mm: float = 40.0,
                       progress: bool = True) -> dict[str, Any]:
    """Checkerboard images through the same camera, lens and sensor as the video."""
    from refflow.io import atomic_path, config_hash, versions, write_json
    from sim.scene import material
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    seed = _seed(config)
    sc, cc = SceneConfig.from_config(config), CameraConfig.from_config(config)
    cam = CameraModel(cc, camera_y_mm=-sc.beam_width_mm / 2 - cc.distance_mm)
    plan = cam.remap_plan(cam.full_window())
    scene = pyrender.Scene(ambient_light=np.full(3, 0.6), bg_color=(0.2, 0.2, 0.2, 1.0))
    scene.add(pyrender.DirectionalLight(intensity=2.0), pose=cam.pose())
    tex = checkerboard_texture(cols, rows)
    bw, bh = (cols + 3) * square_mm, (rows + 3) * square_mm   # squares + white border
    corners = np.array([[-bw / 2, 0, -bh / 2], [bw / 2, 0, -bh / 2], [bw / 2, 0, bh / 2],
                        [-bw / 2, 0, bh / 2]])
    board = scene.add(pyrender.Mesh([quad_primitive(corners, material(tex, 0.9))]))
    fx, fy, cx, cy = cam.render_intrinsics(plan.render, 1)
    scene.add(pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=20.0, zfar=20000.0), pose=cam.pose())
    renderer = offscreen_renderer(plan.render.width, plan.render.height)
    rng = np.random.default_rng([seed, 7])
    images, poses = [], []
    it = range(n_images)
    if progress:
        from tqdm import tqdm
        it = tqdm(it, desc="calibration", unit="image")
    try:
        for i in it:
            dist = rng.uniform(600, 1000)
            half_w = 0.5 * cam.width / cam.fx * (dist) - bw / 2 * 0.8
            half_h = 0.5 * cam.height / cam.fy * (dist) - bh / 2 * 0.8
            x = rng.uniform(-half_w, half_w) if half_w > 0 else 0.0
            z = rng.uniform(-half_h, half_h) if half_h > 0 else 0.0
            rx, rz, ry = np.deg2rad(rng.uniform(-30, 30)), np.deg2rad(rng.uniform(-30, 30)), \
                np.deg2rad(rng.uniform(-15, 15))
            R = (cv2.Rodrigues(np.array([rx, 0, 0.0]))[0] @ cv2.Rodrigues(np.array([0, 0, rz]))[0]
                 @ cv2.Rodrigues(np.array([0, ry, 0.0]))[0])
            pose = np.eye(4)
            pose[:3, :3] = R
            pose[:3, 3] = (x, cam.camera_y_mm + dist, cam.aim_z_mm + z)
            scene.set_pose(board, pose)
            color = renderer.render(scene, flags=_FLAGS)[0]
            lin = plan.apply(srgb8_to_linear16(color)).astype(np.float32) / 65535
            img = sensor_readout(lin, 1.0, cc, seed=seed + 1000, frame=i, window=plan.window)
            name = f"calib_{i:03d}.png"
            with atomic_path(out_dir / name) as tmp:
                cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
            images.append(name)
            poses.append(pose.tolist())
    finally:
        release_renderer(renderer)
    meta = {"images": images, "image_size": [cam.width, cam.height],
            "camera_matrix": cam.K.tolist(), "dist_coeffs": cam.dist.tolist(),
            "distortion": {"k1": cam.k1, "k2": cam.k2, "p1": cam.p1, "p2": cam.p2},
            "board": {"inner_corners": [cols, rows], "square_mm": square_mm},
            "board_poses_world": poses, "seed": seed, "config_hash": config_hash(config),
            "versions": versions()}
    write_json(out_dir / "calibration_truth.json", meta)
    return meta


# ----------------------------------------------------------------- figures
def figure_frames(renderer: BeamRenderer, n_frames: int) -> dict[str, int]:
    """Frames for the figures of a clip of ``n_frames``: ``motion``, where the
    measurement point's displacement x speed peaks (the beam visibly bent *and*
    moving: motion blur) among frames the sheet does not touch; ``occluded``,
    the middle of the configured occlusion; ``occluding``, the frame of the
    sheet's entry in which it covers the share of the crop nearest one half."""
    cc, occ = renderer.cam_cfg, renderer.occ_cfg
    mid = 0.5 * cc.exposure_s + float(renderer.camera.row_times(np.rint(renderer.measure_px[1])))
    t = np.arange(n_frames) / cc.fps
    x = np.array([renderer._beam_points(ti + mid)[0][0] for ti in t])
    speed = np.abs(np.gradient(x, t)) if n_frames > 1 else np.zeros(1)
    sheet_free = np.array([not renderer.sheet.present_during(ti, ti + 1 / cc.fps) for ti in t])
    score = np.where(sheet_free, np.abs(x - renderer.measure_point[0]) * speed, -1.0)
    frames = {"motion": int(np.argmax(score))}
    first, last = occ.start_s, occ.start_s + occ.duration_s
    if occ.enabled and last <= (n_frames - 1) / cc.fps:
        frames["occluded"] = int(np.floor(0.5 * (first + last) * cc.fps))
        crop = renderer.crop_window
        vv, uu = np.mgrid[crop.y:crop.y + crop.height:8, crop.x:crop.x + crop.width:8]
        rays = renderer.camera.pixel_rays(uu.astype(float), vv.astype(float))
        entry = np.arange(max(0, int((first - occ.transit_s) * cc.fps)), int(np.ceil(first * cc.fps)))
        share = [renderer.sheet.covers(i / cc.fps + mid, *renderer.sheet_coords(rays)).mean()
                 for i in entry]
        if entry.size:
            frames["occluding"] = int(entry[np.argmin(np.abs(np.array(share) - 0.5))])
    return frames


def render_figures(config: dict[str, Any], shapes: BeamShapes, out_dir: str | Path) -> list[Path]:
    """render_full.png (4K, downscaled to 1920 wide) and render_crop.png at a frame of
    motion, render_occluded.png (and render_occluding.png, the sheet's entry) with
    the config's occlusion (switched on if the config has it off)."""
    from refflow.io import atomic_path
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(name, renderer, frame, box=None, size=None):
        img = renderer.frame(frame, renderer.gains(frame + 1)[frame])
        if box is not None:
            img = img.copy()
            cv2.rectangle(img, (box.x, box.y), (box.x + box.width, box.y + box.height),
                          (255, 200, 0), 4)
        if size is not None:
            img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
        with atomic_path(out_dir / name) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(img, cv2.COLOR_RGB2BGR))
        written.append(out_dir / name)

    occ = asdict(OcclusionConfig.from_config(config))
    occluding = {**config, "occlusion": {**occ, "enabled": True}}
    crop = BeamRenderer(occluding, shapes)
    try:
        n = crop.n_frames()
        frames = figure_frames(crop, n)
        if "occluded" not in frames:
            raise ValueError(f"the occlusion ({occ['start_s']} s + {occ['duration_s']} s) does "
                             f"not fit the {n} frames the shapes allow: adjust occlusion.start_s "
                             f"or pass longer shapes")
        # the figures of the beam in motion show it without the sheet
        clear = {**config, "occlusion": {**occ, "enabled": False}}
        full = BeamRenderer(clear, shapes, full_frame=True)
        try:
            save("render_full.png", full, frames["motion"], box=full.crop_window, size=(1920, 1080))
        finally:
            full.close()
        plain = BeamRenderer(clear, shapes)
        try:
            save("render_crop.png", plain, frames["motion"])
        finally:
            plain.close()
        save("render_occluded.png", crop, frames["occluded"])
        if "occluding" in frames:  # not declared by the workflow rule: an extra view
            save("render_occluding.png", crop, frames["occluding"])
    finally:
        crop.close()
    return written
