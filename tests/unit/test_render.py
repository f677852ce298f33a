"""Fast checks of the synthetic phone camera (sim.camera, sim.view, sim.masks, sim.render,
sim.truth, sim.clip, sim.figures, sim.occlusion, sim.disturbance, sim.truth_io)."""

from __future__ import annotations

import csv
import dataclasses
import json

import cv2
import numpy as np
import pytest

from sim.camera import (
    AutoExposure,
    CameraConfig,
    CameraModel,
    Window,
    sensor_readout,
    srgb8_to_linear16,
)
from sim.clip import render_clip
from sim.figures import figure_frames
from sim.masks import face_rows, region_heights, regions_mask
from sim.occlusion import OcclusionConfig
from sim.render import BeamRenderer
from sim.scene import (
    GEOMETRY,
    BeamMesh,
    BeamShapes,
    SceneConfig,
    logo_texture,
    material,
    offscreen_renderer,
    pyrender,
    quad_primitive,
    release_renderer,
    synthetic_shapes,
)
from sim.view import View

# A reduced sensor (same optics scaled down) keeps full frames cheap; crops are
# windows of it, exactly as on the 4K sensor.
SMALL = {"width_px": 640, "height_px": 360, "fx_px": 700.0, "crop_width_px": 200,
         "crop_height_px": 100, "aim_z_mm": 700.0, "k1": 0.06, "k2": -0.12, "p1": 2e-4, "p2": -1e-4}
# the paper's optics (4K at 1 m, 2.8 px/mm) through a small crop
PAPER_CROP = {"crop_width_px": 160, "crop_height_px": 240}
CLEAN_SCENE = {"background_contrast": 0.0, "texture_contrast": 0.0, "logo": False}


@pytest.fixture(scope="module")
def shapes() -> BeamShapes:
    return BeamShapes(**synthetic_shapes(duration_s=1.2))


def _small_config(seed=5, **camera):
    return {"seed": seed, "duration_s": 1.0, "camera": {**SMALL, **camera}}


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)


# ----------------------------------------------------------------- geometry
def test_undistort_inverts_distort_exactly():
    cam = CameraModel(CameraConfig(), camera_y_mm=-1050.0)
    x, y = np.meshgrid(np.linspace(-0.75, 0.75, 41), np.linspace(-0.42, 0.42, 23))
    xd, yd = cam.distort(x, y)
    xu, yu = cam.undistort(xd, yd)
    assert np.max(np.abs(xu - x)) < 1e-13 and np.max(np.abs(yu - y)) < 1e-13
    # sanity: the corners move by tens of pixels, as a phone lens would
    assert np.max(np.hypot(xd - x, yd - y)) * cam.fx > 10
    # a pixel gets the same bits alone as inside a larger array (crop = full frame)
    one = cam.undistort(xd[5:6, 7:8], yd[5:6, 7:8])
    assert one[0][0, 0] == xu[5, 7] and one[1][0, 0] == yu[5, 7]


def _render_quad(cam: CameraModel, corners: np.ndarray, texture: np.ndarray, window: Window):
    """Linear image (float64, H x W x 3) of one textured quad through the lens."""
    scene = pyrender.Scene(bg_color=np.zeros(4), ambient_light=np.ones(3))
    scene.add(pyrender.Mesh([quad_primitive(corners, material(texture))]))
    plan = cam.remap_plan(window)
    fx, fy, cx, cy = cam.render_intrinsics(plan.render)
    scene.add(pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear=20.0, zfar=5000.0), pose=cam.pose())
    r = offscreen_renderer(plan.render.width, plan.render.height)
    try:
        color = r.render(scene, flags=pyrender.RenderFlags.FLAT)[0]
    finally:
        release_renderer(r)
    return plan.apply(srgb8_to_linear16(color)).astype(np.float64) / 65535


def _square(centre: np.ndarray, half: float) -> np.ndarray:
    c = centre
    return np.array([[c[0] - half, c[1], c[2] - half], [c[0] + half, c[1], c[2] - half],
                     [c[0] + half, c[1], c[2] + half], [c[0] - half, c[1], c[2] + half]])


def _disc_texture(size=512, radius=0.3):
    yy, xx = (np.mgrid[:size, :size] + 0.5) / size - 0.5
    img = (np.hypot(xx, yy) <= radius).astype(np.float64)
    return np.repeat((img * 255).astype(np.uint8)[..., None], 3, 2)


@pytest.mark.parametrize("target", [(1919.5, 1079.5), (300.0, 250.0), (3500.0, 1900.0),
                                    (1200.0, 377.0)])
def test_marker_lands_on_predicted_distorted_pixel(target):
    """A disc at a known 3D point: its intensity centroid in the rendered,
    distorted image matches the camera model within 0.05 px."""
    cam = CameraModel(CameraConfig(), camera_y_mm=-1050.0)
    c = cam.backproject_to_plane_y(np.array(target[0]), np.array(target[1]), -50.0)
    assert abs(c[1] - (-50.0)) < 1e-9
    u, v = cam.project(c)
    window = Window(int(round(u)) - 40, int(round(v)) - 40, 80, 80)
    img = _render_quad(cam, _square(c, 10.0), _disc_texture(), window)[..., 0]  # r = 6 mm, 17 px
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
    pc = cam.world_to_camera(c[None])
    cv, _ = cv2.projectPoints(pc, np.zeros(3), np.zeros(3), cam.K, cam.dist)
    assert np.allclose(cv.reshape(2), (u, v), atol=1e-6)


def _quadrant_texture(size=256):
    """Red top-left, green top-right, blue bottom-left, white bottom-right."""
    img = np.zeros((size, size, 3), np.uint8)
    h = size // 2
    img[:h, :h] = (255, 0, 0)
    img[:h, h:] = (0, 255, 0)
    img[h:, :h] = (0, 0, 255)
    img[h:, h:] = (255, 255, 255)
    return img


