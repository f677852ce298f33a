"""The error a lossy codec leaves in a region's texture reading, measured on the region itself.

A codec's error is common to the whole region (it rebuilds each block from a reference frame
with motion vectors quantised to a quarter pixel and drops residuals below its quantiser step),
so the fit's own uncertainty, which comes from the scatter of the residuals within the frame,
does not see it: on the bench's H.264 clips the texture fit's sigma was 0.004-0.009 px where its
readings were 0.02-0.05 px off (2-sigma coverage 0.22-0.37).

The floor is measured, not assumed: the region of the reference (with a margin) is shifted by
known sub-pixel amounts along a circle (in Fourier space, as the bias curve of
:class:`~flow.methods.deepflow.regionfit.RegionFit` does), encoded with libx264 at the stream's
own quality (its ``crf``), decoded and fitted like any frame; the rms of the fit's error against
the known shifts is the floor, per axis. It is added in quadrature to the texture fit's sigma,
so it only widens it.

A codec also copies: where a block's motion is below what it codes (a structure moving a few
tenths of a pixel under heavy compression), it repeats the block of an earlier frame, the
reference's included, bit for bit. Such pixels show the reference's motion, none, whatever the
structure did; a fit that counts them reads the motion short (a textured member moving
+-0.3 px at CRF 28: slope 0.57, where the pixels the codec did not copy read 0.77).
:func:`codec_copies` finds them: every pixel of a window of COPY_BLOCK_PX x COPY_BLOCK_PX
that equals the reference exactly. Sensor noise never leaves 64 pixels equal by chance, and
lossless frames (images, camera files) have nothing copied to find.
"""

from __future__ import annotations

import subprocess

import numpy as np
from scipy import ndimage

from flow.io.frames import COPY_WINDOW_PX, unchanged_windows
from flow.methods.deepflow.regionfit import RegionFit

# The shifted copies: FLOOR_FRAMES frames along a circle of FLOOR_RADIUS_PX, one turn in
# FLOOR_PERIOD_FRAMES frames: a radius of H.264's motion-vector step (a quarter pixel), so that
# the shifts fall at every phase within one step, where the codec's rounding of the motion
# differs (a half-pixel circle lands on the step's grid in most frames and its error is
# nothing there). A motion a codec must predict from frame to frame, as a structure's.
FLOOR_FRAMES = 24
FLOOR_RADIUS_PX = 0.25
FLOOR_PERIOD_FRAMES = 12
# Reference kept around the region's bounding box (the fit's window and the codec's blocks).
FLOOR_MARGIN_PX = 24
# The most pixels of the reference the copies are made of: a larger region (a whole 4K
# frame's worth of POIs) is measured in a window of this area about its middle. The codec's
# error is a matter of its blocks, alike over the region, and the fit takes at most
# MAX_POINTS of its pixels either way; the copies' Fourier shifts and encoding grow with the
# area (a 1700x800 region: 12 s; a whole 4K frame's would take minutes and gigabytes).
FLOOR_MAX_PIXELS = 1 << 20
# A copied block (see the module's docstring): a window of this side (px) equal to the reference
# in every pixel. H.264's smallest copied partition (its skip and direct modes work on 16x16
# macroblocks, 8x8 in part); any placement, so that a crop of the frame finds them too. The same
# windows tell frames in lossless files that a lossy codec made (flow.io.frames.copied_share).
COPY_BLOCK_PX = COPY_WINDOW_PX


