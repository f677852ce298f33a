"""Render a clip: the video, the masks a user would paint, the scale and recording sidecars,
the ground truth and ``render.json`` (see docs/formats.md), each written atomically.
"""

from __future__ import annotations

import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.camera import AutoExposure
from sim.codec import CodecConfig, VideoWriter, ffmpeg_version
from sim.masks import background_mask
from sim.render import BeamRenderer
from sim.scene import BeamShapes
from sim.truth import TRUTH_CONVENTION
from sim.truth_io import CSV_COLUMNS, TruthWriter


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
