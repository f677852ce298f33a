"""A clean-room synthetic speckle clip whose displacement field is known everywhere: a sine
along x whose amplitude vibrates in time (a travelling-free standing wave), for the
``--field`` tests. Every speckle is a Gaussian blob evaluated exactly at the displaced
position, so the images carry the field without any interpolation."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

WIDTH, HEIGHT = 160, 96
AMPLITUDE_PX = 0.6
PERIOD_PX = 80.0
FPS = 20.0
HZ = 2.0


def u_true(x: np.ndarray, t: float) -> np.ndarray:
    """The field's x displacement (px) at column ``x`` and time ``t`` (s); v = 0."""
    return AMPLITUDE_PX * np.sin(2 * np.pi * x / PERIOD_PX) * np.sin(2 * np.pi * HZ * t)


def speckle(shift_x: np.ndarray | float = 0.0, *, seed: int = 7, width: int = WIDTH,
            height: int = HEIGHT) -> np.ndarray:
    """8-bit speckle image with the pattern moved by ``shift_x`` (px, per column or one value).

    ``image(x + u(x), y) = reference(x, y)`` approximately: the pattern at column x is taken
    from the reference at ``x - u(x)`` (u small and smooth, so the Eulerian and Lagrangian
    readings agree to far below the tests' tolerance)."""
    rng = np.random.default_rng(seed)
    n = width * height // 12
    cx = rng.uniform(-4, width + 4, n)
    cy = rng.uniform(-4, height + 4, n)
    amp = rng.uniform(0.4, 1.0, n)
    radius = 1.6
    ys, xs = np.mgrid[0:height, 0:width].astype(np.float64)
    source_x = xs - np.broadcast_to(np.asarray(shift_x, np.float64), (width,))[None, :]
    image = np.zeros((height, width))
    for start in range(0, n, 256):
        sl = slice(start, start + 256)
        d2 = (source_x[..., None] - cx[sl]) ** 2 + (ys[..., None] - cy[sl]) ** 2
        image += (amp[sl] * np.exp(-d2 / (2 * radius**2))).sum(axis=-1)
    image = 30 + 200 * image / image.max()
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def write_clip(folder: Path, n_frames: int = 20) -> Path:
    """PNG frames ``frame_000.png``...; frame 0 (t = 0) is the undeformed reference."""
    folder.mkdir(parents=True, exist_ok=True)
    x = np.arange(WIDTH, dtype=np.float64)
    for i in range(n_frames):
        cv2.imwrite(str(folder / f"frame_{i:03d}.png"), speckle(u_true(x, i / FPS)))
    return folder