def _corner_colours(img: np.ndarray) -> dict[str, int]:
    """Dominant channel (0 r, 1 g, 2 b, 3 white) of the image's four quadrants."""
    h, w = img.shape[0] // 2, img.shape[1] // 2
    out = {}
    for name, q in {"tl": img[:h, :w], "tr": img[:h, w:], "bl": img[h:, :w], "br": img[h:, w:]}.items():
        mean = q.reshape(-1, 3).mean(0)
        out[name] = 3 if mean.min() > 0.5 * mean.max() else int(np.argmax(mean))
    return out


def test_textures_render_upright_on_quads_and_the_logo():
    """pyrender flips textures on upload: an asymmetric texture on a quad and on the
    beam's logo plate must show its top-left corner at the image's top-left."""
    cam = CameraModel(CameraConfig(), camera_y_mm=-1050.0)
    c = cam.backproject_to_plane_y(np.array(1919.5), np.array(700.0), 50.5)
    u, v = cam.project(c)
    window = Window(int(round(u)) - 20, int(round(v)) - 20, 40, 40)  # inside the 40 mm quad
    img = _render_quad(cam, _square(c, 20.0), _quadrant_texture(), window)
    assert _corner_colours(img) == {"tl": 0, "tr": 1, "bl": 2, "br": 3}
    # the logo plate, as the beam carries it
    sc = SceneConfig(measure_height_mm=750.0)
    beam = BeamMesh(sc, None, material(_quadrant_texture()), logo_height_mm=c[2])
    corners = beam.logo_primitive(None, 0.0).positions
    assert np.allclose(corners[0], (c[0] - 20, 50.5, c[2] - 20), atol=0.01)  # bottom-left first
    img = _render_quad(cam, corners, _quadrant_texture(), window)
    assert _corner_colours(img) == {"tl": 0, "tr": 1, "bl": 2, "br": 3}
    # the logo's letters read left to right: "REF" sits in the left part of the plate
    logo = logo_texture(128)
    assert (logo[:, :64] < 40).sum() > (logo[:, 64:] < 40).sum()


def test_numpy2_shim_lets_pyrender_compute_mesh_bounds():
    """pyrender 0.1.45's Mesh.bounds reads np.infty (gone in NumPy 2)."""
    corners = _square(np.zeros(3), 5.0)
    mesh = pyrender.Mesh([quad_primitive(corners, material(_disc_texture(8)))])
    assert np.allclose(mesh.bounds, [[-5, 0, -5], [5, 0, 5]])
    assert np.infty == np.inf  # noqa: NPY201 (the alias the shim restores)


def test_released_or_collected_renderers_free_their_context_and_spare_the_others():
    """pyrender's own clean-up eglTerminates the shared display (every other
    renderer's context dies with it); ours destroys one context, whether
    released explicitly or dropped to the garbage collector."""
    import gc
    scene = pyrender.Scene(bg_color=(0.2, 0.4, 0.6, 1.0))
    scene.add(pyrender.IntrinsicsCamera(30.0, 30.0, 16.0, 8.0))
    keep = offscreen_renderer(32, 16)
    try:
        before = keep.render(scene)[0].copy()
        red = pyrender.Scene(bg_color=(1.0, 0, 0, 1.0))
        red.add(pyrender.IntrinsicsCamera(30.0, 30.0, 32.0, 32.0))
        for i in range(6):
            other = offscreen_renderer(64, 64)
            platform = other._platform
            assert other.render(red)[0][5, 5, 0] == 255
            if i % 2:
                release_renderer(other)
                assert other._platform is None and platform._egl_context is None
                release_renderer(other)  # twice is harmless
            del other
            gc.collect()
            assert platform._egl_context is None  # destroyed, not kept for the process
        assert np.array_equal(keep.render(scene)[0], before)  # the survivor still renders
    finally:
        release_renderer(keep)


# ----------------------------------------------------------------- crop = full frame
@pytest.fixture(scope="module")
def small_pair(shapes):
    cfg = _small_config()
    cfg["occlusion"] = {"enabled": True, "start_s": 0.1, "duration_s": 0.2, "transit_s": 0.05}
    full = BeamRenderer(cfg, shapes, full_frame=True)
    crop = BeamRenderer(cfg, shapes)
    yield cfg, full, crop
    full.close()
    crop.close()


def _assert_crop_matches(full: BeamRenderer, crop: BeamRenderer, frames, gains) -> None:
    """Crop pixels equal the full frame's, but for rare edge pixels.

    The remap maps (fixed point of the global position), the noise (a hash of
    the global pixel), the sub-frame weights (of the global row), the
    auto-exposure gain (a full-view meter) and the truth are bit-identical by
    construction. Not so Mesa's rasterisation: the crop renders another
    viewport (principal point shifted by the window's offset), so vertex
    positions and interpolants go through different float32 arithmetic, and an
    MSAA sample that lies within ~1e-4 px of an edge can fall on the other
    side. That pixel then differs by one sample of one sub-frame (1/16 of the
    edge's contrast: up to ~8 LSB at the logo's black-on-white edges, 1 LSB at
    the beam's); it happens to ~1e-4 of the values. Rendering the full frame's
    crop region through the crop's viewport would hide this, not fix it.
    """
    c = crop.view.window
    for frame in frames:
        a = full.frame(frame, gains[frame])[c.y:c.y + c.height, c.x:c.x + c.width]
        b = crop.frame(frame, gains[frame])
        diff = np.abs(a.astype(int) - b.astype(int))
        assert diff.max() <= 8 and (diff > 0).mean() < 2e-4, (frame, int((diff > 0).sum()))


