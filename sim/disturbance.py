"""Field conditions beyond the paper: tripod shake, thermal drift, flickering light.

Each is a deterministic function of the camera clock drawn from the config's
seed, so a crop, the full frame, the auto-exposure meter and the ground truth
all see the same disturbance. All are off by default:

* ``camera.shake``: the camera vibrates (band-limited random rotation and
  translation, ``shake_band_hz``, RMS ``shake_rotation_mrad`` /
  ``shake_translation_mm`` per camera axis), as on a tripod on a floor that
  people walk on.
* ``camera.drift``: the mount creeps (thermal drift): rotation and translation
  approach ``drift_rotation_mrad`` / ``drift_translation_mm`` as
  ``1 - exp(-t / drift_time_constant_s)``.
* ``scene.flicker``: mains lighting; intensity ``1 + flicker_depth * cos(2 pi
  flicker_hz t + phase)`` (``flicker_hz`` is twice the mains frequency: 100 Hz
  in Europe, 120 Hz in America). At 60 fps, 100 Hz aliases to a 20 Hz beat of
  the frame brightness; with a rolling shutter it draws moving bands.
* ``scene.clouds``: daylight through a window; a smooth random relative
  change of RMS ``cloud_depth`` with periods from ``cloud_time_scale_s`` up.
* ``scene.light_drift``: a slow linear change of ``light_drift_per_min``.

Camera motions are rigid motions ``(R, T)`` of the camera in its nominal
OpenCV frame (x right, y down, z forward): the rotation vector is in radians
about those axes (about x tilts the view: the image moves vertically; about y
pans it), T is the camera centre's displacement in mm.
"""

from __future__ import annotations

import cv2
import numpy as np

from sim.camera import CameraConfig, Motion


class RandomSignal:
    """Band-limited random signal, unit RMS per channel: a sum of ``components``
    cosines with frequencies uniform in ``band_hz`` and random phases.

    A sum of many random-phase cosines is near Gaussian with a flat spectrum
    over the band, and it can be evaluated and averaged over an interval exactly
    at any time, independent of the clip length or a sampling grid.
    """

    def __init__(self, rng: np.random.Generator, band_hz: tuple[float, float], *,
                 channels: int = 1, components: int = 48):
        lo, hi = band_hz
        self.omega = 2 * np.pi * rng.uniform(lo, hi, (channels, components))
        self.phase = rng.uniform(0.0, 2 * np.pi, (channels, components))
        self.amplitude = np.sqrt(2.0 / components)

    def __call__(self, t) -> np.ndarray:
        """Values (..., channels) at times ``t`` (s)."""
        t = np.asarray(t, np.float64)[..., None, None]
        return self.amplitude * np.cos(self.omega * t + self.phase).sum(-1)

    def mean(self, a, b) -> np.ndarray:
        """Exact mean (..., channels) over the intervals ``[a, b]`` (b > a)."""
        a = np.asarray(a, np.float64)[..., None, None]
        b = np.asarray(b, np.float64)[..., None, None]
        integral = (np.sin(self.omega * b + self.phase) - np.sin(self.omega * a + self.phase))
        return self.amplitude * (integral / (self.omega * (b - a))).sum(-1)


class CameraMotion:
    """Tripod shake plus thermal drift of the camera (see the module docstring)."""

    def __init__(self, cfg: CameraConfig, seed: int):
        self.cfg = cfg
        rng = np.random.default_rng([seed, 21])
        self.shake = RandomSignal(rng, cfg.shake_band_hz, channels=6) if cfg.shake else None
        self.active = bool(cfg.shake or cfg.drift)

    def rotation_translation(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Rotation vector (rad) and camera-centre displacement (mm) at camera time ``t``."""
        cfg = self.cfg
        rot, shift = np.zeros(3), np.zeros(3)
        if self.shake is not None:
            s = self.shake(float(t))
            rot += 1e-3 * cfg.shake_rotation_mrad * s[:3]
            shift += cfg.shake_translation_mm * s[3:]
        if cfg.drift:
            settled = 1 - np.exp(-max(float(t), 0.0) / cfg.drift_time_constant_s)
            rot += 1e-3 * settled * np.asarray(cfg.drift_rotation_mrad)
            shift += settled * np.asarray(cfg.drift_translation_mm)
        return rot, shift

    def at(self, t: float) -> Motion | None:
        """``(R, T)`` at camera time ``t``, or None while the camera stands still."""
        if not self.active:
            return None
        rot, shift = self.rotation_translation(t)
        return cv2.Rodrigues(rot)[0], shift


class Illumination:
    """Relative intensity of the scene's light over time (1 when undisturbed)."""

    def __init__(self, cfg, seed: int):
        self.cfg = cfg
        rng = np.random.default_rng([seed, 22])
        self.flicker_phase = float(rng.uniform(0.0, 2 * np.pi))
        scale = cfg.cloud_time_scale_s
        self.clouds = RandomSignal(rng, (0.05 / scale, 1.0 / scale)) if cfg.clouds else None
        self.active = bool(cfg.flicker or cfg.clouds or cfg.light_drift)

    def mean(self, a, b) -> np.ndarray:
        """Mean relative intensity over exposures ``[a, b]`` (arrays broadcast, b > a).

        Flicker is averaged exactly; clouds and drift, which change over
        seconds, too (the mean of the product is taken as the product of the
        means: exact to ``(exposure / cloud period)**2``).
        """
        cfg = self.cfg
        a, b = np.broadcast_arrays(np.asarray(a, np.float64), np.asarray(b, np.float64))
        light = np.ones(a.shape)
        if cfg.flicker:
            omega = 2 * np.pi * cfg.flicker_hz
            swing = (np.sin(omega * b + self.flicker_phase)
                     - np.sin(omega * a + self.flicker_phase)) / (omega * (b - a))
            light = light * (1 + cfg.flicker_depth * swing)
        if self.clouds is not None:
            light = light * np.maximum(1 + cfg.cloud_depth * self.clouds.mean(a, b)[..., 0], 0.05)
        if cfg.light_drift:
            light = light * np.maximum(1 + cfg.light_drift_per_min * (a + b) / 120.0, 0.05)
        return light
