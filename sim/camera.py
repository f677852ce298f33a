"""The phone camera: pinhole + Brown-Conrady lens, exposure, noise, gamma, 8 bits.

Image convention (``docs/formats.md``): x right, y down, pixel centres at
integer coordinates; the sensor is ``width x height`` full-resolution pixels
and a *crop* is a window ``{x, y, width, height}`` of it.

Distortion is applied exactly: for every output (distorted) pixel we solve
``distort(x_u) = x_d`` by Newton iteration to machine precision, then sample
an undistorted pinhole render with ``cv2.remap`` using fixed-point maps that
depend only on the *global* pixel position, so a crop reproduces the full
frame's pixels bit for bit. Noise is a counter-based hash of (seed, frame,
global pixel, channel) for the same reason.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from sim.scene import _build

REMAP_BITS = 5  # cv2.INTER_BITS: remap's fixed-point sub-pixel resolution (1/32 px)


@dataclass(frozen=True)
class CameraConfig:
    """``camera`` config section. Defaults: Galaxy S9+ 4K60 at 1 m (paper Sec. 4.1)."""

    width_px: int = 3840
    height_px: int = 2160
    fps: float = 60.0
    distance_mm: float = 1000.0      # lens to the beam's visible (front) face
    fx_px: float = 2800.0            # 2.8 px/mm at the beam face
    fy_px: float | None = None       # None: square pixels
    cx_px: float | None = None       # None: sensor centre
    cy_px: float | None = None
    k1: float = 0.06
    k2: float = -0.12
    p1: float = 2e-4
    p2: float = -1e-4
    aim_z_mm: float = 500.0          # height of the optical axis (phone framing the beam)
    crop_width_px: int = 800
    crop_height_px: int = 400
    exposure_s: float = 1 / 120
    motion_blur_subframes: int = 4
    rolling_shutter_s: float = 0.0   # full-sensor row read-out time; 0: global shutter
    start_offset_s: float = 0.0      # sim time of camera frame 0
    noise: bool = True
    full_well_e: float = 6000.0
    read_noise_e: float = 3.0
    gamma: float = 2.2
    auto_exposure: bool = True
    ae_target: float = 0.18
    ae_time_constant_s: float = 0.25
    ae_max_gain: float = 4.0
    ae_metering_width_px: int = 192
    supersample: int = 1             # render at this factor and area-average (on top of 4x MSAA)

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> CameraConfig:
        cfg = _build(cls, dict(config.get("camera") or {}), "camera")
        for key in ("width_px", "height_px", "fps", "distance_mm", "fx_px", "exposure_s",
                    "motion_blur_subframes", "full_well_e", "gamma", "ae_target",
                    "ae_time_constant_s", "ae_max_gain", "ae_metering_width_px", "supersample",
                    "crop_width_px", "crop_height_px"):
            if getattr(cfg, key) <= 0:
                raise ValueError(f"camera.{key} must be > 0, got {getattr(cfg, key)!r}")
        if cfg.exposure_s > 1 / cfg.fps:
            raise ValueError(f"camera.exposure_s={cfg.exposure_s!r} exceeds the frame time "
                             f"1/fps={1 / cfg.fps:.6f} s")
        if cfg.rolling_shutter_s < 0 or cfg.rolling_shutter_s > 1 / cfg.fps:
            raise ValueError(f"camera.rolling_shutter_s must be in [0, 1/fps], got "
                             f"{cfg.rolling_shutter_s!r}")
        if cfg.crop_width_px > cfg.width_px or cfg.crop_height_px > cfg.height_px:
            raise ValueError(f"camera.crop {cfg.crop_width_px}x{cfg.crop_height_px} is larger "
                             f"than the sensor {cfg.width_px}x{cfg.height_px}")
        return cfg


@dataclass(frozen=True)
class Window:
    """A rectangle of sensor pixels ``[x, x+width) x [y, y+height)``."""

    x: int
    y: int
    width: int
    height: int

    def as_dict(self) -> dict[str, int]:
        return {"x": self.x, "y": self.y, "width": self.width, "height": self.height}


class CameraModel:
    """Pinhole + Brown-Conrady camera at ``(0, camera_y_mm, aim_z_mm)`` looking along +y."""

    def __init__(self, cfg: CameraConfig, *, camera_y_mm: float):
        self.cfg = cfg
        self.width, self.height = cfg.width_px, cfg.height_px
        self.fx = cfg.fx_px
        self.fy = cfg.fy_px if cfg.fy_px is not None else cfg.fx_px
        self.cx = cfg.cx_px if cfg.cx_px is not None else (cfg.width_px - 1) / 2
        self.cy = cfg.cy_px if cfg.cy_px is not None else (cfg.height_px - 1) / 2
        self.k1, self.k2, self.p1, self.p2 = cfg.k1, cfg.k2, cfg.p1, cfg.p2
        self.camera_y_mm = camera_y_mm
        self.aim_z_mm = cfg.aim_z_mm

    # ------------------------------------------------------------ geometry
    @property
    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0, self.cx], [0, self.fy, self.cy], [0, 0, 1.0]])

    @property
    def dist(self) -> np.ndarray:
        """OpenCV order ``(k1, k2, p1, p2, k3)``."""
        return np.array([self.k1, self.k2, self.p1, self.p2, 0.0])

    def pose(self) -> np.ndarray:
        """pyrender camera pose (camera -z = world +y, camera +y = world +z)."""
        pose = np.eye(4)
        pose[:3, 0] = (1, 0, 0)
        pose[:3, 1] = (0, 0, 1)
        pose[:3, 2] = (0, -1, 0)
        pose[:3, 3] = (0, self.camera_y_mm, self.aim_z_mm)
        return pose

    def world_to_camera(self, points: np.ndarray) -> np.ndarray:
        """OpenCV camera frame (x right, y down, z forward)."""
        p = np.asarray(points, np.float64)
        return np.stack([p[..., 0], -(p[..., 2] - self.aim_z_mm), p[..., 1] - self.camera_y_mm], -1)

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = x * x + y * y
        radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 20
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Exact inverse of :meth:`distort` (Newton, converges to ~1e-15)."""
        xd = np.asarray(xd, np.float64)
        yd = np.asarray(yd, np.float64)
        x, y = xd.copy(), yd.copy()
        k1, k2, p1, p2 = self.k1, self.k2, self.p1, self.p2
        for _ in range(iterations):
            r2 = x * x + y * y
            radial = 1 + k1 * r2 + k2 * r2 * r2
            drad = 2 * (k1 + 2 * k2 * r2)
            fx = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x) - xd
            fy = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y - yd
            a = radial + x * x * drad + 2 * p1 * y + 6 * p2 * x
            b = x * y * drad + 2 * p1 * x + 2 * p2 * y
            d = radial + y * y * drad + 6 * p1 * y + 2 * p2 * x
            det = a * d - b * b
            step_x = (d * fx - b * fy) / det
            step_y = (a * fy - b * fx) / det
            x = x - step_x
            y = y - step_y
            if max(np.abs(step_x).max(initial=0), np.abs(step_y).max(initial=0)) < 1e-16:
                break  # converged to the last bit (Newton doubles the digits per step)
        return x, y

    def project(self, points: np.ndarray) -> np.ndarray:
        """World points (…, 3) in mm -> distorted sensor pixels (…, 2)."""
        c = self.world_to_camera(points)
        xd, yd = self.distort(c[..., 0] / c[..., 2], c[..., 1] / c[..., 2])
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], -1)

    def project_undistorted(self, points: np.ndarray) -> np.ndarray:
        c = self.world_to_camera(points)
        return np.stack([self.fx * c[..., 0] / c[..., 2] + self.cx,
                         self.fy * c[..., 1] / c[..., 2] + self.cy], -1)

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted pixels -> undistorted normalised coordinates."""
        return self.undistort((np.asarray(u, np.float64) - self.cx) / self.fx,
                              (np.asarray(v, np.float64) - self.cy) / self.fy)

    def backproject_to_plane_y(self, u, v, plane_y_mm: float) -> np.ndarray:
        """World points where the rays of pixels (u, v) meet the plane y = plane_y_mm."""
        x, y = self.pixel_rays(u, v)
        depth = plane_y_mm - self.camera_y_mm
        return np.stack([x * depth, np.full_like(x, plane_y_mm), self.aim_z_mm - y * depth], -1)

    def mm_per_px_at(self, plane_y_mm: float) -> float:
        return (plane_y_mm - self.camera_y_mm) / self.fx

    # ------------------------------------------------------------ windows
    def crop_around(self, u: float, v: float, width: int | None = None,
                    height: int | None = None) -> Window:
        width = width or self.cfg.crop_width_px
        height = height or self.cfg.crop_height_px
        width, height = width - width % 2, height - height % 2  # yuv420 needs even sizes
        x = int(np.clip(round(u - width / 2), 0, self.width - width))
        y = int(np.clip(round(v - height / 2), 0, self.height - height))
        return Window(x, y, width, height)

    def full_window(self) -> Window:
        return Window(0, 0, self.width, self.height)

    def remap_plan(self, window: Window, margin: int = 3) -> RemapPlan:
        """Undistorted render window and fixed-point remap maps for a sensor window."""
        u = np.arange(window.x, window.x + window.width, dtype=np.float64)
        v = np.arange(window.y, window.y + window.height, dtype=np.float64)
        uu, vv = np.meshgrid(u, v)
        x, y = self.pixel_rays(uu, vv)
        us = self.fx * x + self.cx
        vs = self.fy * y + self.cy
        # fixed point of the global undistorted position: identical for any window
        ufix = np.rint(us * (1 << REMAP_BITS)).astype(np.int64)
        vfix = np.rint(vs * (1 << REMAP_BITS)).astype(np.int64)
        x0 = int(np.floor(us.min())) - margin
        y0 = int(np.floor(vs.min())) - margin
        x1 = int(np.ceil(us.max())) + margin + 1
        y1 = int(np.ceil(vs.max())) + margin + 1
        ufix -= x0 << REMAP_BITS
        vfix -= y0 << REMAP_BITS
        mask = (1 << REMAP_BITS) - 1
        map1 = np.stack([ufix >> REMAP_BITS, vfix >> REMAP_BITS], -1).astype(np.int16)
        map2 = (((vfix & mask) << REMAP_BITS) | (ufix & mask)).astype(np.uint16)
        return RemapPlan(window=window, render=Window(x0, y0, x1 - x0, y1 - y0),
                         map1=map1, map2=map2)

    def render_intrinsics(self, render: Window, supersample: int = 1) -> tuple[float, ...]:
        """pyrender IntrinsicsCamera (fx, fy, cx, cy) for an undistorted window.

        pyrender puts pixel *edges* at integers (centre of pixel j at j + 0.5),
        we put centres at integers: hence the +0.5. With supersampling ``s``,
        sub-pixel j of the window has its centre at ``x0 - 0.5 + (j + 0.5)/s``.
        """
        s = supersample
        cx = (self.cx - render.x + 0.5) * s
        cy = (self.cy - render.y + 0.5) * s
        return self.fx * s, self.fy * s, cx, cy

    def row_times(self, rows: np.ndarray) -> np.ndarray:
        """Exposure start of sensor rows relative to the frame start (rolling shutter)."""
        return np.asarray(rows, np.float64) * (self.cfg.rolling_shutter_s / self.height)

    def exposure_samples(self, window: Window) -> tuple[np.ndarray, np.ndarray]:
        """Sub-frame times (relative to frame start) and per-row weights (rows, samples).

        Samples sit on a global grid of step ``exposure / n``; every row
        averages the ``n`` samples inside its own exposure window, so crops and
        full frames weight the same rows identically.
        """
        n = self.cfg.motion_blur_subframes
        dt = self.cfg.exposure_s / n
        rows = np.arange(window.y, window.y + window.height)
        start = self.row_times(rows)
        first = np.ceil(start / dt - 0.5 - 1e-9).astype(np.int64)  # first k with (k+.5)dt >= start
        k = np.arange(first.min(), first.max() + n)
        times = (k + 0.5) * dt
        weights = ((k[None, :] >= first[:, None]) & (k[None, :] < first[:, None] + n)) / n
        return times, weights.astype(np.float32)

    def sample_weights_for_rows(self, rows_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Sub-frame times (n per point) for points at (fractional) sensor rows."""
        n = self.cfg.motion_blur_subframes
        dt = self.cfg.exposure_s / n
        start = self.row_times(np.rint(rows_px))
        first = np.ceil(start / dt - 0.5 - 1e-9).astype(np.int64)
        return (first[..., None] + np.arange(n) + 0.5) * dt, np.full(n, 1 / n)


