"""Whether the reference frame can be measured against: it shows texture or an outline
around the POIs, and is not washed out there.

Every dense method reads each frame's motion against the one reference frame. A black or
uniform reference (a lens cap, a fade-in) or a washed-out one (a flash) gives every method
nothing to match: they answer anyway, with numbers that look valid and are not (issue 32:
6.6 px RMS off a 10.8 px motion, every frame marked valid). So the reference's content
around the mask is checked before any frame is measured, and a refusal names the first
frame from it that would do.

What counts is the POI mask and its near surroundings, not the mask alone: a plain painted
member has little texture inside its outline, but its edges against the background carry
its motion (``tests/unit/_lowtex_clip.py``), and those lie just outside the mask.

Saturation is the same: a frame washed out by a flash or an exposure that overshot has its
surroundings at the top grey or just below it, and is refused. A member painted white in the
sun, or a bright sky, clipped at the top grey in front of a clearly darker background in this
frame and the ones after it, is the scene itself: its outline carries the motion. It is
measured, with a note.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable

import cv2
import numpy as np

from flow.io.errors import InputError
from flow.io.frames import FrameSource

# The surroundings: the mask grown by this many pixels, or by this share of its larger side.
NEAR_PX = 16
NEAR_SHARE = 0.1
# Texture: the grey levels between the 1st and 99th percentile of the surroundings, lightly
# smoothed, must exceed MIN_SPREAD and NOISE_MULTIPLE times the noise (the robust spread of what
# the smoothing took away). Sensor noise on a uniform frame spreads over about 1.5 times its own
# level; a painted member against a wall over a hundred grey levels, the faint 12-bit texture of
# the tests over 4 (noise 0.2); a black frame, flattened by H.264, over none.
MIN_SPREAD = 1.0
NOISE_MULTIPLE = 4.0
SMOOTH_SIGMA_PX = 1.0
# A frame is saturated where at least this share of the surroundings sits at its brightest
# grey (clipped pixels share one value: a textured bright scene has few pixels there).
SATURATED_SHARE = 0.5
SATURATED_MIN_GREY = 200.0
# Saturation that is the scene's own (see the module's note): at least DARKER_SHARE of the
# surroundings below DARKER_GREY of the top grey (an outline against a darker background: a
# white bar, 262 grey levels clipped to 255, the mask inside it, in front of a wall of 110 +- 25:
# 34 % below; a flash that lifts a texture by 135 grey levels: none), and the light steady over
# the PERSIST_FRAMES frames after the reference (at least one of them): at least half of them
# saturated at least half as much (the frames after a flash: none at the top grey), and its
# pixels that were darker in the reference, where they still are, as bright as there within
# STEADY_LEVEL (the median over those frames of each frame's median ratio to the reference's) and
# with no trend in brightness beyond STEADY_LIGHT over those frames (a line fitted to those
# ratios; with fewer than 3 frames, each within it). A flash in the reference alone, the light
# constant after it, has no trend: its level tells (x1.2: accepted without the level, it read
# 0.104 px where the steady clip reads 0.030; x1.5 0.338); a reference at the peak of a +-5 %
# flicker is within it (0.041 px). An exposure settling after an overshoot
# (its gain 1 + 1.2 exp(-frame / 15), 77 % of a faint bar's surroundings at 255 in the first
# frame, read 1.6 px off with every frame marked valid when it was accepted) darkens them by 3.5 %
# in the next frame and 47 % by the 30th; a mains light's flicker (+-5 %, filmed at 240 fps) has
# no trend.
DARKER_SHARE = 0.05
DARKER_GREY = 0.75
PERSIST_FRAMES = 30
STEADY_LIGHT = 0.05
STEADY_LEVEL = 0.08
# How far ahead a usable frame is looked for, to name it in the refusal.
SEARCH_FRAMES = 1000


def surroundings(mask: np.ndarray) -> np.ndarray:
    """The mask grown by :data:`NEAR_PX` (or :data:`NEAR_SHARE` of its larger side), bool."""
    rows, columns = np.nonzero(mask)
    if rows.size == 0:
        return mask.astype(bool)
    side = max(rows.max() - rows.min(), columns.max() - columns.min()) + 1
    grow = int(max(NEAR_PX, round(NEAR_SHARE * side)))
    # Grow within the mask's bounding box widened by the growth: a 4K frame costs its member.
    top, left = max(rows.min() - grow, 0), max(columns.min() - grow, 0)
    bottom, right = min(rows.max() + grow + 1, mask.shape[0]), min(columns.max() + grow + 1, mask.shape[1])
    window = np.ascontiguousarray(mask[top:bottom, left:right], np.uint8)
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (2 * grow + 1, 2 * grow + 1))
    near = np.zeros(mask.shape, bool)
    near[top:bottom, left:right] = cv2.dilate(window, kernel) > 0
    return near


def problem(grey: np.ndarray, near: np.ndarray) -> str | None:
    """What makes ``grey`` no reference over the pixels ``near`` (see :func:`surroundings`), or None."""
    values = grey[near].astype(np.float32)
    if values.size == 0:
        return None
    rows, columns = np.nonzero(near)
    box = (slice(rows.min(), rows.max() + 1), slice(columns.min(), columns.max() + 1))
    window, inside = grey[box].astype(np.float32), near[box]
    smooth = cv2.GaussianBlur(window, (0, 0), SMOOTH_SIGMA_PX)
    low, high = np.percentile(smooth[inside], [1, 99])
    noise = 1.4826 * float(np.median(np.abs(window - smooth)[inside]))
    needed = max(MIN_SPREAD, NOISE_MULTIPLE * noise)
    if high - low < needed:
        return (f"has no texture around the mask (uniform grey {float(np.median(values)):.0f}: its grey levels "
                f"spread over {high - low:.2g}, {needed:.2g} needed)")
    top, at_top, _ = saturation(values)
    if top >= SATURATED_MIN_GREY and at_top >= SATURATED_SHARE:
        return f"{SATURATED_WORDS} ({100 * at_top:.0f} % of its pixels at the top grey {top:.0f})"
    return None


SATURATED_WORDS = "is saturated around the mask"


def saturation(values: np.ndarray) -> tuple[float, float, float]:
    """``(top, at_top, darker)`` of grey levels ``values``: their brightest grey, the share of
    them at it and the share below :data:`DARKER_GREY` of it."""
    top = float(values.max())
    return top, float(np.mean(values >= top - 0.5)), float(np.mean(values < DARKER_GREY * top))


def _lit_scene(reference: list[np.ndarray], after: Iterable[np.ndarray], near: np.ndarray) -> str | None:
    """A note where the saturation of the reference frames, whose pixels ``near`` are
    ``reference``, is the scene's own (see the module's note), judged on the frames ``after``
    them (grey images); else None."""
    shares = [saturation(values) for values in reference]
    if not all(darker >= DARKER_SHARE for _, _, darker in shares):
        return None
    top, at_top, darker = shares[0]
    first = reference[0]
    dark = first < DARKER_GREY * top
    least = min(share for _, share, _ in shares)
    saturated, light = [], []
    for grey in after:
        now = grey[near].astype(np.float32)
        now_top, now_at_top, _ = saturation(now)
        saturated.append(now_top >= SATURATED_MIN_GREY and now_at_top >= 0.5 * least)
        still = dark & (now < DARKER_GREY * now_top)
        light.append(float(np.median(now[still] / np.maximum(first[still], 1.0))) if still.any() else np.nan)
    if not saturated or np.mean(saturated) < 0.5 or not np.isfinite(light).all():
        return None  # (nothing shows that it lasts; the frames after a flash; the darker part gone)
    if len(light) < 3:
        steady = all(abs(ratio - 1.0) <= STEADY_LIGHT for ratio in light)
    else:
        trend = np.polyfit(np.arange(len(light)), light, 1)[0]
        steady = abs(trend) * (len(light) - 1) <= STEADY_LIGHT and abs(float(np.median(light)) - 1.0) <= STEADY_LEVEL
    if not steady:
        return None
    return (f"the reference shows {100 * at_top:.0f} % of the pixels around the mask at the top grey {top:.0f}, "
            f"as do the frames after it (overexposed): only their outline against the darker "
            f"{100 * darker:.0f} % carries the motion there; lower the exposure if you record again")


def check(source: FrameSource, reference_frame: int, average: int, mask: np.ndarray,
          undistort: Callable[[np.ndarray], np.ndarray] | None = None) -> str | None:
    """Refuse a reference (frame ``reference_frame``, or each of the ``average`` frames from
    it) that :func:`problem` finds wanting, naming the first frame from which ``average``
    frames in a row would do. Frames beyond the video are left to the driver to refuse.
    Returns a note where the reference is saturated as the scene is (see the module's note)."""
    near = surroundings(mask)
    if reference_frame < 0 or average < 1 or not near.any():
        return None  # the driver and the mask checks say what is wrong with these

    def greys(start: int, stop: int):
        for index, _, grey in source.frames(start, stop):
            yield index, undistort(grey) if undistort is not None else grey

    def frames(start: int, stop: int):
        for index, grey in greys(start, stop):
            yield index, problem(grey, near)

    problems, saturated = [], []
    for index, grey in greys(reference_frame, reference_frame + average):
        problems.append((index, problem(grey, near)))
        if problems[-1][1] is not None:
            saturated.append(grey[near].astype(np.float32))
    bad = next(((index, found) for index, found in problems if found), None)
    if bad is None:
        return None
    index, found = bad
    if all(said is None or said.startswith(SATURATED_WORDS) for _, said in problems):
        start = reference_frame + average
        after = (grey for _, grey in greys(start, start + PERSIST_FRAMES))
        note = _lit_scene(saturated, after, near)
        if note is not None:
            return note
    what = f"the reference frame {index}" if average == 1 else \
        f"frame {index} of the reference average ({reference_frame}..{reference_frame + average - 1})"
    run, usable = 0, None
    for later, later_problem in frames(index + 1, index + 1 + SEARCH_FRAMES):
        run = 0 if later_problem else run + 1
        if run == average:
            usable = later - average + 1
            break
    if usable is None:
        raise InputError(f"{what} {found}, and so do the {SEARCH_FRAMES} frames after it (or the video ends): "
                         "check that the mask lies on the structure and that the video shows it, or pass "
                         "--reference-frame N of a frame that shows it")
    first = "the first usable frame after it" if average == 1 else \
        f"the first of {average} usable frames in a row after it"
    raise InputError(f"{what} {found}: pass --reference-frame {usable} ({first})")