def test_crop_pixels_equal_full_frame_pixels(small_pair):
    cfg, full, crop = small_pair
    c = crop.view.window
    assert (full.view.window.width, full.view.window.height) == (640, 360)
    gains = full.gains(20)
    assert np.array_equal(gains, crop.gains(20))  # auto-exposure never depends on the window
    _assert_crop_matches(full, crop, (0, 4, 7, 11, 18), gains)  # 4, 18: the sheet enters, leaves
    assert np.array_equal(full.mask[c.y:c.y + c.height, c.x:c.x + c.width], crop.mask)
    for frame in (2, 7):  # the truth does not depend on the window either
        a, b = full.truth.frame(frame), crop.truth.frame(frame)
        assert all(np.array_equal(a[k], b[k]) for k in a)


def test_same_seed_same_bytes(shapes):
    # every disturbance on: all of them must follow the seed
    scene = {"distractors": True, "flicker": True, "clouds": True, "light_drift": True}

    def frames(seed):
        cfg = {**_small_config(seed=seed, shake=True, drift=True), "scene": scene}
        r = BeamRenderer(cfg, shapes)
        try:
            return [r.frame(i, g).tobytes() for i, g in zip((0, 3), r.gains(4)[[0, 3]], strict=True)]
        finally:
            r.close()

    first, again, other = frames(11), frames(11), frames(12)
    assert first == again
    assert other[0] != first[0]  # the noise (and the shake) follow the seed


