"""Synthetic image pairs with known flow for the DeepFlow / DeepMatching tests."""

from __future__ import annotations

import cv2
import numpy as np


def textured(height: int, width: int, seed: int = 0, contrast: float = 1.0) -> np.ndarray:
    """Multi-scale smooth noise, mean 128, float32 in [0, 255]."""
    rng = np.random.default_rng(seed)
    img = np.zeros((height, width), np.float32)
    for sigma, amp in ((1.0, 0.5), (3.0, 1.0), (8.0, 1.0)):
        noise = rng.standard_normal((height, width)).astype(np.float32)
        img += amp * sigma * cv2.GaussianBlur(noise, (0, 0), sigma)
    img = (img - img.mean()) / img.std()
    return np.clip(128 + 40 * contrast * img, 0, 255).astype(np.float32)


def grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    return np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))


def warp_forward(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``current`` with ``current(x + flow(x)) = image(x)`` (fixed-point inverse map)."""
    height, width = image.shape
    gx, gy = grid(height, width)
    bx, by = gx.copy(), gy.copy()
    for _ in range(25):
        fx = cv2.remap(flow[..., 0], bx, by, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        fy = cv2.remap(flow[..., 1], bx, by, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        bx, by = gx - fx, gy - fy
    return cv2.remap(image, bx, by, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT)


def rigid_flow(height: int, width: int, angle_deg: float, tx: float, ty: float) -> np.ndarray:
    gx, gy = grid(height, width)
    th = np.deg2rad(angle_deg)
    cx, cy = width / 2.0, height / 2.0
    fx = (np.cos(th) - 1) * (gx - cx) - np.sin(th) * (gy - cy) + tx
    fy = np.sin(th) * (gx - cx) + (np.cos(th) - 1) * (gy - cy) + ty
    return np.dstack([fx, fy]).astype(np.float32)


def to_u8(image: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def epe(
    flow: np.ndarray, truth: np.ndarray, mask: np.ndarray | None = None, margin: int = 8
) -> float:
    err = np.hypot(flow[..., 0] - truth[..., 0], flow[..., 1] - truth[..., 1])
    keep = np.zeros(err.shape, bool)
    keep[margin:-margin, margin:-margin] = True
    if mask is not None:
        keep &= mask
    return float(err[keep].mean())


def visible(truth: np.ndarray) -> np.ndarray:
    """Pixels whose true target lies inside the frame."""
    height, width = truth.shape[:2]
    gx, gy = grid(height, width)
    tx, ty = gx + truth[..., 0], gy + truth[..., 1]
    return (tx >= 0) & (tx <= width - 1) & (ty >= 0) & (ty <= height - 1)


def smooth_noise(height: int, width: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Periodic Gaussian-filtered white noise (filtered in the Fourier domain), unit std."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    spectrum = np.fft.fft2(rng.standard_normal((height, width)))
    noise = np.fft.ifft2(spectrum * np.exp(-2 * np.pi**2 * sigma**2 * (fx**2 + fy**2))).real
    return (noise / noise.std()).astype(np.float32)


def fourier_shift(image: np.ndarray, shift_x: float, shift_y: float = 0.0) -> np.ndarray:
    """``image`` moved by (shift_x, shift_y) px, wrapping around; exact for periodic content.

    Cubic interpolation would not do for sub-pixel ground truth: OpenCV's
    INTER_CUBIC (Keys a = -0.75) moves smooth content by up to 0.04 px more
    or less than asked.
    """
    fy = np.fft.fftfreq(image.shape[0])[:, None]
    fx = np.fft.fftfreq(image.shape[1])[None, :]
    phase = np.exp(-2j * np.pi * (fx * shift_x + fy * shift_y))
    return np.fft.ifft2(np.fft.fft2(image) * phase).real.astype(np.float32)


def low_texture_pair(
    shift_x: float,
    shift_y: float,
    height: int = 96,
    width: int = 128,
    seed: int = 5,
    contrast: float = 15.0,
):
    """Smooth, low-contrast noise (std ``contrast`` grey levels) translated by a sub-pixel amount (uint8)."""
    noise = smooth_noise(height, width, 5.0, np.random.default_rng(seed))
    return (
        to_u8(128 + contrast * noise),
        to_u8(128 + contrast * fourier_shift(noise, shift_x, shift_y)),
    )


def bar_frames(
    shifts, height: int = 96, width: int = 160, x0: int = 60, x1: int = 100, bar_std: float = 3.0
):
    """A painted, nearly texture-free bar moving right over a static textured background.

    Returns the reference frame, the list of current frames and a POI mask
    inside the bar (6 px clear of its edges). The bar's edges are
    area-sampled and its paint is moved exactly (Fourier shift), so
    ``shifts`` is the true displacement to well below 0.01 px.
    """
    background = textured(height, width, seed=7)
    pad = 20
    paint = 200 + bar_std * smooth_noise(height, width + 2 * pad, 6.0, np.random.default_rng(11))
    gx, _ = grid(height, width)

    def render(shift: float) -> np.ndarray:
        cover = np.clip(np.minimum(gx + 0.5 - (x0 + shift), (x1 + shift) - (gx - 0.5)), 0, 1)
        tex = fourier_shift(paint, shift)[:, pad : pad + width]
        return to_u8(background * (1 - cover) + tex * cover)

    poi = np.zeros((height, width), bool)
    poi[20 : height - 20, x0 + 6 : x1 - 6] = True
    return render(0.0), [render(s) for s in shifts], poi
