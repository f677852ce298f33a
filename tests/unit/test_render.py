"""Fast checks of the synthetic phone camera (sim.camera, sim.render, sim.occlusion)."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from sim.camera import CameraConfig, CameraModel, Window, srgb8_to_linear16
from sim.occlusion import OcclusionConfig
from sim.render import BeamRenderer, render_clip
from sim.scene import (
    BeamShapes,
    SceneConfig,
    pyrender,
    quad_primitive,
    release_renderer,
    synthetic_shapes,
)

# A reduced sensor (same optics scaled down) keeps full frames cheap; crops are
# windows of it, exactly as on the 4K sensor.
SMALL = {"width_px": 640, "height_px": 360, "fx_px": 700.0, "crop_width_px": 200,
         "crop_height_px": 100, "aim_z_mm": 700.0, "k1": 0.06, "k2": -0.12, "p1": 2e-4, "p2": -1e-4}


@pytest.fixture(scope="module")
def shapes() -> BeamShapes:
    return BeamShapes(**synthetic_shapes(duration_s=1.2))


def _small_config(seed=5, **camera):
    return {"seed": seed, "duration_s": 1.0, "camera": {**SMALL, **camera}}


def test_undistort_inverts_distort_exactly():
    cam = CameraModel(CameraConfig(), camera_y_mm=-1050.0)
    x, y = np.meshgrid(np.linspace(-0.75, 0.75, 41), np.linspace(-0.42, 0.42, 23))
    xd, yd = cam.distort(x, y)
    xu, yu = cam.undistort(xd, yd)
    assert np.max(np.abs(xu - x)) < 1e-13 and np.max(np.abs(yu - y)) < 1e-13
    # sanity: the corners move by tens of pixels, as a phone lens would
    assert np.max(np.hypot(xd - x, yd - y)) * cam.fx > 10


def _disc_texture(size=512, radius=0.3):
    yy, xx = (np.mgrid[:size, :size] + 0.5) / size - 0.5
    img = (np.hypot(xx, yy) <= radius).astype(np.float64)
    return np.repeat((img * 255).astype(np.uint8)[..., None], 3, 2)


@pytest.mark.parametrize("target", [(1919.5, 1079.5), (300.0, 250.0), (3500.0, 1900.0),
                                    (1200.0, 377.0)])
def test_marker_lands_on_predicted_distorted_pixel(target):
    """A disc at a known 3D point: its intensity centroid in the rendered,
    distorted image matches the camera model within 0.05 px."""
    from sim.scene import _material
    cam = CameraModel(CameraConfig(), camera_y_mm=-1050.0)
    depth = 1000.0
    centre = cam.backproject_to_plane_y(np.array(target[0]), np.array(target[1]), -50.0)
    assert abs(centre[1] - (-50.0)) < 1e-9 and depth > 0
    half = 10.0  # 20 mm quad, disc radius 6 mm = ~17 px
    c = centre
    corners = np.array([[c[0] - half, c[1], c[2] - half], [c[0] + half, c[1], c[2] - half],
                        [c[0] + half, c[1], c[2] + half], [c[0] - half, c[1], c[2] + half]])
    scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.ones(3))
    scene.add(pyrender.Mesh([quad_primitive(corners, _material(_disc_texture()))]))
    u, v = cam.project(c)
    window = Window(int(round(u)) - 40, int(round(v)) - 40, 80, 80)
    plan = cam.remap_plan(window)
    fx, fy, cx, cy = cam.render_intrinsics(plan.render)
    scene.add(pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=20.0, zfar=5000.0), pose=cam.pose())
    r = pyrender.OffscreenRenderer(plan.render.width, plan.render.height)
    try:
        color = r.render(scene, flags=pyrender.RenderFlags.FLAT)[0]
    finally:
        release_renderer(r)
    img = plan.apply(srgb8_to_linear16(color)).astype(np.float64)[..., 0]
    vv, uu = np.mgrid[:img.shape[0], :img.shape[1]]
    w = img / img.sum()
    measured = np.array([(w * uu).sum() + window.x, (w * vv).sum() + window.y])
    # expected centroid: the disc's points projected (area-weighted, exact under perspective)
    rr, aa = np.meshgrid(np.sqrt((np.arange(200) + 0.5) / 200) * 6.0, np.linspace(0, 2 * np.pi, 400,
                                                                                  endpoint=False))
    pts = np.stack([c[0] + rr * np.cos(aa), np.full_like(rr, c[1]), c[2] + rr * np.sin(aa)], -1)
    expected = cam.project(pts).reshape(-1, 2).mean(0)
    assert np.hypot(*(measured - expected)) < 0.05, (measured, expected)
    # and the camera model agrees with OpenCV's projectPoints
    import cv2
    pc = cam.world_to_camera(c[None])
    cv, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.allclose(cv.reshape(2), (u, v), atol=1e-6)


@pytest.fixture(scope="module")
def small_pair(shapes):
    cfg = _small_config()
    cfg["occlusion"] = {"enabled": True, "start_s": 0.1, "duration_s": 0.2, "transit_s": 0.05}
    full = BeamRenderer(cfg, shapes, full_frame=True)
    crop = BeamRenderer(cfg, shapes)
    yield cfg, full, crop
    full.close()
    crop.close()


def test_crop_pixels_equal_full_frame_pixels(small_pair):
    cfg, full, crop = small_pair
    c = crop.window
    assert (full.window.width, full.window.height) == (640, 360)
    gains = full.gains(12)
    assert np.array_equal(gains, crop.gains(12))  # auto-exposure never depends on the window
    for frame in (0, 7, 11):  # 7, 11: the sheet is sweeping in / covering
        a = full.frame(frame, gains[frame])[c.y:c.y + c.height, c.x:c.x + c.width]
        b = crop.frame(frame, gains[frame])
        diff = np.abs(a.astype(int) - b.astype(int))
        # The maps, noise, exposure and sub-frames are bit-identical by
        # construction; the GL projection differs by the principal-point shift,
        # so Mesa's float rounding moves a rare edge sample (1 LSB).
        assert diff.max() <= 1 and (diff > 0).mean() < 1e-3, (frame, int((diff > 0).sum()))
    m_full = full.mask[c.y:c.y + c.height, c.x:c.x + c.width]
    assert np.array_equal(m_full, crop.mask)


def test_same_seed_same_bytes(shapes):
    a = BeamRenderer(_small_config(seed=11), shapes)
    try:
        f1 = [a.frame(i, 0.5) for i in (0, 3)]
    finally:
        a.close()
    b = BeamRenderer(_small_config(seed=11), shapes)
    c = BeamRenderer(_small_config(seed=12), shapes)
    try:
        f2 = [b.frame(i, 0.5) for i in (0, 3)]
        f3 = c.frame(0, 0.5)
    finally:
        b.close()
        c.close()
    assert all(x.tobytes() == y.tobytes() for x, y in zip(f1, f2, strict=True))
    assert f3.tobytes() != f1[0].tobytes()  # the noise follows the seed


def test_truth_matches_beam_projection_and_image(shapes):
    """truth.csv's numbers are the projection of the simulated beam, and the
    rendered beam edge sits where the truth says (noise off, 4K optics)."""
    cfg = {"seed": 1, "camera": {"crop_width_px": 120, "crop_height_px": 240, "noise": False,
                                 "motion_blur_subframes": 2},
           "scene": {"background_contrast": 0.0, "texture_contrast": 0.0}}  # a clean edge profile
    r = BeamRenderer(cfg, shapes)
    try:
        truth = r.truth(12)
        t = np.arange(12) / 60 + np.array(r.sample_times)[:, None]
        x_true = np.array([shapes.at(tt, np.array([r.scene_cfg.measure_height_mm]))[0][0]
                           for tt in t.ravel()]).reshape(t.shape).mean(0)
        assert np.allclose(truth["dx_mm"], x_true, atol=1e-9)
        # 0.357 mm/px: dx_px ~ dx_mm / mm_per_px (the lens changes it by < 1 %)
        assert np.allclose(truth["dx_px"], truth["dx_mm"] / r.mm_per_px, rtol=0.01, atol=1e-3)
        # the face in the image, on a row above the logo (the logo sits 100 mm
        # further back and so moves 9 % fewer pixels: keep it out)
        v_row = r.measure_px[1] - 100
        row = int(round(v_row)) - r.window.y
        a, z0 = r._material_points(np.array([r.measure_px[0]]), np.array([float(round(v_row))]))
        pix, _ = r.point_truth(np.array([0, 6, 11]), a, z0, np.array([round(v_row)]))
        expected = pix[:, 0, 0] - pix[0, 0, 0]
        cols = np.arange(r.window.width)
        centres = []
        for f, dx in zip((0, 6, 11), pix[:, 0, 0], strict=True):
            img = r.frame_linear(f)[row].mean(1)
            sel = np.abs(cols - (dx - r.window.x)) <= 12
            base = np.interp(cols[sel], [cols[sel][0], cols[sel][-1]],
                             [img[sel][:3].mean(), img[sel][-3:].mean()])
            w = np.clip(img[sel] - base, 0, None)
            centres.append((w * cols[sel]).sum() / w.sum())
        measured = np.array(centres) + r.window.x
        # 4x MSAA quantises each vertical edge to 1/4 px coverage steps: the
        # centroid of a 14 px face is good to ~0.1 px
        assert np.max(np.abs(measured - pix[:, 0, 0])) < 0.15, (measured, pix[:, 0, 0])
        assert np.max(np.abs(expected)) > 3  # the beam really moved
    finally:
        r.close()


def test_occlusion_covers_exactly_the_configured_frames(small_pair):
    cfg, full, crop = small_pair
    flags, frac = crop.occluded(np.arange(30))
    fps = crop.cam_cfg.fps
    # frames 6..17 lie within [0.1, 0.3) s: covered; frames outside: clear
    expected = ((np.arange(30) / fps >= 0.1 - 1e-9) & (np.arange(30) / fps < 0.3 - 1e-9)).astype(int)
    assert np.array_equal(flags, expected), (flags, expected)
    assert np.all(frac[expected == 1] == 1.0)
    # and the pixels agree: under the sheet the mask region is bright and flat
    gains = crop.gains(13)
    covered = crop.frame_linear(12)[crop.mask > 0]
    clear = crop.frame_linear(2)[crop.mask > 0]
    assert covered.mean() > 1.5 * clear.mean() and covered.std() < 0.05
    assert gains[12] < gains[2]  # auto-exposure backs off while the white sheet fills the view


def test_partial_occlusion_covers_half(shapes):
    cfg = _small_config()
    occ = OcclusionConfig(enabled=True, start_s=0.1, duration_s=0.2, partial=True,
                          direction="+z")
    r = BeamRenderer(cfg, shapes, occlusion=occ)
    try:
        flags, frac = r.occluded(np.arange(24))
        assert flags[10] == 1 and 0.3 < frac[10] < 0.7
        assert flags[0] == 0 and flags[23] == 0
    finally:
        r.close()


@pytest.mark.parametrize("section,key,value", [("camera", "fps", -1), ("camera", "k1", "big"),
                                               ("scene", "texture_contrast", 2.0),
                                               ("occlusion", "direction", "sideways"),
                                               ("codec", "name", "vp9"), ("camera", "bogus", 1)])
def test_bad_config_names_key_and_value(section, key, value):
    from sim.codec import CodecConfig
    cls = {"camera": CameraConfig, "scene": SceneConfig, "occlusion": OcclusionConfig,
           "codec": CodecConfig}[section]
    with pytest.raises(ValueError, match=key):
        cls.from_config({section: {key: value}})


def test_render_clip_writes_documented_files(shapes, tmp_path):
    cfg = _small_config()
    cfg["codec"] = {"name": "ffv1"}
    meta = render_clip(cfg, shapes, tmp_path, max_frames=4, progress=False)
    assert {p.name for p in tmp_path.iterdir()} == {"video.mkv", "mask.png", "truth.csv",
                                                     "poi_truth.npz", "render.json"}
    with (tmp_path / "truth.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded"]
    assert len(rows) == 4
    import cv2
    mask = cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (100, 200) and mask.dtype == np.uint8 and mask.max() == 255
    poi = np.load(tmp_path / "poi_truth.npz")
    assert poi["dx_px"].shape == (4, int((mask > 0).sum()))
    assert meta["crop"] == {"x": meta["crop"]["x"], "y": meta["crop"]["y"], "width": 200,
                            "height": 100}
    # FFV1 is lossless: the decoded frame equals the raw frame
    from sim.codec import read_video_frames
    decoded = next(iter(read_video_frames(tmp_path / "video.mkv")))
    r = BeamRenderer(cfg, shapes)
    try:
        raw = r.frame(0, r.gains(1)[0])
    finally:
        r.close()
    assert np.array_equal(decoded, raw)


def test_sensor_kernel_matches_numpy_reference():
    from sim.camera import _encode_lut, sensor_readout, standard_normal_at
    cfg = CameraConfig()
    w = Window(100, 50, 64, 32)
    lin = np.random.default_rng(0).random((32, 64, 3)).astype(np.float32)
    out = sensor_readout(lin, 0.7, cfg, seed=3, frame=5, window=w)
    sig = lin * np.float32(0.7)
    sigma = np.sqrt(np.maximum(sig, 0) * np.float32(cfg.full_well_e)
                    + np.float32(cfg.read_noise_e ** 2)) / np.float32(cfg.full_well_e)
    sig = sig + sigma * standard_normal_at(3, 5, w, cfg.width_px, 3)
    ref = _encode_lut(cfg.gamma)[np.rint(np.clip(sig, 0, 1) * np.float32(2 ** 20 - 1)).astype(int)]
    assert np.array_equal(out, ref)
    noise = standard_normal_at(3, 5, Window(0, 0, 256, 256), cfg.width_px, 3)
    assert abs(noise.mean()) < 0.01 and abs(noise.std() - 1) < 0.01


def test_rolling_shutter_rows_expose_later_and_crop_matches(shapes):
    cfg = _small_config(rolling_shutter_s=0.012)
    full = BeamRenderer(cfg, shapes, full_frame=True)
    crop = BeamRenderer(cfg, shapes)
    try:
        times, weights = full.sample_times, full.row_weights
        assert np.allclose(weights.sum(1), 1.0)
        first_time = (weights > 0).argmax(1)
        assert np.all(np.diff(first_time) >= 0) and first_time[-1] > first_time[0]
        c = crop.window
        a = full.frame(4, 0.5)[c.y:c.y + c.height, c.x:c.x + c.width]
        b = crop.frame(4, 0.5)
        diff = np.abs(a.astype(int) - b.astype(int))
        assert diff.max() <= 1 and (diff > 0).mean() < 1e-3
        assert np.ptp(times) > 0.012  # the sub-frames span the read-out
    finally:
        full.close()
        crop.close()
