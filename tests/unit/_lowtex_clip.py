"""Clips of a painted, nearly texture-free member over a static textured wall, with exact truth.

The kind of scene where a structure's motion lives at its edges: the member's
grey lies within the wall's range (low edge contrast in places), its paint has
about two grey levels of texture, and the clip goes through H.264 like a phone
video. Written for the tests from the description of such clips (no code of
the independent bench set was used):

* the scene is drawn at ``UP`` times the final resolution: the member's edges
  as exact area coverage of the displaced outline, its paint and a ring mark
  moved by an exact Fourier shift, the wall static;
* box-averaged down to the final size (so every pixel integrates its area),
  sensor noise, rounded to 8 bits, then encoded.

The truth of a frame is the mean true displacement over the mask's pixels.
"""

from __future__ import annotations

import subprocess
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

UP = 4


def smooth_noise(height: int, width: int, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """Gaussian-filtered white noise (filtered in the Fourier domain, periodic), unit std."""
    fy = np.fft.fftfreq(height)[:, None]
    fx = np.fft.fftfreq(width)[None, :]
    spectrum = np.fft.fft2(rng.standard_normal((height, width)))
    noise = np.fft.ifft2(spectrum * np.exp(-2 * np.pi**2 * sigma**2 * (fx**2 + fy**2))).real
    return noise / noise.std()


def _shift_rows(spectrum: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """Each row of the image whose row spectra are ``spectrum`` (``np.fft.fft(image, axis=1)``,
    made once per clip) moved right by its own (sub-pixel) shift, exactly (Fourier)."""
    fx = np.fft.fftfreq(spectrum.shape[1])[None, :]
    # One row of phases where every row moves alike (no bend): the same numbers, made once.
    same = bool(np.all(shifts == shifts[0]))
    phase = np.exp(-2j * np.pi * fx * (shifts[:1, None] if same else shifts[:, None]))
    return np.fft.ifft(spectrum * phase, axis=1).real


@dataclass
class Clip:
    frames: np.ndarray  # (F, H, W) uint8, before encoding
    mask: np.ndarray  # (H, W) bool, the POIs (the member's interior)
    truth_px: np.ndarray  # (F,) mean true displacement over the mask along the motion axis
    axis: str  # "x" or "y"
    fps: float
    occluded: np.ndarray  # (F,) bool


def make_clip(*, seed: int = 0, frames: int = 90, fps: float = 60.0, height: int = 160,
              width: int = 240, bar_width: int = 32, mask_margin: int = 6, texture: float = 2.0,
              amplitude: float = 4.0, frequency_hz: float = 4.3, bend: float = 0.0,
              axis: str = "x", gain_drift: float = 0.0, noise: float = 1.2,
              occlude_s: tuple[float, float] | None = None, blur_px: float = 0.0,
              jump: tuple[float, float, float] | None = None,
              wall_mean: float = 111.0, wall_std: float = 35.0, member_grey: float = 149.0,
              motion_px: np.ndarray | None = None, tip_row: int | None = None) -> Clip:
    """Render a clip (see the module doc). ``axis="y"``: a horizontal member moving vertically
    (the scene is drawn for x and transposed). ``bend``: the displacement grows by this
    fraction from the top row to the bottom row. ``jump = (t0, t1, px)``: an extra
    displacement of ``px`` between ``t0`` and ``t1`` s. ``occlude_s``: a bright sheet covers
    the whole view. ``blur_px``: the lens's Gaussian blur (sigma, final pixels). ``motion_px``:
    the displacement of every frame, given (``amplitude``, ``frequency_hz`` and the noise then
    unused; the random draws stay the same, so the wall and paint are those of ``seed``).
    ``tip_row``: the member ends there (a cantilever's free end, seen from the side), the wall
    below (for ``axis="x"``; its rows are columns with ``axis="y"``)."""
    rng = np.random.default_rng(seed)
    h, w = (height, width) if axis == "x" else (width, height)
    H, W = h * UP, w * UP
    wall = wall_mean + wall_std * smooth_noise(H, W, 2.5 * UP, rng)
    pad = W // 2  # the paint is drawn wider than the frame so that its shift never wraps
    paint = member_grey + texture * smooth_noise(H, W + 2 * pad, 2.0 * UP, rng)
    x0 = (w - bar_width) // 2
    x1 = x0 + bar_width
    # A ring mark on the member near the top, outside the POIs.
    yy, xx = np.mgrid[0:H, 0:W + 2 * pad].astype(np.float64)
    cy, cx = 0.18 * H, (x0 + x1) / 2 * UP + pad
    radius = np.hypot(yy - cy, xx - cx) / UP
    paint -= 70.0 * np.exp(-0.5 * ((radius - 0.22 * bar_width) / 0.9) ** 2)
    rows = (np.arange(H) + 0.5) / UP  # row centres, final pixels
    row_gain = 1.0 + bend * rows / h
    t = np.arange(frames) / fps
    phase = rng.uniform(0, 2 * np.pi)
    base = amplitude * np.sin(2 * np.pi * frequency_hz * t + phase)
    base += 0.08 * amplitude * rng.standard_normal(frames)  # not a pure tone
    if motion_px is not None:
        if np.shape(motion_px) != (frames,):
            raise ValueError(f"motion_px has shape {np.shape(motion_px)}, not ({frames},)")
        base = np.asarray(motion_px, np.float64).copy()
    if jump is not None:
        base += np.where((t >= jump[0]) & (t < jump[1]), jump[2], 0.0)
    occluded = np.zeros(frames, bool) if occlude_s is None else (t >= occlude_s[0]) & (t < occlude_s[1])
    mask = np.zeros((h, w), bool)
    mask[int(0.28 * h):int(0.94 * h), x0 + mask_margin:x1 - mask_margin] = True
    mask_rows = np.nonzero(mask.any(axis=1))[0]
    gx = (np.arange(W) + 0.5) / UP  # column centres, final pixels
    spectrum = np.fft.fft(paint, axis=1)  # the paint's rows, once: every frame shifts them
    out = np.empty((frames, h, w), np.uint8)
    truth = np.empty(frames)
    for i in range(frames):
        shift = base[i] * row_gain  # per fine row, final pixels
        rows_alike = shift[:1] if bend == 0 else shift  # one row's coverage serves all (no bend)
        left = x0 + rows_alike[:, None]
        right = x1 + rows_alike[:, None]
        # Area coverage of each fine pixel by the displaced member.
        cover = np.clip(np.minimum(gx[None, :] + 0.5 / UP - left, right - (gx[None, :] - 0.5 / UP)) * UP,
                        0, 1)
        if tip_row is not None:
            cover = cover * (rows < tip_row)[:, None]
        moved = _shift_rows(spectrum, shift * UP)[:, pad:pad + W]
        fine = cover * moved + (1 - cover) * wall
        if blur_px > 0:  # the lens: a Gaussian point spread, drawn at the fine scale
            fine = cv2.GaussianBlur(fine, (0, 0), blur_px * UP)
        frame = fine.reshape(h, UP, w, UP).mean(axis=(1, 3))
        frame *= 1.0 + gain_drift * np.sin(2 * np.pi * t[i] / max(t[-1], 1e-9))
        if occluded[i]:
            frame = np.full_like(frame, 235.0) + 3.0 * smooth_noise(h, w, 6.0, rng)
        frame += noise * rng.standard_normal(frame.shape)
        out[i] = np.clip(np.rint(frame), 0, 255).astype(np.uint8)
        per_row = base[i] * (1.0 + bend * (mask_rows + 0.5) / h)
        truth[i] = float(np.mean(per_row))  # the mask is a rectangle: every row has as many POIs
    if axis == "y":
        out = np.ascontiguousarray(out.transpose(0, 2, 1))
        mask = mask.T.copy()
    return Clip(out, mask, truth, axis, fps, occluded)


def encode(clip: Clip, path: str | Path, *, crf: int = 12) -> Path:
    """Write the clip as H.264 (x264, ``crf``, yuv420p) with imageio-ffmpeg's binary."""
    import imageio_ffmpeg

    path = Path(path)
    n, h, w = clip.frames.shape
    cmd = [imageio_ffmpeg.get_ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo",
           "-pix_fmt", "gray", "-s", f"{w}x{h}", "-r", str(clip.fps), "-i", "-",
           "-c:v", "libx264", "-crf", str(crf), "-preset", "medium", "-pix_fmt", "yuv420p",
           "-x264-params", "threads=1", str(path)]
    subprocess.run(cmd, input=clip.frames.tobytes(), check=True)
    return path


def decode(path: str | Path) -> np.ndarray:
    """Grey frames of a video (as refflow reads them)."""
    capture = cv2.VideoCapture(str(path))
    frames = []
    while True:
        ok, frame = capture.read()
        if not ok:
            break
        frames.append(cv2.cvtColor(frame, cv2.COLOR_BGR2GRAY))
    capture.release()
    return np.array(frames)