@dataclass
class RemapPlan:
    window: Window   # output (distorted) sensor window
    render: Window   # undistorted window to render
    map1: np.ndarray
    map2: np.ndarray

    def apply(self, undistorted: np.ndarray) -> np.ndarray:
        if undistorted.shape[:2] != (self.render.height, self.render.width):
            raise ValueError(f"render is {undistorted.shape[1]}x{undistorted.shape[0]}, "
                             f"expected {self.render.width}x{self.render.height}")
        return cv2.remap(undistorted, self.map1, self.map2, cv2.INTER_LINEAR,
                         borderMode=cv2.BORDER_REPLICATE)


# ----------------------------------------------------------------- sensor
_SRGB_TO_LINEAR16 = np.round(
    65535 * np.where(np.arange(256) / 255 <= 0.04045, np.arange(256) / 255 / 12.92,
                     ((np.arange(256) / 255 + 0.055) / 1.055) ** 2.4)).astype(np.uint16)


def srgb8_to_linear16(img: np.ndarray) -> np.ndarray:
    """pyrender writes sRGB-ish 8-bit colour; undo it to linear radiance (16 bit)."""
    return _SRGB_TO_LINEAR16[img]


_GAUSS_BITS = 16
_GAUSS_TABLE: np.ndarray | None = None
_ENCODE_BITS = 20
_ENCODE_LUTS: dict[float, np.ndarray] = {}


