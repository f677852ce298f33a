"""Render the synthetic phone video, its ground truth and a calibration set.

One :class:`BeamRenderer` per output window (the default crop around the
measurement point, or the full sensor). A frame is the average of
``camera.motion_blur_subframes`` undistorted pyrender renders within the
exposure (per sensor row when the rolling shutter is on), remapped through the
exact lens model, scaled by the auto-exposure gain, then noise, gamma and 8-bit
quantisation (``sim.camera.sensor_readout``).
"""

from __future__ import annotations

import csv
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.camera import CameraConfig, CameraModel, Window, sensor_readout, srgb8_to_linear16
from sim.codec import CodecConfig, VideoWriter, ffmpeg_version
from sim.occlusion import A4_MM, OcclusionConfig, SheetPath
from sim.scene import (
    BeamMesh,
    BeamShapes,
    SceneConfig,
    build_static_scene,
    pyrender,
    quad_primitive,
    release_renderer,
)

_FLAGS = pyrender.RenderFlags.FLAT  # baked lighting, see sim.scene.shading
_AWAY = np.eye(4)
_AWAY[:3, 3] = (0.0, -1e5, 0.0)  # behind the camera: culled


def _seed(config: dict[str, Any]) -> int:
    seed = config.get("seed", 0)
    if not isinstance(seed, (int, np.integer)) or isinstance(seed, bool) or seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


