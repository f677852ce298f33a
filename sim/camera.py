"""The phone camera: pinhole + Brown-Conrady lens, exposure, noise, gamma, 8 bits.

Image convention (``docs/formats.md``): x right, y down, pixel centres at
integer coordinates; the sensor is ``width x height`` full-resolution pixels
and a *crop* is a window ``{x, y, width, height}`` of it.

Distortion is applied exactly: for every output (distorted) pixel we solve
``distort(x_u) = x_d`` by Newton iteration to machine precision, then sample
an undistorted pinhole render with ``cv2.remap`` using fixed-point maps that
depend only on the *global* pixel position, so a crop gets the same maps as the
full frame. Noise is a counter-based hash of (seed, frame, global pixel,
channel) for the same reason.

Exposure (:class:`SubframeSampling`): the exposure of every sensor row is split
into bins of a grid shared by all rows; a sub-frame is rendered at each bin
centre and every row averages the bins its exposure overlaps, weighted by the
overlap, so a row's exposure centroid is exact and the rolling-shutter skew is
continuous in the row (not stair-stepped at the sub-frame spacing).

Sensor (:func:`sensor_readout`): electrons = full well x exposure-normalised
irradiance; shot noise (Poisson, Gaussian approximation) and read noise are
added in electrons, the well clips; then the analog gain (ISO) amplifies
signal and noise together; gamma; 8 bits.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from sim.config import section_dataclass

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
    crop_center_z_mm: float | None = None  # height the crop centres on; None: the measurement point
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
    # tripod shake: band-limited random rotation + translation of the camera (sim.disturbance)
    shake: bool = False
    shake_rotation_mrad: float = 0.05     # RMS per camera axis
    shake_translation_mm: float = 0.02    # RMS per camera axis
    shake_band_hz: tuple[float, float] = (2.0, 15.0)
    # thermal drift of the mount: rotation/translation approaching these values
    drift: bool = False
    drift_rotation_mrad: tuple[float, float, float] = (0.5, 1.0, 0.0)  # about camera x, y, z
    drift_translation_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)  # camera x right, y down, z fwd
    drift_time_constant_s: float = 30.0

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> CameraConfig:
        cfg = section_dataclass(cls, dict(config.get("camera") or {}), "camera")
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
        if cfg.shake_rotation_mrad < 0 or cfg.shake_translation_mm < 0:
            raise ValueError(f"camera.shake_rotation_mrad / shake_translation_mm must be >= 0, got "
                             f"{cfg.shake_rotation_mrad!r} / {cfg.shake_translation_mm!r}")
        band = cfg.shake_band_hz
        if len(band) != 2 or not 0 < band[0] < band[1]:
            raise ValueError(f"camera.shake_band_hz must be [low, high] with 0 < low < high, "
                             f"got {list(band)!r}")
        for key in ("drift_rotation_mrad", "drift_translation_mm"):
            if len(getattr(cfg, key)) != 3:
                raise ValueError(f"camera.{key} must have 3 entries (camera x, y, z), got "
                                 f"{list(getattr(cfg, key))!r}")
        if cfg.drift_time_constant_s <= 0:
            raise ValueError(f"camera.drift_time_constant_s must be > 0, got "
                             f"{cfg.drift_time_constant_s!r}")
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


# A rigid motion of the camera away from its nominal pose: ``(R, T)`` with the
# rotation R (3 x 3) and the camera centre T (mm), both in the *nominal* OpenCV
# camera frame (x right, y down, z forward). See sim.disturbance.CameraMotion.
Motion = tuple[np.ndarray, np.ndarray]


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

    # world from the nominal OpenCV camera frame: x_cv = world x, y_cv = world -z
    # (image down), z_cv = world +y (the viewing direction)
    _WORLD_FROM_CV = np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]])

    def pose(self, motion: Motion | None = None) -> np.ndarray:
        """pyrender camera pose (camera -z = world +y, camera +y = world +z), moved by ``motion``."""
        rot, centre = (np.eye(3), np.zeros(3)) if motion is None else motion
        pose = np.eye(4)
        # pyrender's camera axes are OpenCV's with y and z flipped
        pose[:3, :3] = self._WORLD_FROM_CV @ rot @ np.diag([1.0, -1.0, -1.0])
        pose[:3, 3] = self._WORLD_FROM_CV @ centre + (0, self.camera_y_mm, self.aim_z_mm)
        return pose

    def world_to_camera(self, points: np.ndarray, motion: Motion | None = None) -> np.ndarray:
        """OpenCV camera frame (x right, y down, z forward) of the nominal or moved camera."""
        p = np.asarray(points, np.float64)
        nominal = np.stack([p[..., 0], -(p[..., 2] - self.aim_z_mm), p[..., 1] - self.camera_y_mm], -1)
        if motion is None:
            return nominal
        rot, centre = motion
        return (nominal - centre) @ rot  # R^T (X - T) for row vectors

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r2 = x * x + y * y
        radial = 1 + self.k1 * r2 + self.k2 * r2 * r2
        xd = x * radial + 2 * self.p1 * x * y + self.p2 * (r2 + 2 * x * x)
        yd = y * radial + self.p1 * (r2 + 2 * y * y) + 2 * self.p2 * x * y
        return xd, yd

    def undistort(self, xd: np.ndarray, yd: np.ndarray, iterations: int = 8
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Exact inverse of :meth:`distort` (Newton from ``(xd, yd)``).

        Newton doubles the correct digits per step: a phone lens converges to the
        last bit in 4-5 steps. The count is fixed (no data-dependent early stop),
        so a pixel gets the same bits whichever window it is computed in.
        """
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
            x = x - (d * fx - b * fy) / det
            y = y - (a * fy - b * fx) / det
        rx, ry = self.distort(x, y)
        residual = max(np.abs(rx - xd).max(initial=0), np.abs(ry - yd).max(initial=0))
        if not residual < 1e-12:
            raise ValueError(f"lens distortion (k1={self.k1}, k2={self.k2}) cannot be inverted "
                             f"over the sensor (residual {residual:.2g}): lower |k1|, |k2|")
        return x, y

    def project(self, points: np.ndarray, motion: Motion | None = None) -> np.ndarray:
        """World points (…, 3) in mm -> distorted sensor pixels (…, 2)."""
        c = self.world_to_camera(points, motion)
        xd, yd = self.distort(c[..., 0] / c[..., 2], c[..., 1] / c[..., 2])
        return np.stack([self.fx * xd + self.cx, self.fy * yd + self.cy], -1)

    def pixel_rays(self, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted pixels -> undistorted normalised coordinates."""
        return self.undistort((np.asarray(u, np.float64) - self.cx) / self.fx,
                              (np.asarray(v, np.float64) - self.cy) / self.fy)

    def backproject_to_plane_y(self, u, v, plane_y_mm: float,
                               motion: Motion | None = None) -> np.ndarray:
        """World points where the rays of pixels (u, v) meet the plane y = plane_y_mm."""
        x, y = self.pixel_rays(u, v)
        return self.rays_to_plane_y(x, y, plane_y_mm, motion)

    def rays_to_plane_y(self, x: np.ndarray, y: np.ndarray, plane_y_mm: float,
                        motion: Motion | None = None) -> np.ndarray:
        """World points where normalised rays ``(x, y, 1)`` meet the plane y = plane_y_mm."""
        depth = plane_y_mm - self.camera_y_mm          # the plane in the nominal camera frame
        ray = np.stack([x, y, np.ones_like(x)], -1)
        if motion is None:
            pts = ray * depth
        else:
            rot, centre = motion
            ray = ray @ rot.T
            pts = centre + ray * ((depth - centre[2]) / ray[..., 2])[..., None]
        return np.stack([pts[..., 0], self.camera_y_mm + pts[..., 2], self.aim_z_mm - pts[..., 1]], -1)

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

    # ------------------------------------------------------------ exposure
    def row_times(self, rows: np.ndarray) -> np.ndarray:
        """Exposure start of sensor rows relative to the frame start (rolling shutter)."""
        return np.asarray(rows, np.float64) * (self.cfg.rolling_shutter_s / self.height)

    def sampling(self, subframes: int) -> SubframeSampling:
        """Sub-frames of a frame whose exposure is split into ``subframes`` bins."""
        cfg = self.cfg
        dt = cfg.exposure_s / subframes
        last_start = float(self.row_times(self.height - 1))
        n_bins = int(np.ceil((last_start + cfg.exposure_s) / dt - 1e-9))
        return SubframeSampling(times=(np.arange(n_bins) + 0.5) * dt, bin_s=dt,
                                exposure_s=cfg.exposure_s,
                                row_period_s=cfg.rolling_shutter_s / self.height)


@dataclass(frozen=True)
class SubframeSampling:
    """Sub-frame times of one frame and each sensor row's weight on them.

    Bin k spans ``[k, k + 1) * bin_s`` after the frame start and is rendered at
    its centre ``times[k]``. A row exposes ``[start, start + exposure_s)`` with
    ``start = row * row_period_s``; its weight on bin k is the overlap / exposure.
    With a global shutter every row weighs ``n`` bins by ``1/n``; with a rolling
    shutter a row's first and last bins get fractional weights, which makes its
    exposure centroid exactly ``start + exposure_s / 2``.
    """

    times: np.ndarray
    bin_s: float
    exposure_s: float
    row_period_s: float

    @property
    def global_shutter(self) -> bool:
        return self.row_period_s == 0

    def weights(self, rows: np.ndarray) -> np.ndarray:
        """Weights (len(rows), K) of integer sensor ``rows``; each row sums to 1."""
        start = np.asarray(rows, np.float64)[:, None] * self.row_period_s
        lo = np.arange(self.times.size)[None, :] * self.bin_s
        overlap = np.minimum(start + self.exposure_s, lo + self.bin_s) - np.maximum(start, lo)
        w = np.clip(overlap, 0, None) / self.exposure_s
        w[w < 1e-9] = 0.0  # rounding slivers would cost a render for nothing
        return w


class AutoExposure:
    """A phone's auto-exposure loop: meter the scene, steer the gain towards
    ``ae_target / meter`` with a first-order lag of ``ae_time_constant_s``.

    :meth:`step` takes the meter of frame i (mean exposure-normalised
    irradiance of the whole field of view at gain 1) and returns frame i's
    gain, which was set from frames 0..i-1 (the phone exposes the next frame
    from the last one it saw); frame 0 starts converged. With
    ``auto_exposure: false`` the gain stays at frame 0's (exposure lock).
    """

    def __init__(self, cfg: CameraConfig):
        self.cfg = cfg
        self.alpha = 1 - np.exp(-1 / (cfg.fps * cfg.ae_time_constant_s))
        self.gain: float | None = None

    def target(self, meter: float) -> float:
        return min(self.cfg.ae_target / max(meter, 1e-6), self.cfg.ae_max_gain)

    def step(self, meter: float) -> float:
        target = self.target(meter)
        if self.gain is None:
            self.gain = target
        gain = self.gain
        if self.cfg.auto_exposure:
            self.gain = gain + self.alpha * (target - gain)
        return gain


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
    return cv2.LUT(np.ascontiguousarray(img), _SRGB_TO_LINEAR16)


_GAUSS_BITS = 16
_GAUSS_TABLE: np.ndarray | None = None
_ENCODE_BITS = 20
_ENCODE_LUTS: dict[float, np.ndarray] = {}


def _gauss_table() -> np.ndarray:
    """N(0, 1) quantiles at the centres of 2**16 equal-probability bins."""
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


def sensor_readout(linear: np.ndarray, gain: float, cfg: CameraConfig, *, seed: int, frame: int,
                   window: Window) -> np.ndarray:
    """Exposure-normalised irradiance (float32, 1 = full well) -> 8-bit gamma-encoded RGB.

    Per pixel and channel: ``e = full_well * linear`` electrons; shot noise
    (Gaussian approximation of Poisson, variance ``e``) plus read noise
    (variance ``read_noise_e**2``); the well clips at ``full_well``; the analog
    gain (ISO) amplifies signal and noise alike; ``gain * e / full_well`` is
    clipped to [0, 1], gamma-encoded and quantised to 8 bits. So at gain g the
    output variance grows with its mean as ``g / full_well`` (photon transfer).
    The noise of a pixel is a counter-based hash of (seed, frame, global pixel,
    channel): the same in a crop as in the full frame.
    """
    linear = np.ascontiguousarray(linear, dtype=np.float32)
    key = np.uint64(_splitmix64(np.uint64((seed & 0xFFFFFFFF) << 32 | (frame & 0xFFFFFFFF))))
    out = np.empty(linear.shape, np.uint8)
    _readout_kernel(linear, np.float32(gain), bool(cfg.noise), np.float32(cfg.full_well_e),
                    np.float32(cfg.read_noise_e ** 2), key, window.y, window.x,
                    cfg.width_px, _gauss_table(), _encode_lut(cfg.gamma), out)
    return out


def _make_kernels():
    import numba

    @numba.njit(cache=True)
    def splitmix64(z):
        """SplitMix64 finaliser (Steele et al. 2014): a well-mixed 64-bit hash of ``z``."""
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        return z ^ (z >> np.uint64(31))

    @numba.njit(cache=True, parallel=True, fastmath=False)
    def kernel(linear, gain, noise, full_well, read_var, key, y0, x0, sensor_width, gauss,
               lut, out):
        h, w, ch = linear.shape
        top = np.float32((1 << 20) - 1)
        zero = np.float32(0)
        for r in numba.prange(h):
            for c in range(w):
                base = np.uint64((y0 + r) * sensor_width + (x0 + c)) * np.uint64(ch)
                for k in range(ch):
                    electrons = max(linear[r, c, k], zero) * full_well
                    if noise:
                        z = splitmix64((base + np.uint64(k)) ^ key)
                        sigma = np.sqrt(electrons + read_var)
                        electrons = electrons + sigma * gauss[np.int64(z >> np.uint64(48))]
                    electrons = min(max(electrons, zero), full_well)  # the well is full
                    sig = min(max(gain * electrons / full_well, zero), np.float32(1))
                    out[r, c, k] = lut[np.int64(np.rint(sig * top))]

    return splitmix64, kernel


_splitmix64, _readout_kernel = _make_kernels()