def _gauss_table() -> np.ndarray:
    global _GAUSS_TABLE
    if _GAUSS_TABLE is None:
        from scipy.special import ndtri
        p = (np.arange(1 << _GAUSS_BITS) + 0.5) / (1 << _GAUSS_BITS)
        _GAUSS_TABLE = ndtri(p).astype(np.float32)
    return _GAUSS_TABLE


def _encode_lut(gamma: float) -> np.ndarray:
    if gamma not in _ENCODE_LUTS:
        lin = np.arange(1 << _ENCODE_BITS) / ((1 << _ENCODE_BITS) - 1)
        _ENCODE_LUTS[gamma] = np.round(255 * lin ** (1 / gamma)).astype(np.uint8)
    return _ENCODE_LUTS[gamma]


def _splitmix64(z: np.ndarray) -> np.ndarray:
    z = z + np.uint64(0x9E3779B97F4A7C15)
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def standard_normal_at(seed: int, frame: int, window: Window, sensor_width: int,
                       channels: int = 3) -> np.ndarray:
    """Seeded N(0, 1) field indexed by global pixel: the same value for a pixel
    in any crop (a counter-based generator, like Philox, but per element)."""
    rows = np.arange(window.y, window.y + window.height, dtype=np.uint64)
    cols = np.arange(window.x, window.x + window.width, dtype=np.uint64)
    idx = (rows[:, None, None] * np.uint64(sensor_width) + cols[None, :, None]) * np.uint64(channels) \
        + np.arange(channels, dtype=np.uint64)[None, None, :]
    key = _splitmix64(np.array([(seed & 0xFFFFFFFF) << 32 | (frame & 0xFFFFFFFF)], np.uint64))
    h = _splitmix64(idx ^ key)
    return _gauss_table()[(h >> np.uint64(64 - _GAUSS_BITS)).astype(np.int64)]