class BeamRenderer:
    """Renders frames of one sensor window; see the module docstring."""

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
        self.mm_per_px = self.camera.mm_per_px_at(self.face_y_mm)
        self.measure_point = np.array([0.0, self.face_y_mm, sc.measure_height_mm])
        self.measure_px = self.camera.project(self.measure_point)
        if window is None:
            window = (self.camera.full_window() if full_frame
                      else self.camera.crop_around(*self.measure_px))
        self.window = window
        self.crop_window = self.camera.crop_around(*self.measure_px)
        t0 = time.perf_counter()
        self.plan = self.camera.remap_plan(window)
        self.timings = {"remap_plan_s": time.perf_counter() - t0}
        self.mask = self._mask()
        self._setup_scene()
        self.sample_times, self.row_weights = self.camera.exposure_samples(window)

    # ------------------------------------------------------------ set-up
    def _mask(self) -> np.ndarray:
        """POIs a user would paint: the beam's edge face, 3 px in from its
        edges, over the crop height around the measurement point minus 20 px."""
        w = self.window
        crop = self.crop_window
        # only the crop's rows can hold POIs: back-project just those pixels
        y0, y1 = max(w.y, crop.y + 20), min(w.y + w.height, crop.y + crop.height - 20)
        x0, x1 = max(w.x, crop.x), min(w.x + w.width, crop.x + crop.width)
        mask = np.zeros((w.height, w.width), np.uint8)
        if y1 > y0 and x1 > x0:
            vv, uu = np.mgrid[y0:y1, x0:x1].astype(np.float64)
            pts = self.camera.backproject_to_plane_y(uu, vv, self.face_y_mm)
            # 3 px in from the edges (1.07 mm at 4K), at most a quarter of the thickness
            inset_mm = min(3 * self.mm_per_px, 0.25 * self.scene_cfg.beam_thickness_mm)
            inside = np.abs(pts[..., 0]) <= self.scene_cfg.beam_thickness_mm / 2 - inset_mm
            mask[y0 - w.y:y1 - w.y, x0 - w.x:x1 - w.x] = inside.astype(np.uint8) * 255
        if not mask.any():
            raise ValueError(f"the beam face is too narrow for a POI mask at {self.mm_per_px:.3f} "
                             f"mm/px: raise camera.fx_px or lower camera.distance_mm")
        return mask

    def _setup_scene(self) -> None:
        sc, cam = self.scene_cfg, self.camera
        self.scene, mats = build_static_scene(sc, camera_y_mm=cam.camera_y_mm,
                                              aim_z_mm=cam.aim_z_mm, seed=self.seed)
        # by default the logo is centred on the measurement point's line of sight
        logo_y = sc.beam_width_mm / 2 + 0.5
        logo_z = sc.logo_height_mm or (cam.aim_z_mm + (sc.measure_height_mm - cam.aim_z_mm)
                                       * (logo_y - cam.camera_y_mm) / (self.face_y_mm - cam.camera_y_mm))
        self.beam = BeamMesh(sc, mats["paint"], mats["logo"], logo_height_mm=logo_z)
        self.beam_node = self.scene.add(self.beam.mesh(self.shapes, 0.0), name="beam")
        # the sheet: a quad centred at its node origin in the x-z plane, facing the camera
        hw, hh = A4_MM[0] / 2, A4_MM[1] / 2
        corners = np.array([[-hw, 0, -hh], [hw, 0, -hh], [hw, 0, hh], [-hw, 0, hh]])
        self.sheet_node = self.scene.add(pyrender.Mesh([quad_primitive(corners, mats["paper"])]),
                                         name="sheet", pose=_AWAY)
        self.sheet_plane_y = cam.camera_y_mm + self.occ_cfg.distance_mm
        self._setup_sheet_path()
        s = self.cam_cfg.supersample
        r = self.plan.render
        fx, fy, cx, cy = cam.render_intrinsics(r, s)
        self.cam_node = self.scene.add(
            pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=20.0, zfar=20000.0), pose=cam.pose())
        self.renderer = pyrender.OffscreenRenderer(r.width * s, r.height * s)
        self._meter()

    def _plane_coords(self, u, v, depth):
        """Travel-axis coordinate on a plane ``depth`` mm in front of the lens."""
        x, y = self.camera.pixel_rays(u, v)
        axis = 0 if self.occ_cfg.direction in ("+x", "-x") else 1
        return x * depth if axis == 0 else self.camera.aim_z_mm - y * depth

    def _setup_sheet_path(self) -> None:
        d = self.occ_cfg.distance_mm
        crop = self.crop_window
        vv, uu = np.nonzero(self._mask_crop())
        uu, vv = uu + crop.x, vv + crop.y
        s_mask = self._plane_coords(uu, vv, d)
        s_point = float(self._plane_coords(*self.measure_px, d))
        cam = self.camera
        corners_u = np.array([0, cam.width - 1, 0, cam.width - 1], float)
        corners_v = np.array([0, 0, cam.height - 1, cam.height - 1], float)
        s_fov = self._plane_coords(corners_u, corners_v, d)
        self.fov_s = (float(s_fov.min()), float(s_fov.max()))
        axis = 0 if self.occ_cfg.direction in ("+x", "-x") else 1
        across = (cam.aim_z_mm - float(cam.pixel_rays(*self.measure_px)[1]) * d if axis == 0
                  else float(cam.pixel_rays(*self.measure_px)[0]) * d)
        self.sheet = SheetPath(self.occ_cfg, region_s=(float(s_mask.min()), float(s_mask.max())),
                               point_s=s_point, fov_s=self.fov_s, across_center=across)
        self._poi_sheet_s = None

    def _mask_crop(self) -> np.ndarray:
        if self.window == self.crop_window:
            return self.mask
        c, w = self.crop_window, self.window
        return self.mask[c.y - w.y:c.y - w.y + c.height, c.x - w.x:c.x - w.x + c.width]

    def _sheet_pose(self, t_cam: float) -> np.ndarray:
        ext = self.sheet.extent(t_cam)
        if ext is None:
            return _AWAY
        centre = 0.5 * (ext[0] + ext[1])
        pose = np.eye(4)
        if self.sheet.axis == 0:
            pose[:3, 3] = (centre, self.sheet_plane_y, self.sheet.across_center)
        else:
            pose[:3, :3] = [[0, 0, -1], [0, 1, 0], [1, 0, 0]]  # landscape when moving vertically
            pose[:3, :3] = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]]).T
            pose[:3, 3] = (self.sheet.across_center, self.sheet_plane_y, centre)
        return pose

    def _meter(self) -> None:
        """Scene brightness for auto-exposure: metered once without and once
        behind the sheet (a low-resolution pinhole view of the whole sensor);
        per frame the meter mixes them by the sensor fraction the sheet covers,
        so the exposure never depends on which window is rendered."""
        cam, cc = self.camera, self.cam_cfg
        scale = cc.ae_metering_width_px / cam.width
        mw, mh = cc.ae_metering_width_px, max(2, int(round(cam.height * scale)))
        meter_cam = pyrender.IntrinsicsCamera(cam.fx * scale, cam.fy * scale,
                                              (cam.cx + 0.5) * scale, (cam.cy + 0.5) * scale,
                                              znear=20.0, zfar=20000.0)
        node = self.scene.add(meter_cam, pose=cam.pose())
        self.scene.main_camera_node = node
        r = self.renderer
        size = (r.viewport_width, r.viewport_height)
        r.viewport_width, r.viewport_height = mw, mh
        try:
            clear = r.render(self.scene, flags=_FLAGS)[0]
            pose = np.eye(4)
            pose[:3, 3] = (0.0, cam.camera_y_mm + 60.0, cam.aim_z_mm)  # fills the view
            self.scene.set_pose(self.sheet_node, pose)
            covered = r.render(self.scene, flags=_FLAGS)[0]
        finally:
            r.viewport_width, r.viewport_height = size
            self.scene.set_pose(self.sheet_node, _AWAY)
            self.scene.main_camera_node = self.cam_node
            self.scene.remove_node(node)
        self.meter_clear = float(srgb8_to_linear16(clear).mean() / 65535)
        self.meter_sheet = float(srgb8_to_linear16(covered).mean() / 65535)

    def covered_fraction(self, t_cam: float) -> float:
        ext = self.sheet.extent(t_cam)
        if ext is None:
            return 0.0
        lo, hi = self.fov_s
        return float(max(0.0, min(hi, ext[1]) - max(lo, ext[0])) / (hi - lo))

    def gains(self, n_frames: int) -> np.ndarray:
        """Auto-exposure gain per frame: first-order lag towards target/meter."""
        cc = self.cam_cfg
        gain0 = min(cc.ae_target / max(self.meter_clear, 1e-6), cc.ae_max_gain)
        out = np.empty(n_frames)
        g = gain0
        alpha = 1 - np.exp(-1 / (cc.fps * cc.ae_time_constant_s))
        for i in range(n_frames):
            if cc.auto_exposure:
                f = self.covered_fraction(i / cc.fps + 0.5 * cc.exposure_s)
                meter = (1 - f) * self.meter_clear + f * self.meter_sheet
                target = min(cc.ae_target / max(meter, 1e-6), cc.ae_max_gain)
                g = g + alpha * (target - g) if i else gain0
            out[i] = g
        return out

    # ------------------------------------------------------------ frames
    def render_undistorted(self, t_cam: float) -> np.ndarray:
        """Linear 16-bit undistorted render (the plan's render window) at ``t_cam``."""
        t_sim = t_cam + self.cam_cfg.start_offset_s
        self.scene.remove_node(self.beam_node)
        self.beam_node = self.scene.add(self.beam.mesh(self.shapes, t_sim), name="beam")
        self.scene.set_pose(self.sheet_node, self._sheet_pose(t_cam))
        color = self.renderer.render(self.scene, flags=_FLAGS)[0]
        s = self.cam_cfg.supersample
        lin = srgb8_to_linear16(color)
        if s > 1:
            lin = cv2.resize(lin.astype(np.float32), (self.plan.render.width, self.plan.render.height),
                             interpolation=cv2.INTER_AREA)
            lin = np.rint(lin).astype(np.uint16)
        return lin

    def render_linear(self, t_cam: float) -> np.ndarray:
        """Linear radiance (float32, H x W x 3) of the window at camera time ``t_cam``."""
        return self.plan.apply(self.render_undistorted(t_cam)).astype(np.float32) * np.float32(1 / 65535)

    def _sheet_moving(self, t_frame: float) -> bool:
        ends = [self.sheet.extent(t_frame + dt) for dt in (0.0, self.cam_cfg.exposure_s)]
        return any(e is not None for e in ends) and ends[0] != ends[1]

    def frame_linear(self, index: int) -> np.ndarray:
        t_frame = index / self.cam_cfg.fps
        if self.cam_cfg.rolling_shutter_s == 0:
            # global shutter: every row sees the same sub-frames, so average the
            # undistorted renders first and remap once (remap is linear)
            times = self.sample_times
            if self._sheet_moving(t_frame):
                # the sheet sweeps ~100 px within an exposure: sample it finely
                # so its blur is smooth rather than a few ghosts
                m = max(len(times), 16)
                times = (np.arange(m) + 0.5) / m * self.cam_cfg.exposure_s
            acc = None
            for dt in times:
                img = self.render_undistorted(t_frame + dt).astype(np.uint32)
                acc = img if acc is None else acc + img
            n = len(times)
            mean = ((acc + n // 2) // n).astype(np.uint16)
            return self.plan.apply(mean).astype(np.float32) * np.float32(1 / 65535)
        acc = None
        for k, dt in enumerate(self.sample_times):
            w = self.row_weights[:, k]
            if not np.any(w):
                continue
            img = self.render_linear(t_frame + dt) * w[:, None, None]
            acc = img if acc is None else acc + img
        return acc

    def frame(self, index: int, gain: float) -> np.ndarray:
        """8-bit RGB frame ``index`` of the window."""
        return sensor_readout(self.frame_linear(index), gain, self.cam_cfg, seed=self.seed,
                              frame=index, window=self.window)

    def close(self) -> None:
        release_renderer(self.renderer)

    # ------------------------------------------------------------ truth
    def n_frames(self, duration_s: float | None = None) -> int:
        cc = self.cam_cfg
        duration = float(self.config.get("duration_s", 10.0) if duration_s is None else duration_s)
        n = int(np.floor(duration * cc.fps + 1e-9))
        if self.shapes is not None:
            span = self.shapes.time_s[-1] - cc.start_offset_s - self.sample_times.max()
            n = min(n, int(np.floor(span * cc.fps + 1e-9)) + 1)
        if n < 1:
            raise ValueError(f"no frame fits: duration_s={duration} and shapes up to "
                             f"{self.shapes.time_s[-1] if self.shapes else 0} s")
        return n

    def _material_points(self, u: np.ndarray, v: np.ndarray):
        rest = self.camera.backproject_to_plane_y(u, v, self.face_y_mm)
        return rest[..., 0], rest[..., 2]

    def point_truth(self, frames: np.ndarray, a: np.ndarray, z0: np.ndarray, rows_px: np.ndarray):
        """Exposure-averaged distorted pixel position (F, P, 2) and world position
        (F, P, 3) of material points (a across the thickness, z0 height) on the face."""
        times, _ = self.camera.sample_weights_for_rows(rows_px)   # (P, n)
        F, P = len(frames), a.size
        pix = np.zeros((F, P, 2))
        world = np.zeros((F, P, 3))
        groups = {}
        for p in range(P):
            groups.setdefault(tuple(np.round(times[p] * 1e9).astype(np.int64)), []).append(p)
        for key, members in groups.items():
            members = np.array(members)
            offs = np.array(key) * 1e-9
            for fi, f in enumerate(frames):
                for dt in offs:
                    t_sim = f / self.cam_cfg.fps + dt + self.cam_cfg.start_offset_s
                    pts = self.shapes.material_to_world(t_sim, a[members], self.face_y_mm,
                                                        z0[members])
                    world[fi, members] += pts / len(offs)
                    pix[fi, members] += self.camera.project(pts) / len(offs)
        return pix, world

    def occluded(self, frames: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per frame: any mask pixel behind the sheet during the exposure, and the
        mean covered fraction of the mask pixels."""
        crop = self.crop_window
        vv, uu = np.nonzero(self._mask_crop())
        s_mask = self._plane_coords(uu + crop.x, vv + crop.y, self.occ_cfg.distance_mm)
        flag = np.zeros(len(frames), np.int64)
        frac = np.zeros(len(frames))
        dts = np.unique(self.sample_times)
        for i, f in enumerate(frames):
            cov = np.zeros(s_mask.shape, bool)
            for dt in dts:
                cov |= self.sheet.covers(f / self.cam_cfg.fps + dt, s_mask)
            flag[i] = int(cov.any())
            frac[i] = cov.mean()
        return flag, frac

    def truth(self, n_frames: int) -> dict[str, np.ndarray]:
        frames = np.arange(n_frames)
        sc = self.scene_cfg
        rest = self.measure_px
        a, z0 = np.array([0.0]), np.array([sc.measure_height_mm])
        pix, world = self.point_truth(frames, a, z0, np.array([rest[1]]))
        flag, frac = self.occluded(frames)
        w = self.window
        vv, uu = np.nonzero(self.mask)
        pa, pz = self._material_points(uu + w.x, vv + w.y)
        ppix, _ = self.point_truth(frames, pa, pz, (vv + w.y).astype(float))
        rest_p = self.camera.project(np.stack([pa, np.full_like(pa, self.face_y_mm), pz], -1))
        return {
            "frame": frames, "time_s": frames / self.cam_cfg.fps,
            "dx_px": pix[:, 0, 0] - rest[0], "dy_px": pix[:, 0, 1] - rest[1],
            "dx_mm": world[:, 0, 0] - self.measure_point[0],
            "dy_mm": -(world[:, 0, 2] - self.measure_point[2]),
            "occluded": flag, "occluded_frac": frac,
            "poi_dx_px": (ppix[..., 0] - rest_p[None, :, 0]).astype(np.float32),
            "poi_dy_px": (ppix[..., 1] - rest_p[None, :, 1]).astype(np.float32),
            "poi_x_px": uu.astype(np.float32), "poi_y_px": vv.astype(np.float32),
        }

    def metadata(self) -> dict[str, Any]:
        cam = self.camera
        return {
            "mm_per_px": self.mm_per_px, "fps": self.cam_cfg.fps, "crop": self.window.as_dict(),
            "sensor": {"width": cam.width, "height": cam.height},
            "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                           "K": cam.K.tolist()},
            "distortion": {"k1": cam.k1, "k2": cam.k2, "p1": cam.p1, "p2": cam.p2,
                           "model": "Brown-Conrady, OpenCV order (k1, k2, p1, p2, k3=0)"},
            "camera_start_offset_s": self.cam_cfg.start_offset_s,
            "camera_position_mm": [0.0, cam.camera_y_mm, cam.aim_z_mm],
            "camera_looks_along": "+y (world x = image right, world z = image up)",
            "measurement_point_mm": self.measure_point.tolist(),
            "measurement_point_px": self.measure_px.tolist(),
            "exposure_s": self.cam_cfg.exposure_s,
            "rolling_shutter_s": self.cam_cfg.rolling_shutter_s,
            "sample_times_s": self.sample_times.tolist(),
            "truth_convention": ("truth.csv: displacement from the rest (undeformed) position of "
                                 "the measurement point on the beam's front face, averaged over "
                                 "the exposure sub-frames of its sensor row; dx_mm/dy_mm are "
                                 "world displacements (dx_mm along world x, dy_mm along -z, "
                                 "i.e. image-down sign); time_s = frame/fps on the camera clock "
                                 "(sim time = time_s + camera_start_offset_s); occluded = 1 when "
                                 "any mask pixel is behind the sheet during the exposure"),
            "meter": {"clear": self.meter_clear, "sheet": self.meter_sheet},
            "config": {"camera": asdict(self.cam_cfg), "scene": asdict(self.scene_cfg),
                       "occlusion": asdict(self.occ_cfg)},
        }


# ----------------------------------------------------------------- clips
def render_clip(config: dict[str, Any], shapes: BeamShapes, out_dir: str | Path, *,
                full_frame: bool = False, max_frames: int | None = None,
                progress: bool = True) -> dict[str, Any]:
    """Render the video and its ground truth into ``out_dir`` (see docs/formats.md)."""
    from refflow.io import atomic_path, config_hash, versions, write_json
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    codec = CodecConfig.from_config(config)
    t_start = time.perf_counter()
    r = BeamRenderer(config, shapes, full_frame=full_frame)
    try:
        n = r.n_frames()
        if max_frames is not None:
            n = min(n, int(max_frames))
        gains = r.gains(n)
        w = r.window
        t0 = time.perf_counter()
        truth = r.truth(n)
        t_truth = time.perf_counter() - t0
        video = out_dir / f"video{codec.suffix}"
        frame_times = []
        with atomic_path(video) as tmp:
            with VideoWriter(tmp, w.width, w.height, r.cam_cfg.fps, codec) as writer:
                it = range(n)
                if progress:
                    from tqdm import tqdm
                    it = tqdm(it, desc=f"render {w.width}x{w.height}", unit="frame")
                for i in it:
                    t1 = time.perf_counter()
                    writer.write(r.frame(i, gains[i]))
                    frame_times.append(time.perf_counter() - t1)
        with atomic_path(out_dir / "mask.png") as tmp:
            cv2.imwrite(str(tmp), r.mask)
        with atomic_path(out_dir / "truth.csv") as tmp:
            with tmp.open("w", newline="") as fh:
                wr = csv.writer(fh, lineterminator="\n")
                wr.writerow(["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded"])
                for i in range(n):
                    wr.writerow([i, f"{truth['time_s'][i]:.6f}", f"{truth['dx_px'][i]:.6f}",
                                 f"{truth['dy_px'][i]:.6f}", f"{truth['dx_mm'][i]:.6f}",
                                 f"{truth['dy_mm'][i]:.6f}", int(truth["occluded"][i])])
        with atomic_path(out_dir / "poi_truth.npz") as tmp:
            np.savez_compressed(tmp, dx_px=truth["poi_dx_px"], dy_px=truth["poi_dy_px"],
                                x_px=truth["poi_x_px"], y_px=truth["poi_y_px"],
                                occluded_frac=truth["occluded_frac"], gain=gains)
        meta = r.metadata()
        ft = np.array(frame_times) if frame_times else np.zeros(1)
        meta.update({
            "video": video.name, "frames": n, "codec": asdict(codec),
            "codec_bitrate_bps": codec.bitrate_bps(w.width, w.height, r.cam_cfg.fps),
            "ffmpeg": ffmpeg_version(), "seed": r.seed, "config_hash": config_hash(config),
            "versions": versions(), "n_pois": int(truth["poi_x_px"].size),
            "timings": {**r.timings, "truth_s": t_truth, "frames_s": float(ft.sum()),
                        "frame_median_s": float(np.median(ft)),
                        "fps_rendered": float(n / max(ft.sum(), 1e-9)),
                        "total_s": time.perf_counter() - t_start},
            "units": {"dx_px": "px", "dx_mm": "mm", "time_s": "s", "mm_per_px": "mm/px"},
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
    from sim.scene import _material
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
    board = scene.add(pyrender.Mesh([quad_primitive(corners, _material(tex, 0.9))]))
    fx, fy, cx, cy = cam.render_intrinsics(plan.render, 1)
    scene.add(pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=20.0, zfar=20000.0), pose=cam.pose())
    renderer = pyrender.OffscreenRenderer(plan.render.width, plan.render.height)
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
def render_figures(config: dict[str, Any], shapes: BeamShapes, out_dir: str | Path) -> list[Path]:
    """render_full.png (4K, downscaled to 1920 wide), render_crop.png, render_occluded.png."""
    from refflow.io import atomic_path
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written = []

    def save(name, rgb):
        with atomic_path(out_dir / name) as tmp:
            cv2.imwrite(str(tmp), cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
        written.append(out_dir / name)

    frame = 15  # a quarter period into the 4 Hz swing
    full = BeamRenderer(config, shapes, full_frame=True)
    try:
        img = full.frame(frame, full.gains(frame + 1)[frame])
        c = full.crop_window
        img = img.copy()
        cv2.rectangle(img, (c.x, c.y), (c.x + c.width, c.y + c.height), (255, 200, 0), 4)
        save("render_full.png", cv2.resize(img, (1920, 1080), interpolation=cv2.INTER_AREA))
    finally:
        full.close()
    crop = BeamRenderer(config, shapes)
    try:
        save("render_crop.png", crop.frame(frame, crop.gains(frame + 1)[frame]))
    finally:
        crop.close()
    occ = OcclusionConfig(enabled=True, start_s=0.2, duration_s=1.0)
    occr = BeamRenderer(config, shapes, occlusion=occ)
    try:
        f = int(0.6 * occr.cam_cfg.fps)
        save("render_occluded.png", occr.frame(f, occr.gains(f + 1)[f]))
        f2 = int(0.185 * occr.cam_cfg.fps)  # the leading edge crosses the crop
        save("render_occluding.png", occr.frame(f2, occr.gains(f2 + 1)[f2]))
    finally:
        occr.close()
    return written