# ----------------------------------------------------------------- ground truth
def test_truth_csv_matches_projection_of_the_simulated_beam_and_the_image(shapes, tmp_path):
    """The *written* truth.csv: dx_px and dy_px are the camera model's projection
    of the simulated 3D beam point at the measurement height, averaged over the
    exposure's sub-frames (to the CSV's 6 decimals); the rendered face sits on
    that row where the truth says (noise off, 4K optics)."""
    n = 12
    cfg = {"seed": 1, "camera": {"crop_width_px": 120, "crop_height_px": 240, "noise": False,
                                 "motion_blur_subframes": 2},
           "scene": CLEAN_SCENE, "codec": {"name": "ffv1"}}
    render_clip(cfg, shapes, tmp_path, max_frames=n, progress=False)
    with (tmp_path / "truth.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    dx = np.array([float(r["dx_px"]) for r in rows])
    dy = np.array([float(r["dy_px"]) for r in rows])
    # independent: the beam's centreline at the measurement height from the shapes,
    # projected by the camera at the two sub-frame times (k + 1/2) * exposure / 2
    cc = CameraConfig.from_config(cfg)
    cam = CameraModel(cc, camera_y_mm=-50.0 - 1000.0)
    z0 = np.array([750.0])
    rest = cam.project(np.array([0.0, -50.0, 750.0]))
    expected = []
    for f in range(n):
        pix = []
        for k in range(2):
            x, z, _ = shapes.at(f / 60 + (k + 0.5) * cc.exposure_s / 2, z0)
            pix.append(cam.project(np.array([x[0], -50.0, z[0]])))
        expected.append(np.mean(pix, 0) - rest)
    expected = np.array(expected)
    assert np.max(np.abs(dx - expected[:, 0])) < 1e-6 and np.max(np.abs(dy - expected[:, 1])) < 1e-6
    assert np.max(np.abs(dx)) > 3  # the beam really moved
    assert np.max(np.abs(dy)) < 0.01  # the first mode barely shortens the beam at 1.8 mm
    # the image at the measurement row: the face's intensity centroid is at rest + dx
    r = BeamRenderer(cfg, shapes)
    try:
        row = int(round(rest[1])) - r.view.window.y
        cols = np.arange(r.view.window.width)
        for f in (0, 6, 11):
            img = r.frame_linear(f)[row].mean(1)
            sel = np.abs(cols + r.view.window.x - (rest[0] + dx[f])) <= 12
            base = np.interp(cols[sel], [cols[sel][0], cols[sel][-1]],
                             [img[sel][:3].mean(), img[sel][-3:].mean()])
            w = np.clip(img[sel] - base, 0, None)
            measured = (w * cols[sel]).sum() / w.sum() + r.view.window.x
            # 4x MSAA quantises each vertical edge to 1/4 px coverage steps: the
            # centroid of a 14 px face is good to ~0.1 px
            assert abs(measured - (rest[0] + dx[f])) < 0.15, (f, measured, rest[0] + dx[f])
    finally:
        r.close()


def test_subframe_weights_are_continuous_with_exact_centroids():
    cc = CameraConfig(rolling_shutter_s=0.012, motion_blur_subframes=4)
    cam = CameraModel(cc, camera_y_mm=-1050.0)
    smp = cam.sampling(4)
    rows = np.arange(0, 2160, 7)
    w = smp.weights(rows)
    assert np.allclose(w.sum(1), 1.0)
    centroid = (w * smp.times).sum(1)
    assert np.allclose(centroid, rows * 0.012 / 2160 + cc.exposure_s / 2, atol=1e-12)
    glob = CameraModel(CameraConfig(), camera_y_mm=-1050.0).sampling(4)
    assert np.allclose(glob.weights(np.array([0, 2159])), 0.25) and glob.times.size == 4


def test_rolling_shutter_skews_a_moving_edge_in_proportion_to_readout():
    """A rigid beam translating at constant speed: the face's centroid column
    moves linearly with the row, by speed x read-out time over the sensor,
    without the stair steps of rows snapped to the sub-frame grid (a sawtooth
    of 0.6 px at this speed)."""
    t = np.arange(0, 0.3, 0.001)
    z = np.linspace(0, 1000, 11)
    speed_mm_s = 400.0
    slopes = {}
    for readout in (0.008, 0.016):
        # centred on frame 3's middle row: the beam stays within +-2 mm, its sides edge-on
        x = np.repeat((speed_mm_s * (t - 3 / 60 - readout / 2 - 1 / 240))[:, None], z.size, 1)
        rigid = BeamShapes(time_s=t, z_mm=z, x_mm=x, z_def_mm=np.tile(z, (t.size, 1)),
                           theta_rad=np.zeros_like(x))
        cfg = {**_small_config(rolling_shutter_s=readout, noise=False), "scene": CLEAN_SCENE}
        r = BeamRenderer(cfg, rigid, full_frame=True)
        try:
            img = r.frame_linear(3).mean(2)
            background = r.frame_linear(12).mean(2)  # the beam has left these columns
            rows = np.arange(20, 340)
            cols = np.arange(int(r.view.camera.cx) - 8, int(r.view.camera.cx) + 10)
            face = img[np.ix_(rows, cols)] - background[np.ix_(rows, cols)]
            centre = (face * cols).sum(1) / face.sum(1)  # signed: linear in the blend
        finally:
            r.close()
        fit = np.polyfit(rows, centre, 1)
        residual = centre - np.polyval(fit, rows)
        slopes[readout] = fit[0]
        expected = 700.0 * speed_mm_s / 1000.0 * readout / 360  # px per row
        # 4x MSAA quantises the edges: ~1 % on the slope, ~0.02 px on a row
        assert abs(fit[0] / expected - 1) < 0.03, (readout, fit[0], expected)
        assert np.sqrt(np.mean(residual**2)) < 0.03, (readout, np.sqrt(np.mean(residual**2)))
    assert abs(slopes[0.016] / slopes[0.008] - 2) < 0.06


def test_rolling_shutter_crop_matches_full_frame(shapes):
    cfg = _small_config(rolling_shutter_s=0.012)
    full = BeamRenderer(cfg, shapes, full_frame=True)
    crop = BeamRenderer(cfg, shapes)
    try:
        assert full.subframes.at(4).sampling.times.size > crop.view.cam_cfg.motion_blur_subframes  # spans the read-out
        _assert_crop_matches(full, crop, (4,), {4: 0.5})
    finally:
        full.close()
        crop.close()


# ----------------------------------------------------------------- occlusion
def _sheet_share_model(r: BeamRenderer, frame: int) -> np.ndarray:
    """Share of each window pixel's exposure covered by the sheet per the model:
    the SheetPath extent at the sub-frames, as the fraction of every undistorted
    pixel's footprint it covers, averaged with the sub-frame weights, then
    remapped through the lens like the image (global shutter)."""
    cam, rw = r.view.camera, r.plan.render
    smp = r.subframes.at(frame).sampling
    weights = smp.weights(np.array([r.view.window.y]))[0]
    uu, vv = np.meshgrid(np.arange(rw.x, rw.x + rw.width, dtype=float),
                         np.arange(rw.y, rw.y + rw.height, dtype=float))
    s, _ = r.view.sheet_coords(((uu - cam.cx) / cam.fx, (vv - cam.cy) / cam.fy))
    along_x = r.view.occ_cfg.direction in ("+x", "-x")
    pixel_mm = r.view.occ_cfg.distance_mm / (cam.fx if along_x else cam.fy)
    share = np.zeros(s.shape)
    for w, t in zip(weights, frame / r.view.cam_cfg.fps + smp.times, strict=True):
        ext = r.sheet.extent(t)
        if w > 0 and ext is not None:
            share += w * np.clip((np.minimum(s + pixel_mm / 2, ext[1])
                                  - np.maximum(s - pixel_mm / 2, ext[0])) / pixel_mm, 0, 1)
    return r.plan.apply(share.astype(np.float32))


@pytest.mark.parametrize("direction", ["+x", "-x", "+z", "-z"])
def test_sheet_pixels_agree_with_the_occlusion_model(direction):
    """Every pixel of every frame around the occlusion: the sheet's share of the
    exposure seen in the image equals the model's (the drawn sheet is where the
    model says, to MSAA precision), and the occluded flags equal 'the image
    shows the sheet on the POI mask', the first and last occluded frames too."""
    cfg = {**_small_config(noise=False), "scene": {"logo": False}}
    occ = OcclusionConfig(enabled=True, start_s=0.1, duration_s=0.1, transit_s=0.05,
                          direction=direction)
    sheet = BeamRenderer(cfg, None, occlusion=occ)  # a still beam: only the sheet changes
    clear = BeamRenderer(cfg, None, occlusion=dataclasses.replace(occ, enabled=False))
    try:
        paper = sheet.frame_linear(9).mean(2)  # the sheet fills the crop
        background = clear.frame_linear(0).mean(2)
        contrast = paper - background
        assert np.abs(contrast).min() > 0.1  # the paper stands out from everything
        poi = sheet.mask > 0
        flags, shown = [], []
        for f in range(16):
            seen = (sheet.frame_linear(f).mean(2) - background) / contrast
            model = _sheet_share_model(sheet, f)
            err = np.abs(seen - model)
            assert err.max() < 0.15 and err.mean() < 0.02, (f, err.max(), err.mean())
            truth = sheet.truth.frame(f)
            # the POIs flagged covered are those the sheet reaches at a sub-frame
            assert np.array_equal(truth["poi_covered"], model[poi] > 0), f
            flags.append(truth["occluded"])
            shown.append(int(seen[poi].max() > 1 / 32))  # half a sub-frame's worth of sheet
        assert flags == shown
        assert flags == [int(6 <= f < 12) for f in range(16)], flags  # [0.1, 0.2) s
    finally:
        sheet.close()
        clear.close()


@pytest.mark.parametrize("direction", ["+x", "+z"])
def test_partial_occlusion_covers_the_configured_share_of_the_mask(direction):
    cfg = {"seed": 3, "camera": {**PAPER_CROP, "noise": False}, "scene": {"logo": False}}
    occ = OcclusionConfig(enabled=True, start_s=0.1, duration_s=0.2, transit_s=0.05,
                          direction=direction, partial=True, partial_fraction=0.4)
    sheet = BeamRenderer(cfg, None, occlusion=occ)
    clear = BeamRenderer(cfg, None, occlusion=dataclasses.replace(occ, enabled=False))
    try:
        poi = sheet.mask > 0
        flags = [sheet.truth.frame(f)["occluded"] for f in range(24)]
        assert flags == [int(6 <= f < 18) for f in range(24)]
        truth = sheet.truth.frame(12)
        background = clear.frame_linear(12).mean(2)
        seen = sheet.frame_linear(12).mean(2) - background
        sheet_value = np.median(seen[poi][truth["poi_covered"]])
        covered = seen[poi] > 0.5 * sheet_value
        # one row / column of the mask is the granularity of a straight sheet edge
        step = 1 / (poi.any(0).sum() if direction == "+x" else poi.any(1).sum())
        assert abs(truth["occluded_frac"] - 0.4) <= step / 2 + 1e-9
        assert abs(covered.mean() - truth["occluded_frac"]) < 1e-9
        assert np.array_equal(covered, truth["poi_covered"])
    finally:
        sheet.close()
        clear.close()


@pytest.mark.parametrize("section,key,value", [("camera", "fps", -1), ("camera", "k1", "big"),
                                               ("scene", "texture_contrast", 2.0),
                                               ("occlusion", "direction", "sideways"),
                                               ("occlusion", "partial_fraction", 1.0),
                                               ("camera", "shake_band_hz", [15, 2]),
                                               ("camera", "drift_rotation_mrad", [1, 2]),
                                               ("scene", "flicker_depth", 1.5),
                                               ("scene", "distractor_count", 0),
                                               ("codec", "name", "vp9"), ("camera", "bogus", 1)])
def test_bad_config_names_key_and_value(section, key, value):
    from sim.codec import CodecConfig
    cls = {"camera": CameraConfig, "scene": SceneConfig, "occlusion": OcclusionConfig,
           "codec": CodecConfig}[section]
    with pytest.raises(ValueError, match=key):
        cls.from_config({section: {key: value}})


# ----------------------------------------------------------------- sensor
def _splitmix64(z: np.ndarray) -> np.ndarray:
    """Reference SplitMix64 in NumPy (uint64 arithmetic wraps)."""
    with np.errstate(over="ignore"):
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def test_sensor_kernel_matches_numpy_reference():
    """Shot + read noise in electrons, the well clips, then the gain, gamma, 8 bits;
    the noise is a hash of (seed, frame, global pixel, channel)."""
    from sim.camera import _encode_lut, _gauss_table
    cfg = CameraConfig()
    w = Window(100, 50, 64, 32)
    lin = np.random.default_rng(0).random((32, 64, 3)).astype(np.float32)
    out = sensor_readout(lin, 1.7, cfg, seed=3, frame=5, window=w)
    rows = np.arange(w.y, w.y + w.height, dtype=np.uint64)[:, None, None]
    cols = np.arange(w.x, w.x + w.width, dtype=np.uint64)[None, :, None]
    idx = (rows * np.uint64(cfg.width_px) + cols) * np.uint64(3) + np.arange(3, dtype=np.uint64)
    key = _splitmix64(np.uint64(3 << 32 | 5))
    z = _gauss_table()[(_splitmix64(idx ^ key) >> np.uint64(48)).astype(np.int64)]
    well = np.float32(cfg.full_well_e)
    electrons = np.maximum(lin, 0) * well
    electrons = electrons + np.sqrt(electrons + np.float32(cfg.read_noise_e ** 2)) * z
    electrons = np.clip(electrons, 0, well)
    sig = np.clip(np.float32(1.7) * electrons / well, 0, 1)
    ref = _encode_lut(cfg.gamma)[np.rint(sig * np.float32(2 ** 20 - 1)).astype(int)]
    assert np.array_equal(out, ref)
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1) < 0.05


