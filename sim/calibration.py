"""Checkerboard images for the camera calibration, through the same camera, lens and sensor
as the video (``python -m sim render calibration``), with the boards' true poses.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.camera import CameraConfig, CameraModel, sensor_readout, srgb8_to_linear16
from sim.render import RENDER_FLAGS
from sim.scene import SceneConfig, offscreen_renderer, pyrender, quad_primitive, release_renderer
from sim.view import config_seed


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
