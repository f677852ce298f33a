"""The pyrender scene: a deformed cantilever seen edge-on, a logo, a clamp, a wall.

Geometry (all lengths in mm, world axes as in ``docs/formats.md``): the beam
runs along +z from the clamp (z = 0) to the tip (z = L); its 5 mm thickness
lies along x (the bending direction) and its 100 mm width along y. The camera
looks along +y, so it sees the beam *edge-on*: the visible face is the
5 mm x 1000 mm front edge at y = -width/2, which spans 14 px at 2.8 px/mm —
the paper's scale reference (Sec. 4.1). A 40 x 40 mm logo plate is fixed to
the back of the beam (y = +width/2) so it sticks out on both sides of the edge
and moves with the beam, luring corner detectors as in the paper; a textured
wall stands ``scene.background_distance_mm`` behind the beam.
"""

from __future__ import annotations

import functools
import os
import types
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

# NumPy 2 shim: pyrender 0.1.45 still reads ``np.infty`` (``Mesh.bounds``, used
# whenever a mesh is added to a scene), an alias NumPy 2.0 removed. Restore the
# alias before pyrender is imported and used (sim imports pyrender only through
# this module) rather than pin NumPy < 2; on NumPy 1.x the alias exists and
# nothing changes. tests/unit/test_render.py checks ``Mesh.bounds``. The noqa
# keeps ``ruff --fix`` (rule NPY201) from rewriting the alias into a no-op
# ``np.inf = np.inf``, which is how this shim once broke.
if not hasattr(np, "infty"):
    np.infty = np.inf  # noqa: NPY201
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
import pyrender  # noqa: E402

from sim.beam import BeamParams  # noqa: E402
from sim.config import section_dataclass  # noqa: E402


def _delete_own_egl_context(platform) -> None:
    """EGLPlatform.delete_context without ``eglTerminate``: destroy this context only."""
    from OpenGL.EGL import EGL_NO_CONTEXT, EGL_NO_SURFACE, eglDestroyContext, eglMakeCurrent
    display, context = platform._egl_display, platform._egl_context
    if display is None or context is None:
        return
    eglMakeCurrent(display, EGL_NO_SURFACE, EGL_NO_SURFACE, EGL_NO_CONTEXT)
    if not eglDestroyContext(display, context):
        raise RuntimeError("eglDestroyContext failed while releasing a renderer")
    platform._egl_context = platform._egl_display = None


def _spare_other_renderers(renderer: pyrender.OffscreenRenderer) -> pyrender.OffscreenRenderer:
    platform = getattr(renderer, "_platform", None)
    if getattr(platform, "_egl_context", None) is not None:
        platform.delete_context = types.MethodType(_delete_own_egl_context, platform)
    return renderer


def offscreen_renderer(width: int, height: int) -> pyrender.OffscreenRenderer:
    """A pyrender OffscreenRenderer that frees only its own EGL context.

    pyrender's clean-up (``OffscreenRenderer.delete``, also run by its
    finaliser when a renderer is garbage-collected) ends with ``eglTerminate``
    on the process-wide default display, which invalidates the contexts of
    every other live renderer (a crop and a full frame live side by side in
    tests and figures). This one destroys its own context and leaves the
    display, one per process, initialised. Other platforms (OSMesa) own their
    contexts and are left as pyrender made them.
    """
    return _spare_other_renderers(pyrender.OffscreenRenderer(width, height))


def release_renderer(renderer: pyrender.OffscreenRenderer) -> None:
    """Free a renderer's GL objects, framebuffers and EGL context, sparing the
    other renderers' (see :func:`offscreen_renderer`); a second call does nothing."""
    if getattr(renderer, "_renderer", None) is None:
        return
    _spare_other_renderers(renderer).delete()


# The scene's copies of the beam's geometry (scene name: beam section name).
GEOMETRY = {"beam_length_mm": "length_mm", "beam_thickness_mm": "thickness_mm", "beam_width_mm": "width_mm"}