def test_photon_transfer_slope_grows_with_the_gain():
    """The analog gain amplifies shot noise: output variance vs mean has slope
    gain / full well (a longer exposure would keep it at 1 / full well)."""
    cfg = CameraConfig(full_well_e=400.0, read_noise_e=2.0, gamma=1.0)
    window = Window(0, 0, 256, 256)
    slopes = {}
    for gain in (1.0, 2.0):
        means, variances = [], []
        for level in (0.05, 0.1, 0.2, 0.3, 0.4):
            img = sensor_readout(np.full((256, 256, 3), level, np.float32), gain, cfg, seed=2,
                                 frame=int(100 * level), window=window).astype(np.float64) / 255
            means.append(img.mean())
            variances.append(img.var())
        slopes[gain] = np.polyfit(means, variances, 1)[0]
        assert abs(slopes[gain] / (gain / cfg.full_well_e) - 1) < 0.05, (gain, slopes[gain])
    assert abs(slopes[2.0] / slopes[1.0] - 2) < 0.1


def test_auto_exposure_meters_the_render_backs_off_for_the_sheet_and_recovers(shapes):
    cfg = _small_config(ae_time_constant_s=0.05)
    cfg["occlusion"] = {"enabled": True, "start_s": 0.1, "duration_s": 0.3, "transit_s": 0.05}
    r = BeamRenderer(cfg, shapes, full_frame=True)
    try:
        meters = np.array([r.meter(i) for i in range(50)])
        ae = AutoExposure(r.view.cam_cfg)
        gains = np.array([ae.step(m) for m in meters])
        assert np.array_equal(gains, r.gains(50))  # deterministic
        # the meter is the rendered image's brightness
        assert abs(meters[0] / r.frame_linear(0).mean() - 1) < 0.05
        assert meters[15] > 1.5 * meters[0]  # the white sheet fills the view
        assert gains[2] == pytest.approx(gains[0], rel=1e-3)  # only the beam moves
        assert gains[20] < 0.7 * gains[0]  # backed off while covered
        assert gains[7] > gains[20]  # with a lag (a phone's time constant)
        assert abs(gains[49] / gains[0] - 1) < 0.05  # recovered after the sheet left
    finally:
        r.close()


# ----------------------------------------------------------------- the paper's scale
def _corners(rgb: np.ndarray, harris: bool) -> np.ndarray:
    found = cv2.goodFeaturesToTrack(_gray(rgb), maxCorners=200, qualityLevel=0.01, minDistance=5,
                                    blockSize=3, useHarrisDetector=harris, k=0.04)
    return np.zeros((0, 2)) if found is None else found.reshape(-1, 2)


