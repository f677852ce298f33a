"""Render the frames of the synthetic phone video.

One :class:`BeamRenderer` per output window (the default crop around the measurement
point, or the full sensor; a :class:`sim.view.View`). It composes the POI mask and its
POIs (``sim.masks``), the sheet's path, the sub-frames (``sim.subframes``) and the ground
truth (``sim.truth``), and owns the pyrender scene. A frame (:meth:`BeamRenderer.frame_linear`)
averages undistorted pyrender renders at the sub-frames of its exposure with each sensor
row's weights (:class:`sim.camera.SubframeSampling`), remaps them through the exact lens
model and scales each row by the light's relative intensity over its exposure;
:meth:`BeamRenderer.frame` adds the sensor (noise, the auto-exposure's analog gain, gamma,
8 bits; ``sim.camera``).

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
from sim.masks import Pois, background_mask, poi_mask
from sim.occlusion import OcclusionConfig
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
from sim.subframes import SubframeTable
from sim.truth import TRUTH_CONVENTION, GroundTruth
from sim.truth_io import CSV_COLUMNS, TruthWriter
from sim.view import View, config_seed

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


# ----------------------------------------------------------------- clips
def clip_metadata(renderer: BeamRenderer) -> dict[str, Any]:
    """The description of a clip's camera, truth and disturbances in its ``render.json``."""
    view = renderer.view
    cam, cc = view.camera, view.cam_cfg
    return {
        "mm_per_px": view.mm_per_px, "fps": cc.fps, "crop": view.window.as_dict(),
        "sensor": {"width": cam.width, "height": cam.height},
        "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "K": cam.K.tolist()},
        "distortion": {"k1": cam.k1, "k2": cam.k2, "p1": cam.p1, "p2": cam.p2,
                       "model": "Brown-Conrady, OpenCV order (k1, k2, p1, p2, k3=0)"},
        "camera_start_offset_s": cc.start_offset_s,
        "camera_position_mm": [0.0, cam.camera_y_mm, cam.aim_z_mm],
        "camera_looks_along": "+y (world x = image right, world z = image up)",
        "measurement_point_mm": view.measure_point.tolist(),
        "measurement_point_px": view.measure_px.tolist(),
        "exposure_s": cc.exposure_s,
        "rolling_shutter_s": cc.rolling_shutter_s,
        "subframes": {"camera": cc.motion_blur_subframes,
                      "sheet_moving": view.occ_cfg.motion_blur_subframes,
                      "rule": "bins of exposure/n on a grid shared by all rows, rendered at "
                              "their centres; a row weighs each bin by its exposure overlap"},
        "truth_columns": list(CSV_COLUMNS),
        "truth_convention": TRUTH_CONVENTION,
        "disturbances": {"camera_shake": cc.shake, "camera_drift": cc.drift,
                         "flicker": view.scene_cfg.flicker, "clouds": view.scene_cfg.clouds,
                         "light_drift": view.scene_cfg.light_drift},
        "distractors_mm": ([] if renderer.distractors is None
                           else renderer.distractors[0].tolist()),
        "config": {"camera": asdict(cc), "scene": asdict(view.scene_cfg),
                   "occlusion": asdict(view.occ_cfg)},
    }


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
    view = r.view
    try:
        n = view.n_frames()
        if max_frames is not None:
            n = min(n, int(max_frames))
        w = view.window
        video = out_dir / f"video{codec.suffix}"
        ae = AutoExposure(view.cam_cfg)
        spent = {"meter_s": 0.0, "truth_s": 0.0}
        frame_times = []
        outputs = (video, out_dir / "mask.png", out_dir / "background.png", out_dir / "scale.json",
                   out_dir / "recording.json", out_dir / "poi_truth.npz", out_dir / "truth.csv")
        with atomic_paths(*outputs) as (tmp_video, tmp_mask, tmp_background, tmp_scale, tmp_recording,
                                        tmp_npz, tmp_csv):
            with VideoWriter(tmp_video, w.width, w.height, view.cam_cfg.fps, codec) as writer, \
                    TruthWriter(tmp_csv, tmp_npz, poi_x_px=r.pois.window_px[:, 0],
                                poi_y_px=r.pois.window_px[:, 1]) as truth_out:
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
                    truth_out.write(r.truth.frame(i), gain)
                    spent["meter_s"] += t1 - t0
                    spent["truth_s"] += time.perf_counter() - t2
                    frame_times.append(t2 - t1)
            cv2.imwrite(str(tmp_mask), r.mask)
            cv2.imwrite(str(tmp_background), background_mask(view))
            # the scale as the paper's user takes it (refflow track --scale-file reads it)
            tmp_scale.write_text(json_text({
                "known_length_mm": view.scene_cfg.beam_thickness_mm,
                "between_px": [round(float(v), 4) for v in r.truth.scale_points()],
                "what": "the beam's front-face edges at the measurement height on frame 0 (raw video "
                        "pixels, exact); their distance is the beam thickness"}))
            # what the recording itself tells: the video is this window of the sensor
            # (refflow track --video-origin reads it to use the full-sensor calibration)
            tmp_recording.write_text(json_text({
                "video_origin_px": [w.x, w.y], "video_size_px": [w.width, w.height],
                "sensor_size_px": [view.camera.width, view.camera.height], "fps": view.cam_cfg.fps}))
        meta = clip_metadata(r)
        ft = np.array(frame_times) if frame_times else np.zeros(1)
        meta.update({
            "video": video.name, "frames": n, "codec": asdict(codec),
            "codec_bitrate_bps": codec.bitrate_bps(w.width, w.height, view.cam_cfg.fps),
            "ffmpeg": ffmpeg_version(), "seed": view.seed, "config_hash": config_hash(config),
            "versions": versions(), "n_pois": r.pois.count,
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
    seed = config_seed(config)
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
            color = renderer.render(scene, flags=RENDER_FLAGS)[0]
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
    view = renderer.view
    cc, occ = view.cam_cfg, view.occ_cfg
    mid = 0.5 * cc.exposure_s + float(view.camera.row_times(np.rint(view.measure_px[1])))
    t = np.arange(n_frames) / cc.fps
    x = np.array([renderer.truth.beam_points(ti + mid)[0][0] for ti in t])
    speed = np.abs(np.gradient(x, t)) if n_frames > 1 else np.zeros(1)
    sheet_free = np.array([not renderer.sheet.present_during(ti, ti + 1 / cc.fps) for ti in t])
    score = np.where(sheet_free, np.abs(x - view.measure_point[0]) * speed, -1.0)
    frames = {"motion": int(np.argmax(score))}
    first, last = occ.start_s, occ.start_s + occ.duration_s
    if occ.enabled and last <= (n_frames - 1) / cc.fps:
        frames["occluded"] = int(np.floor(0.5 * (first + last) * cc.fps))
        crop = view.crop_window
        vv, uu = np.mgrid[crop.y:crop.y + crop.height:8, crop.x:crop.x + crop.width:8]
        rays = view.camera.pixel_rays(uu.astype(float), vv.astype(float))
        entry = np.arange(max(0, int((first - occ.transit_s) * cc.fps)), int(np.ceil(first * cc.fps)))
        share = [renderer.sheet.covers(i / cc.fps + mid, *view.sheet_coords(rays)).mean()
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
        n = crop.view.n_frames()
        frames = figure_frames(crop, n)
        if "occluded" not in frames:
            raise ValueError(f"the occlusion ({occ['start_s']} s + {occ['duration_s']} s) does "
                             f"not fit the {n} frames the shapes allow: adjust occlusion.start_s "
                             f"or pass longer shapes")
        # the figures of the beam in motion show it without the sheet
        clear = {**config, "occlusion": {**occ, "enabled": False}}
        full = BeamRenderer(clear, shapes, full_frame=True)
        try:
            save("render_full.png", full, frames["motion"], box=full.view.crop_window, size=(1920, 1080))
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