@dataclass(frozen=True)
class SceneConfig:
    """``scene`` config section (lengths in mm), with the beam's geometry from the ``beam``
    section (:class:`sim.beam.BeamParams`, its one definition: not settable here)."""

    beam_length_mm: float = BeamParams.length_mm
    beam_thickness_mm: float = BeamParams.thickness_mm
    beam_width_mm: float = BeamParams.width_mm
    measure_height_mm: float | None = None   # None: ``sensor.height_mm`` or 750
    texture_contrast: float = 0.03           # std of the paint's albedo / mean
    texture_feature_mm: float = 1.5          # size of the paint's blotches
    paint_albedo: float = 0.45
    logo: bool = True
    logo_size_mm: float = 40.0
    logo_height_mm: float | None = None      # None: measurement height
    background_distance_mm: float = 500.0    # wall behind the beam axis
    background_contrast: float = 0.35
    light_intensity: float = 0.6             # key light (linear irradiance, 1 = full)
    fill_intensity: float = 0.2
    ambient: float = 0.2
    ring_spacing_mm: float = 2.0             # mesh resolution along the beam
    # static high-contrast features on the wall inside the measurement crop (bolts,
    # stickers, cable clips): corners that lure sparse trackers (paper Fig. 6)
    distractors: bool = False
    distractor_count: int = 6
    distractor_contrast: float = 0.8         # 0..1: departure from the wall's grey
    distractor_size_mm: float = 15.0
    # light disturbances (sim.disturbance.Illumination)
    flicker: bool = False
    flicker_hz: float = 100.0                # intensity modulation: twice the mains frequency
    flicker_depth: float = 0.2               # relative amplitude (intensity 1 +- depth)
    clouds: bool = False
    cloud_depth: float = 0.15                # RMS relative change of the light
    cloud_time_scale_s: float = 3.0          # shortest period of the changes
    light_drift: bool = False
    light_drift_per_min: float = -0.1        # relative change of the light per minute

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> SceneConfig:
        section = dict(config.get("scene") or {})
        for key in GEOMETRY:
            if key in section:
                raise ValueError(f"scene.{key}: the beam's geometry is set once, as beam.{GEOMETRY[key]}")
        out = section_dataclass(cls, section, "scene")
        beam = BeamParams.from_dict(config.get("beam"))
        out = _replace(out, **{key: getattr(beam, name) for key, name in GEOMETRY.items()})
        if out.measure_height_mm is None:
            height = (config.get("sensor") or {}).get("height_mm", 750.0)
            out = _replace(out, measure_height_mm=float(height))
        for key in ("beam_length_mm", "beam_thickness_mm", "beam_width_mm", "logo_size_mm",
                    "background_distance_mm", "ring_spacing_mm", "texture_feature_mm"):
            if getattr(out, key) <= 0:
                raise ValueError(f"scene.{key} must be > 0, got {getattr(out, key)!r}")
        for key in ("texture_contrast", "distractor_contrast", "flicker_depth"):
            if not 0 <= getattr(out, key) <= 1:
                raise ValueError(f"scene.{key} must be in [0, 1], got {getattr(out, key)!r}")
        for key in ("distractor_count", "distractor_size_mm", "flicker_hz", "cloud_time_scale_s"):
            if getattr(out, key) <= 0:
                raise ValueError(f"scene.{key} must be > 0, got {getattr(out, key)!r}")
        if out.cloud_depth < 0:
            raise ValueError(f"scene.cloud_depth must be >= 0, got {out.cloud_depth!r}")
        if not 0 < out.measure_height_mm <= out.beam_length_mm:
            raise ValueError(f"scene.measure_height_mm must lie on the beam (0, "
                             f"{out.beam_length_mm}], got {out.measure_height_mm!r}")
        return out


def _replace(obj, **kw):
    import dataclasses
    return dataclasses.replace(obj, **kw)