@pytest.mark.parametrize("harris", [False, True])
def test_corner_detectors_find_nothing_inside_the_painted_beam(shapes, harris):
    """Paper Fig. 6-7: at 2.8 px/mm the painted face has no corners; the logo
    behind it has plenty (Shi-Tomasi and Harris alike)."""
    cfg = {"seed": 2, "camera": {"crop_width_px": 200, "crop_height_px": 400}}
    r = BeamRenderer(cfg, shapes)
    try:
        frame = 20  # the beam is 4 px right of rest: where the mask was drawn
        img = r.frame(frame, r.gains(frame + 1)[frame])
        truth = r.truth.frame(frame)
        face = np.zeros_like(r.mask)  # the POIs where they are in this frame
        moved = np.rint(r.pois.window_px + np.stack([truth["poi_dx_px"], truth["poi_dy_px"]], -1))
        face[moved[:, 1].astype(int), moved[:, 0].astype(int)] = 1
        assert abs(truth["dx_px"]) > 3
        pts = np.rint(_corners(img, harris)).astype(int)
        pts = np.clip(pts, 0, np.array(img.shape[1::-1]) - 1)
        inside = face[pts[:, 1], pts[:, 0]] > 0
        assert len(pts) >= 10, len(pts)  # the detector works (on the logo)
        assert inside.sum() == 0, pts[inside]
    finally:
        r.close()


def test_distractors_put_corners_on_the_wall_near_the_beam(shapes):
    """scene.distractors: fixtures inside the crop, clear of the beam and logo,
    each with corners (stronger with more contrast); none there when off."""
    base = {"seed": 4, "camera": {"crop_width_px": 480, "crop_height_px": 240, "noise": False},
            "scene": {"logo": False, "distractors": True, "distractor_count": 4}}
    with_fixtures = BeamRenderer(base, shapes)
    try:
        centres, kinds = with_fixtures.distractors
        assert len(centres) == 4 and sorted(kinds) == [0, 1, 2, 3]
        plane_y = with_fixtures.view.scene_cfg.background_distance_mm - 1.0
        world = np.stack([centres[:, 0], np.full(4, plane_y), centres[:, 1]], -1)
        px = with_fixtures.view.camera.project(world) - (with_fixtures.view.window.x, with_fixtures.view.window.y)
        half_px = 0.5 * 15.0 * with_fixtures.view.camera.fx / (plane_y - with_fixtures.view.camera.camera_y_mm)
        beam_u = with_fixtures.view.measure_px[0] - with_fixtures.view.window.x
        assert np.all(np.abs(px[:, 0] - beam_u) > 2 * half_px)  # off the beam and its logo
        assert np.all((px > half_px).all(1) & (px < (480 - half_px, 240 - half_px)).all(1))
    finally:
        with_fixtures.close()
    response, hits = {}, {}
    for name, scene in {"strong": {"distractor_contrast": 0.8}, "weak": {"distractor_contrast": 0.2},
                        "off": {"distractors": False}}.items():
        r = BeamRenderer({**base, "scene": {**base["scene"], **scene}}, shapes)
        try:
            gray = _gray(r.frame(0, 1.0))
        finally:
            r.close()
        pts = _corners(np.repeat(gray[..., None], 3, 2), harris=False)
        near = np.abs(pts[None, :, :] - px[:, None, :]).max(2) <= half_px + 1
        hits[name] = int(near.any(1).sum())
        eig = cv2.cornerMinEigenVal(gray.astype(np.float32), 3)
        response[name] = min(eig[int(y - half_px):int(y + half_px), int(x - half_px):int(x + half_px)].max()
                             for x, y in px)
    # the corner detector finds every fixture; without them only the wall's
    # faint texture is there, and contrast sets the strength
    assert hits["strong"] == hits["weak"] == 4, hits
    assert response["strong"] > 3 * response["weak"] and response["strong"] > 10 * response["off"], \
        response


# ----------------------------------------------------------------- disturbances
@pytest.mark.parametrize("camera", [{"shake": True, "shake_rotation_mrad": 1.0,
                                     "shake_translation_mm": 0.0, "shake_band_hz": [2.0, 4.0]},
                                    {"drift": True, "drift_time_constant_s": 0.1,
                                     "drift_rotation_mrad": [3.0, -4.0, 0.0]}])
def test_camera_motion_moves_the_image_as_the_truth_says(shapes, camera):
    """The ground truth stays the beam's motion relative to the ground; the
    image of the static wall moves by cam_dx_px / cam_dy_px (a rotation moves
    all depths alike). A slow shake keeps the blur within an exposure small
    enough for a translation to register it."""
    still = BeamRenderer(_small_config(noise=False), shapes)
    moving = BeamRenderer(_small_config(noise=False, **camera), shapes)
    try:
        for f in (5, 17, 30):
            a, b = still.truth.frame(f), moving.truth.frame(f)
            assert all(np.array_equal(a[k], b[k]) for k in ("dx_px", "dy_px", "poi_dx_px"))
            assert a["cam_dx_px"] == a["cam_dy_px"] == 0.0
            shift = np.array([b["cam_dx_px"], b["cam_dy_px"]])
            assert np.hypot(*shift) > 0.25
            # image shift of the wall (ECC registration) left and right of the beam:
            # their mean is the shift at the beam (a roll turns the two sides apart)
            ref, img = still.frame_linear(f).mean(2), moving.frame_linear(f).mean(2)
            criteria = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 200, 1e-8)
            seen = np.mean([cv2.findTransformECC(ref[10:90, cols], img[10:90, cols],
                                                 np.eye(2, 3, dtype=np.float32),
                                                 cv2.MOTION_TRANSLATION, criteria, None, 5)[1][:, 2]
                            for cols in (np.s_[5:70], np.s_[130:195])], axis=0)
            # registering an image blurred by the motion: good to ~2 % of the shift
            assert np.hypot(*(seen - shift)) < 0.03 + 0.02 * np.hypot(*shift), (f, seen, shift)
    finally:
        still.close()
        moving.close()