def codec_copies(reference: np.ndarray, current: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Which of the pixels ``rows, cols`` of ``current`` a codec copied from ``reference``
    unchanged (bool, one per pixel): those in a COPY_BLOCK_PX square, anywhere, whose every
    pixel equals the reference's (see the module's docstring)."""
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    if rows.size == 0:
        return np.zeros(0, bool)
    height, width = reference.shape
    pad = COPY_BLOCK_PX
    r0, c0 = max(int(rows.min()) - pad, 0), max(int(cols.min()) - pad, 0)
    r1, c1 = min(int(rows.max()) + pad + 1, height), min(int(cols.max()) + pad + 1, width)
    # The squares equal throughout (anchored at each pixel: it and the pixels up to
    # COPY_BLOCK_PX / 2 before and after), then every pixel such a square covers.
    unchanged = unchanged_windows(current[r0:r1, c0:c1], reference[r0:r1, c0:c1], COPY_BLOCK_PX)
    covered = ndimage.maximum_filter(unchanged.astype(np.uint8), size=COPY_BLOCK_PX, origin=-1,
                                     mode="constant", cval=0)
    return covered[rows - r0, cols - c0] > 0


def shifted_copies(crop: np.ndarray, shifts: np.ndarray) -> np.ndarray:
    """``crop`` (H, W) shifted exactly by each ``(dx, dy)`` of ``shifts`` (N, 2), as 8-bit frames
    (mirrored before the Fourier shift, so that the shift's wrap-around stays outside). Each
    copy is rounded to 8 bits as it is made (before 2026-12-05 all N were held as float64 and
    their whole mirrored planes with them: 2.9 GB for a 1700x800 region)."""
    height, width = crop.shape
    mirrored = np.pad(np.asarray(crop, np.float64), ((0, height), (0, width)), mode="symmetric")
    spectrum = np.fft.fft2(mirrored)
    del mirrored
    fy = np.fft.fftfreq(2 * height)[:, None]
    fx = np.fft.fftfreq(2 * width)[None, :]
    frames = np.empty((len(shifts), height, width), np.uint8)
    for frame, (dx, dy) in zip(frames, shifts, strict=True):
        moved = np.real(np.fft.ifft2(spectrum * np.exp(-2j * np.pi * (dx * fx + dy * fy))))[:height, :width]
        frame[:] = np.clip(np.rint(moved), 0, 255)
    return frames


def x264_round_trip(frames: np.ndarray, crf: float) -> np.ndarray | None:
    """``frames`` (N, H, W) uint8, even H and W, encoded with libx264 (its default preset and GOP,
    B-frames included; one thread: the same bytes every run) at ``crf`` and decoded; None where
    the bundled ffmpeg is missing or fails."""
    count, height, width = frames.shape
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
        encoded = subprocess.run(
            [exe, "-nostdin", "-v", "error", "-f", "rawvideo", "-pix_fmt", "gray", "-s", f"{width}x{height}",
             "-r", "30", "-i", "-", "-c:v", "libx264", "-threads", "1", "-crf", f"{crf:g}",
             "-pix_fmt", "yuv420p", "-f", "h264", "-"],
            input=frames.tobytes(), capture_output=True, timeout=120, check=True).stdout
        decoded = subprocess.run([exe, "-nostdin", "-v", "error", "-f", "h264", "-i", "-", "-f", "rawvideo",
                                  "-pix_fmt", "gray", "-"],
                                 input=encoded, capture_output=True, timeout=120, check=True).stdout
    except (ImportError, RuntimeError, OSError, subprocess.SubprocessError):
        return None
    if len(decoded) != frames.size:
        return None
    return np.frombuffer(decoded, np.uint8).reshape(count, height, width)


def codec_floor(reference: np.ndarray, rows: np.ndarray, cols: np.ndarray, crf: float, *,
                presmooth_px: float = 0.0) -> tuple[float, float]:
    """The rms error ``(u, v)`` (px) of the texture fit of the region ``rows, cols`` of
    ``reference`` on copies of it shifted by known amounts and passed through libx264 at
    ``crf`` (see the module's docstring); ``(nan, nan)`` where it cannot be measured (no
    encoder, a region too small, fits that do not converge). ``presmooth_px``: the fit's
    pre-smoothing, as the readings' own fit has it (see :class:`RegionFit`)."""
    if not (np.isfinite(crf) and 0 <= crf <= 51):
        raise ValueError(f"crf must be a number in 0..51, got {crf!r}")
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    failed = (float("nan"), float("nan"))
    height, width = reference.shape
    r0, c0 = max(int(rows.min()) - FLOOR_MARGIN_PX, 0), max(int(cols.min()) - FLOOR_MARGIN_PX, 0)
    r1 = min(int(rows.max()) + FLOOR_MARGIN_PX + 1, height)
    c1 = min(int(cols.max()) + FLOOR_MARGIN_PX + 1, width)
    if (r1 - r0) * (c1 - c0) > FLOOR_MAX_PIXELS:
        # A window of FLOOR_MAX_PIXELS, the box's shape, about the region's middle pixel.
        shrink = np.sqrt(FLOOR_MAX_PIXELS / ((r1 - r0) * (c1 - c0)))
        h, w = max(int((r1 - r0) * shrink), 16), max(int((c1 - c0) * shrink), 16)
        middle = int(np.argmin(np.hypot(rows - np.median(rows), cols - np.median(cols))))
        r0 = int(np.clip(rows[middle] - h // 2, r0, r1 - h))
        c0 = int(np.clip(cols[middle] - w // 2, c0, c1 - w))
        r1, c1 = r0 + h, c0 + w
    r1 -= (r1 - r0) % 2  # yuv420p: even sides
    c1 -= (c1 - c0) % 2
    inside = (rows >= r0) & (cols >= c0) & (rows < r1) & (cols < c1)
    if inside.sum() < 8 or r1 - r0 < 16 or c1 - c0 < 16:
        return failed
    phase = 2.0 * np.pi * np.arange(FLOOR_FRAMES) / FLOOR_PERIOD_FRAMES
    shifts = FLOOR_RADIUS_PX * np.column_stack([np.sin(phase), np.cos(phase) - 1.0])  # (0, 0) first
    decoded = x264_round_trip(shifted_copies(reference[r0:r1, c0:c1], shifts), crf)
    if decoded is None:
        return failed
    # The decoded first copy is the reference, as a decoded frame is in a measurement.
    fit = RegionFit(decoded[0].astype(np.float64), rows[inside] - r0, cols[inside] - c0, bias_correction=False,
                    presmooth_px=presmooth_px, rounding_floor=False)
    errors = []
    for frame, (dx, dy) in zip(decoded[1:], shifts[1:], strict=True):
        # Started at the known shift: the floor is the error at the criterion's minimum, not the
        # fit's reach (a chain starts each frame near its motion).
        found = fit.fit(frame.astype(np.float64), np.array([dx, 0.0, 0.0, dy, 0.0, 0.0]))
        if found.converged:
            errors.append((found.params[0] - dx, found.params[3] - dy))
    if len(errors) < FLOOR_FRAMES // 2:
        return failed
    return tuple(float(x) for x in np.sqrt(np.mean(np.square(errors), axis=0)))