# ----------------------------------------------------------------- shapes
@dataclass
class BeamShapes:
    """Deformed centreline from ``shapes.npz`` with smooth interpolation.

    Time: linear between samples (1 kHz in the sim, far finer than a frame's
    exposure). Height: cubic Hermite using the nodal deflection and slope
    (``tan(theta)``), so the deformed beam is C1-smooth without joints.
    """

    time_s: np.ndarray
    z_mm: np.ndarray
    x_mm: np.ndarray
    z_def_mm: np.ndarray
    theta_rad: np.ndarray

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> BeamShapes:
        path = Path(path)
        if not path.is_file():
            raise ValueError(f"{path}: shapes file not found (run `python -m sim simulate` first)")
        with np.load(path) as data:
            missing = [k for k in ("time_s", "z_mm", "x_mm", "z_def_mm", "theta_rad") if k not in data]
            if missing:
                raise ValueError(f"{path}: missing array(s) {', '.join(missing)}")
            arrays = {k: np.asarray(data[k], dtype=np.float64)
                      for k in ("time_s", "z_mm", "x_mm", "z_def_mm", "theta_rad")}
        shapes = cls(**arrays)
        shapes.validate(str(path))
        return shapes

    def validate(self, name: str = "shapes") -> None:
        T, N = self.time_s.size, self.z_mm.size
        for key in ("x_mm", "z_def_mm", "theta_rad"):
            if getattr(self, key).shape != (T, N):
                raise ValueError(f"{name}: {key} has shape {getattr(self, key).shape}, "
                                 f"expected (T, N) = ({T}, {N})")
        if T < 2 or N < 2 or np.any(np.diff(self.time_s) <= 0) or np.any(np.diff(self.z_mm) <= 0):
            raise ValueError(f"{name}: time_s and z_mm must be increasing with >= 2 entries")

    def _time_weights(self, t: float):
        t = float(np.clip(t, self.time_s[0], self.time_s[-1]))
        i = int(np.clip(np.searchsorted(self.time_s, t, side="right") - 1, 0, self.time_s.size - 2))
        w = (t - self.time_s[i]) / (self.time_s[i + 1] - self.time_s[i])
        return i, w

    def at(self, t: float, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Centreline ``(x_mm, z_mm, theta_rad)`` at undeformed heights ``z`` and time ``t``."""
        i, w = self._time_weights(t)
        x = (1 - w) * self.x_mm[i] + w * self.x_mm[i + 1]
        zd = (1 - w) * self.z_def_mm[i] + w * self.z_def_mm[i + 1]
        th = (1 - w) * self.theta_rad[i] + w * self.theta_rad[i + 1]
        z = np.asarray(z, dtype=np.float64)
        k = np.clip(np.searchsorted(self.z_mm, z, side="right") - 1, 0, self.z_mm.size - 2)
        h = self.z_mm[k + 1] - self.z_mm[k]
        s = (z - self.z_mm[k]) / h
        h00, h10 = 2 * s**3 - 3 * s**2 + 1, s**3 - 2 * s**2 + s
        h01, h11 = -2 * s**3 + 3 * s**2, s**3 - s**2
        m0, m1 = np.tan(th[k]), np.tan(th[k + 1])
        xi = h00 * x[k] + h10 * h * m0 + h01 * x[k + 1] + h11 * h * m1
        dh00, dh10 = 6 * s**2 - 6 * s, 3 * s**2 - 4 * s + 1
        dh01, dh11 = -6 * s**2 + 6 * s, 3 * s**2 - 2 * s
        slope = (dh00 * x[k] + dh01 * x[k + 1]) / h + dh10 * m0 + dh11 * m1
        zi = zd[k] + s * (zd[k + 1] - zd[k]) + (z - (self.z_mm[k] + s * h))
        return xi, zi, np.arctan(slope)

    def material_to_world(self, t: float, a: np.ndarray, b: np.ndarray, z0: np.ndarray) -> np.ndarray:
        """World points (…, 3) of material points: offset ``a`` across the
        thickness (x), ``b`` across the width (y), undeformed height ``z0``."""
        xc, zc, th = self.at(t, z0)
        return np.stack([xc + a * np.cos(th), np.broadcast_to(b, xc.shape) * 1.0,
                         zc - a * np.sin(th)], axis=-1)


def synthetic_shapes(*, duration_s: float = 2.0, rate_hz: float = 1000.0, freq_hz: float = 4.0,
                     peak_mm: float = 1.8, peak_height_mm: float = 750.0,
                     length_mm: float = 1000.0, n_nodes: int = 21) -> dict[str, np.ndarray]:
    """Analytic first cantilever mode oscillating sinusoidally (for tests/dev).

    Returns the ``shapes.npz`` arrays; ``x_mm`` at ``peak_height_mm`` peaks at
    ``peak_mm``.
    """
    beta = 1.8751040687119611 / length_mm
    sigma = (np.cosh(beta * length_mm) + np.cos(beta * length_mm)) / \
            (np.sinh(beta * length_mm) + np.sin(beta * length_mm))

    def phi(z):
        return np.cosh(beta * z) - np.cos(beta * z) - sigma * (np.sinh(beta * z) - np.sin(beta * z))

    def dphi(z):
        return beta * (np.sinh(beta * z) + np.sin(beta * z)
                       - sigma * (np.cosh(beta * z) - np.cos(beta * z)))

    z = np.linspace(0.0, length_mm, n_nodes)
    t = np.arange(int(round(duration_s * rate_hz)) + 1) / rate_hz
    amp = peak_mm / phi(peak_height_mm)
    q = amp * np.sin(2 * np.pi * freq_hz * t)[:, None]
    x = q * phi(z)[None, :]
    slope = q * dphi(z)[None, :]
    # axial shortening of the inextensible centreline: 0.5 * int_0^z slope^2
    dz = np.diff(z)
    short = np.concatenate([np.zeros((t.size, 1)),
                            np.cumsum(0.25 * (slope[:, 1:] ** 2 + slope[:, :-1] ** 2) * dz, axis=1)],
                           axis=1)
    return {"time_s": t, "z_mm": z, "x_mm": x, "z_def_mm": z[None, :] - short,
            "theta_rad": np.arctan(slope)}


def write_synthetic_shapes(path: str | os.PathLike[str], **kwargs) -> Path:
    from refflow.io import atomic_path
    path = Path(path)
    with atomic_path(path) as tmp:
        np.savez(tmp, **synthetic_shapes(**kwargs))
    return path


# ----------------------------------------------------------------- textures
def _smooth_noise(shape: tuple[int, int], sigma_px: float, rng: np.random.Generator) -> np.ndarray:
    """Unit-variance Gaussian-filtered noise; broad filters run on a coarser grid."""
    factor = max(1, int(sigma_px // 4))
    small = (max(2, shape[0] // factor), max(2, shape[1] // factor))
    noise = rng.standard_normal(small).astype(np.float32)
    noise = cv2.GaussianBlur(noise, (0, 0), sigma_px / factor, borderType=cv2.BORDER_REFLECT)
    if factor > 1:
        noise = cv2.resize(noise, (shape[1], shape[0]), interpolation=cv2.INTER_CUBIC)
    return noise / max(float(noise.std()), 1e-12)


def paint_texture(cfg: SceneConfig, rng: np.random.Generator) -> np.ndarray:
    """Low-texture painted steel: a grey with smooth blotches of ``texture_contrast``."""
    texels_per_mm = 4
    h = int(cfg.beam_length_mm * texels_per_mm)
    w = 64
    noise = _smooth_noise((h, w), cfg.texture_feature_mm * texels_per_mm / 2, rng)
    albedo = cfg.paint_albedo * (1 + cfg.texture_contrast * noise)
    tint = np.array([1.0, 1.0, 0.97], dtype=np.float32)
    return _to_srgb8(np.clip(albedo[..., None] * tint, 0, 1))


def logo_texture(size: int = 512) -> np.ndarray:
    """A high-contrast logo (rings, a bar and letters): corners galore."""
    img = np.full((size, size, 3), 235, np.uint8)
    c = size // 2
    cv2.circle(img, (c, c), int(size * 0.46), (20, 40, 160), -1, cv2.LINE_AA)
    cv2.circle(img, (c, c), int(size * 0.36), (240, 240, 240), -1, cv2.LINE_AA)
    cv2.circle(img, (c, c), int(size * 0.30), (200, 30, 30), -1, cv2.LINE_AA)
    cv2.rectangle(img, (int(size * 0.15), int(size * 0.44)), (int(size * 0.85), int(size * 0.56)),
                  (250, 250, 250), -1)
    cv2.putText(img, "REF", (int(size * 0.22), int(size * 0.545)), cv2.FONT_HERSHEY_DUPLEX,
                size / 200, (10, 10, 10), max(2, size // 100), cv2.LINE_AA)
    return img


WALL_GREY = 0.35  # linear albedo of the wall's mean


def wall_texture(cfg: SceneConfig, rng: np.random.Generator,
                 shape: tuple[int, int] = (1536, 2560)) -> np.ndarray:
    """A lab wall: mid grey with multi-scale blotches and a few dark objects."""
    size = max(shape)
    base = WALL_GREY + cfg.background_contrast * 0.12 * (
        _smooth_noise(shape, 40, rng) + 0.6 * _smooth_noise(shape, 6, rng)
        + 0.4 * _smooth_noise(shape, 1.5, rng))
    img = np.repeat(base[..., None], 3, axis=2) * np.array([1.0, 0.98, 0.93], np.float32)
    for _ in range(60):
        y, x = rng.integers(0, shape[0]), rng.integers(0, shape[1])
        w, h = rng.integers(size // 80, size // 20, 2)
        # darker than the paint, so the beam stays visible; flat at zero contrast
        relative = cfg.background_contrast / SceneConfig.background_contrast
        shade = WALL_GREY + (float(rng.uniform(0.04, 0.25)) - WALL_GREY) * relative
        cv2.rectangle(img, (int(x), int(y)), (int(x + w), int(y + h)), (shade,) * 3, -1)
    return _to_srgb8(np.clip(img, 0, 1))


def distractor_atlas(contrast: float, tile: int = 128) -> np.ndarray:
    """Four wall fixtures side by side (sRGB8, tile x 4*tile): an anchor plate with
    a hex bolt, a QC sticker, a cable clip with its cable, a cross-hair marker.

    Dark parts have linear albedo ``WALL_GREY * (1 - contrast)``, bright parts
    ``WALL_GREY + (0.95 - WALL_GREY) * contrast``: at zero contrast only the
    fixtures' flat outline on the textured wall remains.
    """
    wall, dark, mid, bright = 0, 1, 2, 3  # drawn as indices (OpenCV draws text in 8 bits only)
    img = np.zeros((tile, 4 * tile), np.uint8)
    t = tile
    # anchor plate with a hex bolt
    cv2.rectangle(img, (4, 4), (t - 5, t - 5), mid, -1)
    hexagon = np.array([[t / 2 + 0.3 * t * np.cos(a), t / 2 + 0.3 * t * np.sin(a)]
                        for a in np.arange(6) * np.pi / 3], np.int32)
    cv2.fillConvexPoly(img, hexagon, dark)
    cv2.circle(img, (t // 2, t // 2), t // 8, bright, -1)
    # QC sticker: bright label, dark border, bar code and a line of text
    x0 = t
    cv2.rectangle(img, (x0 + 6, 16), (x0 + t - 7, t - 17), bright, -1)
    cv2.rectangle(img, (x0 + 6, 16), (x0 + t - 7, t - 17), dark, 3)
    for i, width in enumerate((3, 1, 2, 4, 1, 3, 2, 1, 3)):
        bx = x0 + 16 + 10 * i
        cv2.rectangle(img, (bx, 28), (bx + width, 60), dark, -1)
    cv2.putText(img, "QC 07", (x0 + 16, t - 30), cv2.FONT_HERSHEY_SIMPLEX, t / 170, dark, 2)
    # cable clip: a dark cable across a bright saddle
    x0 = 2 * t
    cv2.rectangle(img, (x0 + t // 2 - 6, 0), (x0 + t // 2 + 6, t - 1), dark, -1)
    cv2.rectangle(img, (x0 + 14, t // 2 - 18), (x0 + t - 15, t // 2 + 18), bright, -1)
    cv2.circle(img, (x0 + 24, t // 2), 6, dark, -1)
    cv2.circle(img, (x0 + t - 25, t // 2), 6, dark, -1)
    # cross-hair marker: a 2 x 2 checker in a bright square
    x0 = 3 * t
    cv2.rectangle(img, (x0 + 8, 8), (x0 + t - 9, t - 9), bright, -1)
    cv2.rectangle(img, (x0 + 20, 20), (x0 + t // 2, t // 2), dark, -1)
    cv2.rectangle(img, (x0 + t // 2, t // 2), (x0 + t - 21, t - 21), dark, -1)
    d, b = WALL_GREY * (1 - contrast), WALL_GREY + (0.95 - WALL_GREY) * contrast
    levels = {wall: WALL_GREY, dark: d, mid: 0.5 * (d + b), bright: b}
    albedo = np.array([levels[i] for i in range(4)])[img]
    return _to_srgb8(np.repeat(albedo[..., None], 3, axis=2))


def distractor_mesh(cfg: SceneConfig, centres_xz: np.ndarray, kinds: np.ndarray, plane_y_mm: float,
                    material) -> pyrender.Mesh:
    """Square fixtures of ``cfg.distractor_size_mm`` centred at ``centres_xz`` on the
    plane y = ``plane_y_mm``, facing the camera; ``kinds`` index the atlas tiles."""
    half = cfg.distractor_size_mm / 2
    n = len(centres_xz)
    dx = np.array([-half, half, half, -half])
    dz = np.array([-half, -half, half, half])
    pos = np.stack([centres_xz[:, :1] + dx, np.full((n, 4), plane_y_mm),
                    centres_xz[:, 1:] + dz], -1).reshape(-1, 3)
    tile_u = (np.asarray(kinds)[:, None] + np.array(UPRIGHT_UV)[None, :, 0]) / 4
    uv = np.stack([tile_u, np.broadcast_to(np.array(UPRIGHT_UV)[:, 1], (n, 4))], -1).reshape(-1, 2)
    base = 4 * np.arange(n, dtype=np.uint32)[:, None]
    idx = np.concatenate([base + np.array([0, 1, 2]), base + np.array([0, 2, 3])])
    prim = pyrender.Primitive(positions=pos.astype(np.float32),
                              normals=np.tile(np.float32([0, -1, 0]), (4 * n, 1)),
                              texcoord_0=uv.astype(np.float32), indices=idx.astype(np.uint32),
                              material=material)
    return pyrender.Mesh([prim])


def paper_texture(rng: np.random.Generator, size: int = 256) -> np.ndarray:
    fibre = 0.88 + 0.01 * _smooth_noise((size, size), 1.0, rng)
    return _to_srgb8(np.clip(np.repeat(fibre[..., None], 3, axis=2), 0, 1))


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    linear = np.asarray(linear, np.float64)
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)
    return np.round(np.clip(srgb, 0, 1) * 255).astype(np.uint8)


# Lighting is baked (Lambert, two directional lights + ambient) and rendered
# with pyrender's FLAT shader: its PBR shader costs 5x more on Mesa's software
# rasteriser and adds nothing for matte paint, paper and a wall. FLAT writes
# factor * texel in sRGB space, so the linear shading L enters as L**(1/2.2).
KEY_DIRECTION = np.array([-0.25, 1.0, -0.35]) / np.linalg.norm([-0.25, 1.0, -0.35])
FILL_DIRECTION = np.array([0.5, 1.0, 0.1]) / np.linalg.norm([0.5, 1.0, 0.1])


def shading(cfg: SceneConfig, normals: np.ndarray) -> np.ndarray:
    """sRGB-space colour factor for surfaces with (unit) ``normals`` (…, 3)."""
    n = np.asarray(normals, np.float64)
    lin = (cfg.ambient + cfg.light_intensity * np.clip(n @ -KEY_DIRECTION, 0, None)
           + cfg.fill_intensity * np.clip(n @ -FILL_DIRECTION, 0, None))
    return np.clip(lin, 0, 1) ** (1 / 2.2)


def material(texture: np.ndarray, roughness: float = 0.8,
              factor: float = 1.0) -> pyrender.MetallicRoughnessMaterial:
    tex = pyrender.Texture(source=texture, source_channels="RGB",
                           sampler=pyrender.Sampler(magFilter=9729, minFilter=9987))
    return pyrender.MetallicRoughnessMaterial(baseColorTexture=tex, metallicFactor=0.0,
                                              roughnessFactor=roughness,
                                              baseColorFactor=(factor, factor, factor, 1.0))


# pyrender uploads a texture image bottom row first (``np.flip(source, 0)``), so
# texture coordinate v = 0 is the image's *bottom* row and v = 1 its top: the
# OpenGL convention, not glTF's (trimesh flips v when it loads glTF/OBJ).
# Corners (bottom-left, bottom-right, top-right, top-left) therefore take
# (0, 0), (1, 0), (1, 1), (0, 1) to show an image upright.
UPRIGHT_UV = ((0, 0), (1, 0), (1, 1), (0, 1))


def quad_primitive(corners: np.ndarray, material, uv=UPRIGHT_UV):
    """Two-triangle quad; ``corners`` (4, 3) counter-clockwise seen from the front, starting
    bottom-left; the texture shows upright (image row 0 at the top edge)."""
    corners = np.asarray(corners, np.float32)
    normal = np.cross(corners[1] - corners[0], corners[3] - corners[0])
    normal = normal / np.linalg.norm(normal)
    return pyrender.Primitive(positions=corners, normals=np.tile(normal, (4, 1)),
                              texcoord_0=np.asarray(uv, np.float32),
                              indices=np.array([[0, 1, 2], [0, 2, 3]], np.uint32),
                              material=material)


def box_mesh(lo, hi, color) -> pyrender.Mesh:
    import trimesh
    box = trimesh.creation.box(extents=np.subtract(hi, lo))
    box.apply_translation((np.asarray(lo) + np.asarray(hi)) / 2)
    mat = pyrender.MetallicRoughnessMaterial(baseColorFactor=(*np.asarray(color) ** (1 / 2.2), 1.0),
                                             metallicFactor=0.2,
                                             roughnessFactor=0.6)
    return pyrender.Mesh.from_trimesh(box, material=mat, smooth=False)


# ----------------------------------------------------------------- the beam
class BeamMesh:
    """Builds the deformed beam (one continuous tube, four textured faces)."""

    def __init__(self, cfg: SceneConfig, material, logo_material=None, *,
                 logo_height_mm: float | None = None):
        self.cfg = cfg
        self.logo_height_mm = logo_height_mm or cfg.logo_height_mm or cfg.measure_height_mm
        n = int(np.ceil(cfg.beam_length_mm / cfg.ring_spacing_mm)) + 1
        self.z0 = np.linspace(0.0, cfg.beam_length_mm, n)
        self.material = material
        self.logo_material = logo_material
        t, w = cfg.beam_thickness_mm / 2, cfg.beam_width_mm / 2
        # (a, b) corners of the four faces, each face counter-clockwise outward:
        # front (y=-w, seen by the camera), right (+x), back (+y), left (-x).
        self.faces = [((-t, -w), (t, -w)), ((t, -w), (t, w)), ((t, w), (-t, w)), ((-t, w), (-t, -w))]
        self.face_width = [2 * t, 2 * w, 2 * t, 2 * w]
        idx = []
        for f in range(4):
            base = f * 2 * n
            k = np.arange(n - 1)
            v00, v01 = base + 2 * k, base + 2 * k + 1
            v10, v11 = base + 2 * (k + 1), base + 2 * (k + 1) + 1
            idx.append(np.stack([v00, v01, v11], 1))
            idx.append(np.stack([v00, v11, v10], 1))
        self.indices = np.concatenate(idx).astype(np.uint32)
        uv = []
        for f in range(4):
            # 4 texels/mm on a 64-texel-wide texture (repeats on the wide faces)
            u = np.tile([0.0, self.face_width[f] * 4 / 64], n)
            v = np.repeat(1.0 - self.z0 / cfg.beam_length_mm, 2)  # (random paint: any way up)
            uv.append(np.stack([u, v], 1))
        self.uv = np.concatenate(uv).astype(np.float32)

    def mesh(self, shapes: BeamShapes | None, t: float) -> pyrender.Mesh:
        cfg = self.cfg
        if shapes is None:
            xc, zc, th = np.zeros_like(self.z0), self.z0.copy(), np.zeros_like(self.z0)
        else:
            xc, zc, th = shapes.at(t, self.z0)
        c, s = np.cos(th), np.sin(th)
        pos, nrm = [], []
        for (a0, b0), (a1, b1) in self.faces:
            p0 = np.stack([xc + a0 * c, np.full_like(xc, b0), zc - a0 * s], 1)
            p1 = np.stack([xc + a1 * c, np.full_like(xc, b1), zc - a1 * s], 1)
            pos.append(np.stack([p0, p1], 1).reshape(-1, 3))
            # outward normal: the face direction rotated with the section
            da, db = a1 - a0, b1 - b0
            na, nb = db, -da  # (a, b) plane outward normal for CCW order seen from outside
            norm = np.hypot(na, nb)
            na, nb = na / norm, nb / norm
            n_world = np.stack([na * c, np.full_like(c, nb), -na * s], 1)
            nrm.append(np.repeat(n_world, 2, axis=0))
        normals = np.concatenate(nrm)
        shade = shading(cfg, normals)
        colors = np.concatenate([np.repeat(shade[:, None], 3, 1), np.ones((shade.size, 1))], 1)
        prim = pyrender.Primitive(positions=np.concatenate(pos).astype(np.float32),
                                  normals=normals.astype(np.float32),
                                  color_0=colors.astype(np.float32),
                                  texcoord_0=self.uv, indices=self.indices, material=self.material)
        prims = [prim]
        if self.logo_material is not None and cfg.logo:
            prims.append(self.logo_primitive(shapes, t))
        return pyrender.Mesh(prims)

    def logo_primitive(self, shapes: BeamShapes | None, t: float):
        cfg = self.cfg
        half = cfg.logo_size_mm / 2
        zl = self.logo_height_mm
        # plate glued to the back face, facing the camera (-y); it follows the
        # section at the logo height (rigid, small rotation theta about y)
        a = np.array([-half, half, half, -half])
        dz = np.array([-half, -half, half, half])
        y = cfg.beam_width_mm / 2 + 0.5
        if shapes is None:
            xc, zc, th = 0.0, zl, 0.0
        else:
            xs, zs, ths = shapes.at(t, np.array([zl]))
            xc, zc, th = xs[0], zs[0], ths[0]
        c, s = np.cos(th), np.sin(th)
        corners = np.stack([xc + a * c + dz * s, np.full(4, y), zc - a * s + dz * c], 1)
        return quad_primitive(corners, self.logo_material)


@functools.lru_cache(maxsize=4)
def _static_textures(beam_length_mm: float, texture_feature_mm: float, paint_albedo: float,
                     texture_contrast: float, background_contrast: float, seed: int
                     ) -> dict[str, np.ndarray]:
    """The scene's textures (read-only), cached: the wall alone takes ~0.5 s and a
    crop and a full-frame renderer of one clip share them."""
    cfg = SceneConfig(beam_length_mm=beam_length_mm, texture_feature_mm=texture_feature_mm,
                      paint_albedo=paint_albedo, texture_contrast=texture_contrast,
                      background_contrast=background_contrast)
    rng = np.random.default_rng([seed, 1])
    # The wall is stored upside down: quads used to show textures flipped (see
    # UPRIGHT_UV), and the trackers' accuracy depends on what the wall shows
    # around the beam (a dark patch behind it doubles deepflow's error), so the
    # fix of the logo's orientation keeps the wall the scenarios were measured on.
    out = {"paint": paint_texture(cfg, rng), "logo": logo_texture(),
           "wall": np.ascontiguousarray(wall_texture(cfg, rng)[::-1]), "paper": paper_texture(rng)}
    for texture in out.values():
        texture.flags.writeable = False
    return out


def build_static_scene(cfg: SceneConfig, *, camera_y_mm: float, aim_z_mm: float, seed: int,
                       distractors: tuple[np.ndarray, np.ndarray] | None = None
                       ) -> tuple[pyrender.Scene, dict[str, Any]]:
    """Scene with lights, wall, clamp (and the wall fixtures at ``distractors``:
    centres (n, 2) in world x, z and atlas kinds (n,)); returns it and the
    materials to reuse."""
    textures = _static_textures(cfg.beam_length_mm, cfg.texture_feature_mm, cfg.paint_albedo,
                                cfg.texture_contrast, cfg.background_contrast, seed)
    scene = pyrender.Scene(ambient_light=np.full(3, cfg.ambient), bg_color=np.zeros(4))
    facing = shading(cfg, np.array([0.0, -1.0, 0.0]))  # surfaces facing the camera
    paint = material(textures["paint"], roughness=0.7)  # shaded per vertex
    logo = material(textures["logo"], factor=facing)
    wall = material(textures["wall"], factor=facing)
    paper = material(textures["paper"], roughness=0.95, factor=facing)
    # the wall: a quad facing the camera, wide enough to fill the field of view
    yb = cfg.background_distance_mm
    half_w, half_h = 0.75 * (yb - camera_y_mm), 0.45 * (yb - camera_y_mm)  # > the 4K field of view
    corners = np.array([[-half_w, yb, aim_z_mm - half_h], [half_w, yb, aim_z_mm - half_h],
                        [half_w, yb, aim_z_mm + half_h], [-half_w, yb, aim_z_mm + half_h]])
    scene.add(pyrender.Mesh([quad_primitive(corners, wall)]), name="wall")  # ~1.1 texel/mm
    w = cfg.beam_width_mm
    scene.add(box_mesh((-40, -w / 2 - 10, -80), (-cfg.beam_thickness_mm / 2, w / 2 + 10, 60),
                       (0.25, 0.25, 0.27)), name="clamp_left")
    scene.add(box_mesh((cfg.beam_thickness_mm / 2, -w / 2 - 10, -80), (40, w / 2 + 10, 60),
                       (0.25, 0.25, 0.27)), name="clamp_right")
    scene.add(box_mesh((-200, -200, -120), (200, 200, -80), (0.3, 0.3, 0.3)), name="base")
    if distractors is not None and len(distractors[0]):
        fixtures = material(distractor_atlas(cfg.distractor_contrast), factor=facing)
        scene.add(distractor_mesh(cfg, *distractors, yb - 1.0, fixtures), name="distractors")
    return scene, {"paint": paint, "logo": logo, "paper": paper}

