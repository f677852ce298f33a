"""The figures of the synthetic video: a frame of motion in full and cropped, and the sheet
covering the crop (``python -m sim render figures``).
"""

from __future__ import annotations

from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from sim.occlusion import OcclusionConfig
from sim.render import BeamRenderer
from sim.scene import BeamShapes


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