def test_flicker_aliases_and_clouds_drift_the_frame_brightness(shapes):
    plain = _small_config(noise=False)
    r0 = BeamRenderer(plain, shapes)
    flick = BeamRenderer({**plain, "scene": {"flicker": True, "flicker_hz": 100.0,
                                             "flicker_depth": 0.5}}, shapes)
    slow = BeamRenderer({**plain, "scene": {"clouds": True, "cloud_depth": 0.2,
                                            "light_drift": True}}, shapes)
    try:
        light = np.array([flick.truth.frame(f)["light_rel"] for f in range(9)])
        # 100 Hz seen at 60 fps: the brightness beats at 20 Hz, every third frame alike
        assert np.allclose(light[:6], light[3:9]) and np.ptp(light) > 0.1
        for f in (0, 1):
            ratio = flick.frame_linear(f).mean() / r0.frame_linear(f).mean()
            assert abs(ratio - light[f]) < 1e-3
        clouds = np.array([slow.truth.frame(f)["light_rel"] for f in range(0, 60, 6)])
        assert np.all(np.abs(np.diff(clouds)) < 0.05) and np.ptp(clouds) > 0
    finally:
        for r in (r0, flick, slow):
            r.close()
    # with a rolling shutter, mains flicker draws bands across the rows
    banded = BeamRenderer({**_small_config(rolling_shutter_s=0.015),
                           "scene": {"flicker": True, "flicker_depth": 0.8}}, shapes,
                          full_frame=True)
    try:
        rows = banded.light_rows(0)
        assert np.ptp(rows) > 0.1 and np.sum(np.diff(np.sign(np.diff(rows))) != 0) >= 2
    finally:
        banded.close()


# ----------------------------------------------------------------- outputs
def test_render_clip_writes_documented_files_streamed(shapes, tmp_path):
    cfg = {**_small_config(shake=True), "codec": {"name": "ffv1"}}
    meta = render_clip(cfg, shapes, tmp_path, max_frames=4, progress=False)
    assert {p.name for p in tmp_path.iterdir()} == {"video.mkv", "mask.png", "background.png", "scale.json",
                                                     "recording.json", "truth.csv", "poi_truth.npz",
                                                     "render.json"}
    with (tmp_path / "truth.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert list(rows[0]) == ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "occluded",
                             "occluded_frac", "cam_dx_px", "cam_dy_px", "light_rel", "gain"]
    assert len(rows) == 4
    mask = cv2.imread(str(tmp_path / "mask.png"), cv2.IMREAD_UNCHANGED)
    assert mask.shape == (100, 200) and mask.dtype == np.uint8 and mask.max() == 255
    # the static wall a user would mark: both sides of the beam, clear of the POIs by a margin
    background = cv2.imread(str(tmp_path / "background.png"), cv2.IMREAD_UNCHANGED)
    assert background.shape == mask.shape and background.dtype == np.uint8
    cols = np.flatnonzero(background.max(axis=0))
    poi_cols = np.flatnonzero(mask.max(axis=0))
    assert cols.min() < poi_cols.min() and cols.max() > poi_cols.max()
    gap = np.abs(cols[:, None] - poi_cols[None, :]).min()
    assert gap >= 12 and not (background & mask).any()
    # the scale reference: the beam's edges, its thickness apart, across the POIs' row band
    scale = json.loads((tmp_path / "scale.json").read_text())
    x1, y1, x2, y2 = scale["between_px"]
    assert scale["known_length_mm"] == 5.0
    assert x1 < poi_cols.min() and x2 > poi_cols.max() and abs(y2 - y1) < 0.01
    assert (x2 - x1) == pytest.approx(5.0 / meta["mm_per_px"], rel=0.01)
    recording = json.loads((tmp_path / "recording.json").read_text())
    assert recording["video_origin_px"] == [meta["crop"]["x"], meta["crop"]["y"]]
    r = BeamRenderer(cfg, shapes)
    try:
        raw = r.frame(0, r.gains(1)[0])
        truth = r.truth.stack(4)
        gains = r.gains(4)
    finally:
        r.close()
    # the streamed npz holds what the in-memory truth holds
    with np.load(tmp_path / "poi_truth.npz") as poi:
        assert set(poi.files) == {"dx_px", "dy_px", "x_px", "y_px", "occluded_frac", "gain",
                                  "cam_dx_px", "cam_dy_px", "light_rel"}
        assert poi["dx_px"].shape == (4, int((mask > 0).sum())) and poi["dx_px"].dtype == np.float32
        assert np.array_equal(poi["dx_px"], truth["poi_dx_px"])
        assert np.array_equal(poi["dy_px"], truth["poi_dy_px"])
        assert np.array_equal(poi["x_px"], truth["poi_x_px"])
        assert np.array_equal(poi["gain"], gains)
        assert np.array_equal(poi["cam_dx_px"], truth["cam_dx_px"])
    assert np.allclose([float(row["cam_dx_px"]) for row in rows], truth["cam_dx_px"], atol=1e-6)
    assert meta["crop"]["width"] == 200 and meta["crop"]["height"] == 100
    # FFV1 is lossless: the decoded frame equals the raw frame
    from sim.codec import read_video_frames
    decoded = next(iter(read_video_frames(tmp_path / "video.mkv")))
    assert np.array_equal(decoded, raw)