def sensor_readout(linear: np.ndarray, gain: float, cfg: CameraConfig, *, seed: int, frame: int,
                   window: Window) -> np.ndarray:
    """Linear radiance (float32, 0..1 at gain 1) -> 8-bit gamma-encoded RGB.

    Photon noise (Gaussian approximation of Poisson, variance = electrons),
    read noise, clipping at full well, gamma, 8-bit quantisation. The noise of
    a pixel depends only on (seed, frame, global pixel, channel).
    """
    linear = np.ascontiguousarray(linear, dtype=np.float32)
    key = int(_splitmix64(np.array([(seed & 0xFFFFFFFF) << 32 | (frame & 0xFFFFFFFF)],
                                   np.uint64))[0])
    out = np.empty(linear.shape, np.uint8)
    _readout_kernel(linear, np.float32(gain), bool(cfg.noise), np.float32(cfg.full_well_e),
                    np.float32(cfg.read_noise_e ** 2), np.uint64(key), window.y, window.x,
                    cfg.width_px, _gauss_table(), _encode_lut(cfg.gamma), out)
    return out


def _make_kernel():
    import numba

    @numba.njit(cache=True, parallel=False, fastmath=False)
    def kernel(linear, gain, noise, full_well, read_var, key, y0, x0, sensor_width, gauss,
               lut, out):
        h, w, ch = linear.shape
        top = np.float32((1 << 20) - 1)
        for r in range(h):
            for c in range(w):
                base = np.uint64((y0 + r) * sensor_width + (x0 + c)) * np.uint64(ch)
                for k in range(ch):
                    sig = linear[r, c, k] * gain
                    if noise:
                        z = (base + np.uint64(k)) ^ key
                        z = z + np.uint64(0x9E3779B97F4A7C15)
                        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
                        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
                        z = z ^ (z >> np.uint64(31))
                        e = max(sig, np.float32(0)) * full_well
                        sigma = np.sqrt(e + read_var) / full_well
                        sig = sig + sigma * gauss[np.int64(z >> np.uint64(48))]
                    sig = min(max(sig, np.float32(0)), np.float32(1))
                    out[r, c, k] = lut[np.int64(np.rint(sig * top))]
    return kernel


_readout_kernel = _make_kernel()
