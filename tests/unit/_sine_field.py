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
    # A Gaussian blob is the product of its row's and its column's profile, and the shift
    # depends on the column alone: the image is one matrix product of the two profiles.
    source_x = np.arange(width, dtype=np.float64) - np.broadcast_to(np.asarray(shift_x, np.float64), (width,))
    across = np.exp(-((source_x[:, None] - cx) ** 2) / (2 * radius**2))  # (width, n)
    down = np.exp(-((np.arange(height, dtype=np.float64)[:, None] - cy) ** 2) / (2 * radius**2))  # (height, n)
    image = (down * amp) @ across.T
    image = 30 + 200 * image / image.max()
    return np.clip(np.rint(image), 0, 255).astype(np.uint8)


def write_clip(folder: Path, n_frames: int = 20) -> Path:
    """PNG frames ``frame_000.png``...; frame 0 (t = 0) is the undeformed reference."""
    folder.mkdir(parents=True, exist_ok=True)
    x = np.arange(WIDTH, dtype=np.float64)
    for i in range(n_frames):
        cv2.imwrite(str(folder / f"frame_{i:03d}.png"), speckle(u_true(x, i / FPS)))
    return folder