def test_figure_frames_pick_motion_not_the_held_pluck():
    """The workflow's pluck holds the beam still until 0.5 s: the crop figure
    must show a frame of motion, and the occluded one a frame of the config's
    occlusion."""
    base = synthetic_shapes(duration_s=2.0)
    t = base["time_s"]
    held = np.where(t < 0.5, 1.0, np.cos(2 * np.pi * 4.0 * (t - 0.5)))[:, None]
    peak = np.argmax(base["x_mm"][:, -1])
    shapes = BeamShapes(time_s=t, z_mm=base["z_mm"], x_mm=held * base["x_mm"][peak],
                        z_def_mm=np.tile(base["z_mm"], (t.size, 1)),
                        theta_rad=held * base["theta_rad"][peak])
    cfg = {**_small_config(), "occlusion": {"enabled": True, "start_s": 1.0, "duration_s": 0.5}}
    r = BeamRenderer(cfg, shapes)
    try:
        frames = figure_frames(r, r.view.n_frames(1.9))
        f = frames["motion"]
        truth = r.truth.frame(f)
        speed = (r.truth.frame(f + 1)["dx_px"] - r.truth.frame(f - 1)["dx_px"]) * 30
        assert f / 60 > 0.5 and abs(truth["dx_px"]) > 0.3 and abs(speed) > 10
        assert r.truth.frame(frames["occluded"])["occluded"] == 1
        assert 1.25 <= frames["occluded"] / 60 < 1.3
        assert frames["occluding"] / 60 < 1.0 and r.truth.frame(frames["occluding"])["occluded"] == 0
    finally:
        r.close()


def test_config_schema_documents_every_render_key_with_its_default():
    """workflow/schemas/config.schema.yaml states (does not inject) the camera,
    scene and occlusion keys and defaults of the dataclasses: keep them in step."""
    from pathlib import Path

    import jsonschema
    import yaml
    root = Path(__file__).resolve().parents[2]
    schema = yaml.safe_load((root / "workflow/schemas/config.schema.yaml").read_text())
    sections = schema["properties"]["defaults"]["properties"]
    for name, cls in {"camera": CameraConfig, "scene": SceneConfig,
                      "occlusion": OcclusionConfig}.items():
        props = sections[name]["properties"]
        fields = {f.name: f.default for f in dataclasses.fields(cls)}
        if cls is SceneConfig:  # the beam's geometry is the beam section's, not settable here
            fields = {k: v for k, v in fields.items() if k not in GEOMETRY}
        assert set(props) == set(fields), (name, set(props) ^ set(fields))
        for key, default in fields.items():
            value = list(default) if isinstance(default, tuple) else default
            stated = yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("...").strip()
            assert props[key]["description"].endswith(f"default {stated}"), (name, key)
            assert "default" not in props[key]  # the dataclass is the one source of defaults
            jsonschema.validate(value, props[key])
        with pytest.raises(jsonschema.ValidationError):
            jsonschema.validate({"bogus_key": 1}, sections[name])


def test_beam_geometry_is_read_from_the_beam_section_only() -> None:
    """The beam's size is configured once (``beam``): the scene takes it from there, and the
    scene's copies cannot be set (they once disagreed with the simulated beam's)."""
    scene = SceneConfig.from_config({"beam": {"thickness_mm": 6.0, "width_mm": 80.0, "length_mm": 900.0},
                                     "sensor": {"height_mm": 700.0}})
    assert (scene.beam_thickness_mm, scene.beam_width_mm, scene.beam_length_mm) == (6.0, 80.0, 900.0)
    assert SceneConfig.from_config({}).beam_thickness_mm == 5.0
    with pytest.raises(ValueError, match="beam.thickness_mm"):
        SceneConfig.from_config({"scene": {"beam_thickness_mm": 6.0}})


# ----------------------------------------------------------------- regions
def _modal_scenario_config():
    """The `modal` scenario of config/config.yaml, merged onto the defaults as the workflow does."""
    from pathlib import Path

    import yaml

    from refflow.config import deep_merge
    config = yaml.safe_load((Path(__file__).parents[2] / "config" / "config.yaml").read_text())
    return deep_merge(config["defaults"], config["scenarios"]["modal"])


def test_regions_mask_labels_each_sensor_height_on_the_beam_face():
    cfg = _modal_scenario_config()
    heights, half = region_heights(cfg)
    assert heights.tolist() == [250.0, 500.0, 750.0, 1000.0]
    view = View(cfg, None)
    labels = regions_mask(view, heights, half)
    face, _ = face_rows(view)
    project_row = lambda z: float(view.camera.project(np.array([0.0, view.face_y_mm, z]))[1]) - view.window.y  # noqa: E731
    length = view.scene_cfg.beam_length_mm
    assert labels.dtype == np.uint8 and labels.shape == (view.window.height, view.window.width)
    assert set(np.unique(labels).tolist()) == {0, 1, 2, 3, 4}
    # every labelled pixel is a POI of the binary mask (the beam's face, 3 px in)
    assert np.all(face[labels > 0])
    for k, height in enumerate(heights, start=1):
        rows = np.flatnonzero((labels == k).any(axis=1))
        assert np.all(np.diff(rows) == 1), f"region {k} is not one band of rows"
        # 2 x half_height_mm tall at 0.357 mm/px, give or take the lens's distortion
        assert abs(rows.size - 2 * half / view.mm_per_px) < 6, (k, rows.size)
        if height + half <= length:
            centre = project_row(height)
            assert rows[0] < centre < rows[-1], (k, centre, rows[[0, -1]])
        else:  # the tip's region: the top 2 x half_height_mm, just below the free end
            assert rows[0] - project_row(length) == pytest.approx(3, abs=1.5)
            assert rows[0] < project_row(length - half) < rows[-1]
    # region k is the k-th height from the clamp up: image rows go the other way
    tops = [np.flatnonzero((labels == k).any(axis=1))[0] for k in range(1, 5)]
    assert tops == sorted(tops, reverse=True)


def test_regions_mask_names_the_crop_when_a_height_is_outside_the_window():
    cfg = _modal_scenario_config()
    cfg["camera"] = {**cfg["camera"], "crop_height_px": 1200}
    with pytest.raises(ValueError, match="crop_height_px"):
        regions_mask(View(cfg, None), [250.0, 500.0, 750.0, 1000.0], 25.0)
