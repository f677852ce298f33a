"""The default on structures that are not a painted bar, against a baseline run in the same test.

The clips are generated here (clean-room, not the bench's generator): each scene layer is a
band-limited random texture drawn at twice the final resolution, every frame resampled at the
exactly warped coordinates (quintic spline of a texture smooth on that grid), box-averaged to
the final size, sensor noise of one grey level, 8 bits, H.264 at CRF 18 (phone quality). The
truth of a frame is the mean true displacement of the mask's pixels. What a user runs:
``refflow track VIDEO --mask MASK`` with no options, and the same with ``--method dis``.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

from flow.cli import main
from flow.methods.deepflow.method import REFUSALS
from flow.pipeline import DEFAULT_CRF

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import Clip, decode, encode, make_clip  # noqa: E402

UP = 2
HEIGHT, WIDTH = 160, 208
FRAMES = 36
FPS = 60.0


def _texture(height: int, width: int, rng: np.random.Generator, blob_px: float) -> np.ndarray:
    """Unit-std band-limited texture on the fine grid (blobs of ``blob_px`` final pixels)."""
    image = sum(s * ndimage.gaussian_filter(rng.standard_normal((height, width)), s * UP, mode="wrap")
                for s in (blob_px, 2.5 * blob_px))
    return (image - image.mean()) / image.std()


def _warp(layer: np.ndarray, motion, t: int) -> np.ndarray:
    """``layer`` (fine grid) moved by ``motion(t, x, y) -> (u, v)`` (final px), resampled at the
    inverse positions (a fixed-point inverse of the motion; exact for rigid motions)."""
    ys, xs = np.mgrid[0:layer.shape[0], 0:layer.shape[1]].astype(np.float64) / UP
    bx, by = xs.copy(), ys.copy()
    for _ in range(6):
        u, v = motion(t, bx, by)
        bx, by = xs - u, ys - v
    return ndimage.map_coordinates(layer, [by * UP, bx * UP], order=5, mode="reflect")


def _down(image: np.ndarray) -> np.ndarray:
    return image.reshape(HEIGHT, UP, WIDTH, UP).mean(axis=(1, 3))


def _shaded_column(fine: tuple[int, int], centre: float, radius: float) -> np.ndarray:
    """A round column's shading on the fine grid ``fine``: bright to dark across it (lit from the
    left), its limbs darkening, centred on x = ``centre`` px with ``radius`` px; constant along it."""
    across = np.clip((np.arange(fine[1]) / UP - centre) / radius, -1.0, 1.0)
    shade = 60 + 150 * np.clip(1.0 - 0.8 * (across + 1.0) / 2.0, 0, 1) * np.sqrt(1 - across ** 2)
    return np.tile(shade, (fine[0], 1))


def _scene(kind: str, seed: int, noise: float = 1.0) -> Clip:
    rng = np.random.default_rng(seed)
    fine = (HEIGHT * UP, WIDTH * UP)
    wall = 110 + 25 * _texture(*fine, rng, 2.0)
    member = 140 + 30 * _texture(*fine, rng, 1.5)
    t_axis = np.arange(FRAMES) / FPS
    mask = np.zeros((HEIGHT, WIDTH), bool)
    inside = np.zeros(fine, bool)  # where the member covers the reference (fine grid)
    axis = "x"
    blur_px = 0.0  # a lens out of focus: the frame's Gaussian blur (px), before the sensor's noise
    light = None  # the light falling on the scene in frame t: a gain over the frame (1: as in the reference)
    if kind == "panel":  # a rigid panel translating over a different wall
        amp = 3.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        inside[30 * UP:130 * UP, 40 * UP:170 * UP] = True
        mask[45:115, 55:155] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.full_like(x, 0.3 * amp[t])
    elif kind == "windows":  # a facade of sharp-edged windows (a 16 px grid) translating over a wall
        amp = 2.5 * np.sin(2 * np.pi * 1.7 * t_axis)
        ys_f, xs_f = np.mgrid[0:fine[0], 0:fine[1]] / UP
        dark = (np.mod(xs_f, 16) < 8) & (np.mod(ys_f, 16) < 8)
        member = ndimage.gaussian_filter(160.0 - 80.0 * dark, 1.0) + 3 * _texture(*fine, rng, 1.5)
        inside[30 * UP:130 * UP, 40 * UP:170 * UP] = True
        mask[45:115, 55:155] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.full_like(x, 0.3 * amp[t])
    elif kind == "stripes":  # a girder in hazard tape (diagonal stripes over faint paint) moving across
        amp = 2.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        ys_f, xs_f = np.mgrid[0:fine[0], 0:fine[1]] / UP
        member = ndimage.gaussian_filter(130.0 + 40.0 * (np.mod(xs_f + ys_f, 12) < 6), 1.0) + 2 * _texture(*fine, rng, 1.5)
        inside[65 * UP:95 * UP, :] = True
        mask[70:90, 20:188] = True
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind == "shadow":  # a textured panel, the soft edge of a shadow sweeping across it (a cloud's, a truck's)
        amp = 2.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        inside[30 * UP:130 * UP, 40 * UP:170 * UP] = True
        mask[45:115, 55:155] = True

        def light(t):  # 35 % darker beyond the edge (4 px wide), which crosses the mask over the clip
            return 1.0 - 0.35 / (1.0 + np.exp(-(np.arange(WIDTH) - (40.0 + 130.0 * t / FRAMES)) / 4.0))[None, :]

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind in ("deck", "deck-faint"):  # a deck against a flat sky, the mask inside its one outline in reach
        amp = 2.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        # (deck-faint: a grey deck 40 grey levels darker than a grey sky)
        wall = (215 if kind == "deck" else 140) + 1.0 * _texture(*fine, rng, 4.0)
        member = (60 if kind == "deck" else 100) + 4 * _texture(*fine, rng, 1.5)
        inside[40 * UP:100 * UP, :] = True
        mask[70:98, 20:188] = True
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind == "whole-view":  # everything moves, no still background
        amp = 2.5 * np.sin(2 * np.pi * 2.1 * t_axis)
        inside[:] = True
        mask[40:120, 50:160] = True
        axis = "y"

        def motion(t, x, y):
            return np.full_like(x, 0.3 * amp[t]), np.full_like(x, amp[t])
    elif kind == "rotation":  # a slab turning about a pivot left of the view
        angle = np.deg2rad(1.2) * np.sin(2 * np.pi * 1.3 * t_axis)
        inside[40 * UP:120 * UP, :] = True
        mask[55:105, 90:190] = True
        axis = "y"
        pivot = (-120.0, 80.0)

        def motion(t, x, y):
            c, s = np.cos(angle[t]), np.sin(angle[t])
            dx, dy = x - pivot[0], y - pivot[1]
            return c * dx - s * dy - dx, s * dx + c * dy - dy
    elif kind == "tiny":  # a girder moving a few tenths of a pixel
        amp = 0.3 * np.sin(2 * np.pi * 2.3 * t_axis)
        inside[50 * UP:110 * UP, :] = True
        mask[58:102, 20:188] = True
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind in ("tiny-faint", "tiny-faint-view"):  # a faint texture moving a few tenths of a pixel
        amp = 0.3 * np.sin(2 * np.pi * 2.3 * t_axis)
        member = 140 + (5 * _texture(*fine, rng, 2.0) if kind == "tiny-faint" else 3 * _texture(*fine, rng, 1.0))
        if kind == "tiny-faint":  # a panel over a wall
            inside[20 * UP:140 * UP, 20 * UP:188 * UP] = True
        else:  # filling the view: no outline anywhere
            inside[:] = True
        mask[40:120, 40:168] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind == "large":  # a textured bar swinging +-25 px
        amp = 25.0 * np.sin(2 * np.pi * 1.1 * t_axis)
        inside[10 * UP:150 * UP, 80 * UP:130 * UP] = True
        mask[20:140, 90:120] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind in ("along", "along-faint"):  # a faintly painted bar moving along its length (a column settling)
        amp = (2.0 if kind == "along" else 1.5) * np.sin(2 * np.pi * 1.7 * t_axis)
        member = 150 + (4 if kind == "along" else 2) * _texture(*fine, rng, 1.5)
        inside[:, 84 * UP:124 * UP] = True
        mask[10:150, 90:118] = True
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind == "inclined":  # a faint bar at 30 degrees moving along x (half of it along the bar)
        angle = np.deg2rad(30)
        ys_f, xs_f = np.mgrid[0:fine[0], 0:fine[1]] / UP
        inside = np.abs((xs_f - 104) * np.cos(angle) - (ys_f - 80) * np.sin(angle)) < 14
        member = 150 + 2 * _texture(*fine, rng, 1.5)
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
        mask = ((np.abs((xx - 104) * np.cos(angle) - (yy - 80) * np.sin(angle)) < 9)
                & (np.abs((xx - 104) * np.sin(angle) + (yy - 80) * np.cos(angle)) < 60))
        amp = 3.0 * np.sin(2 * np.pi * 1.7 * t_axis)

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind == "round":  # a column shaded bright to dark across, with a faint texture
        amp = 3.5 * np.sin(2 * np.pi * 1.9 * t_axis)
        member = _shaded_column(fine, 84.0, 40.0) + 3 * _texture(*fine, rng, 2.0)  # x = 44 to 124
        inside[:, 44 * UP:124 * UP] = True
        mask[10:150, 66:102] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind in ("column-along", "column-along-far"):  # a narrow column shaded across, a faint texture,
        # moving along its axis (+-3 px; +-12 px)
        amp = (3.0 if kind == "column-along" else 12.0) * np.sin(2 * np.pi * 1.7 * t_axis)
        member = _shaded_column(fine, 104.0, 20.0) + 2 * _texture(*fine, rng, 2.0)  # x = 84 to 124
        inside[:, 84 * UP:124 * UP] = True
        mask[15:145, 92:116] = True
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind == "cable":  # a cable 6 px thick, 3 degrees off level, over a plain sky, moving across
        amp = 2.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        ys_f, xs_f = np.mgrid[0:fine[0], 0:fine[1]] / UP
        inside = np.abs(ys_f - 80 - 0.05 * (xs_f - 104)) < 3.0
        wall = 200 - 0.1 * ys_f + 2 * _texture(*fine, rng, 4.0)
        member = 60 + 3 * _texture(*fine, rng, 1.0)
        yy, xx = np.mgrid[0:HEIGHT, 0:WIDTH] + 0.5
        mask = (np.abs(yy - 80 - 0.05 * (xx - 104)) < 2.5) & (xx > 20) & (xx < 188)
        axis = "y"

        def motion(t, x, y):
            return np.zeros_like(x), np.full_like(x, amp[t])
    elif kind == "lengthwise":  # a bar painted in lengthwise stripes (an 8 px period) moving across
        amp = 3.0 * np.sin(2 * np.pi * 1.7 * t_axis)
        xs = np.arange(fine[1]) / UP
        member = np.tile(150.0 + 4.0 * np.sin(2 * np.pi * (xs - 104) / 8), (fine[0], 1)) + _texture(*fine, rng, 1.5)
        inside[:, 84 * UP:124 * UP] = True
        mask[15:145, 92:116] = True

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    elif kind == "ibeam-blurred":  # an I-beam's web between its dark flanges, the lens out of focus
        amp = 2.5 * np.sin(2 * np.pi * 1.5 * t_axis)
        xs = np.arange(fine[1]) / UP
        web = np.abs(xs - 104) < 30  # the flanges' dark faces 10 px either side
        member = np.tile(np.where(web, 150.0, 70.0), (fine[0], 1)) + 3 * _texture(*fine, rng, 1.5)
        inside[:, 64 * UP:144 * UP] = True
        mask[10:150, 79:129] = True
        blur_px = 1.5

        def motion(t, x, y):
            return np.full_like(x, amp[t]), np.zeros_like(x)
    else:
        raise ValueError(kind)
    frames, truth = [], []
    ys, xs = np.nonzero(mask)
    coverage = inside.astype(np.float64)
    for t in range(FRAMES):
        cover = np.clip(_warp(coverage, motion, t), 0, 1)
        image = _down(cover * _warp(member, motion, t) + (1 - cover) * wall)
        if light is not None:
            image = image * light(t)
        if blur_px:
            image = cv2.GaussianBlur(image, (0, 0), blur_px)
        image += noise * rng.standard_normal(image.shape)
        frames.append(np.clip(np.rint(image), 0, 255).astype(np.uint8))
        u, v = motion(t, xs.astype(np.float64), ys.astype(np.float64))
        truth.append(float(np.mean(u if axis == "x" else v)))
    return Clip(np.array(frames), mask, np.array(truth), axis, FPS, np.zeros(FRAMES, bool))


def _png_folder(tmp_path: Path, clip: Clip) -> Path:
    """The clip's frames as a folder of PNG images (lossless)."""
    frames = tmp_path / "frames"
    frames.mkdir()
    for index, frame in enumerate(clip.frames):
        cv2.imwrite(str(frames / f"{index:04d}.png"), frame)
    return frames


def _run(tmp_path: Path, clip: Clip, video: Path, name: str, *extra: str) -> tuple[float, float, float, dict]:
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), clip.mask.astype(np.uint8) * 255)
    out = tmp_path / f"{name}.csv"
    assert main(["track", str(video), "--mask", str(mask), "--out", str(out), "--no-progress", *extra]) == 0
    return score(clip, out)


def _error_and_sigma(tmp_path: Path, clip: Clip, name: str = "default") -> tuple[np.ndarray, np.ndarray, list[dict]]:
    """The error and the sigma of each frame of :func:`_run`'s ``name`` along the clip's axis, and
    the CSV's rows."""
    with (tmp_path / f"{name}.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    key = "dx_px" if clip.axis == "x" else "dy_px"
    error = np.array([float(r[key]) for r in rows]) - (clip.truth_px - clip.truth_px[0])
    return error, np.array([float(r[f"sigma_{key}"]) for r in rows]), rows


def score(clip: Clip, out: Path) -> tuple[float, float, float, dict]:
    """RMSE (px) and slope of the track CSV ``out`` against the clip's truth along its axis,
    the share of its frames valid, and its sidecar's timings."""
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    key = "dx_px" if clip.axis == "x" else "dy_px"
    measured = np.array([float(r[key]) for r in rows])
    valid = np.array([r["valid"] == "1" for r in rows])
    true = clip.truth_px - clip.truth_px[0]
    use = np.isfinite(measured)
    slope = float(np.polyfit(true[use], measured[use], 1)[0])
    rmse = float(np.sqrt(np.mean((measured[use] - true[use]) ** 2)))
    timings = json.loads(out.with_suffix(".json").read_text())["timings"]
    return rmse, slope, float(np.mean(valid & use)), timings


# The default must not lose to a plain baseline on any kind (within 10 %, or a floor of a few
# hundredths of a pixel that H.264 leaves on every reading), read the scale right and keep
# its frames valid.
KINDS = ["panel", "whole-view", "rotation", "tiny", "large", "round", "along", "windows", "stripes", "shadow"]
# The shaded round member with a faint texture: its outline (the limb darkening into the wall, no
# step to fit) once read 0.19 px RMS, 6 % long, with its own uncertainty at 0.3-1.8 px, where DIS
# read 0.15 (an xfail until 2026-12-03): an outline that imprecise is now refused and the dense
# flow read (0.08 px). A girder in hazard tape, whose stripes' grey levels overlap the wall's:
# its support grew into the wall, the outline was refused and the texture fit, blind to the
# motion along the stripes but for the faint paint under them, read 0.113 px (DIS 0.059) before
# 2026-12-05; 0.056 now. A textured panel under a shadow's edge sweeping across the mask: the
# texture fit, with one gain and offset for the region, read the light that changed across it as
# motion, 0.09-0.20 px RMS on three draws where DIS read 0.042-0.046, before 2026-12-07; where the
# light changed across it, each block of the region has its own gain and offset now
# (regionfit.light_changed): 0.042-0.043 on those draws; on this test's, 0.043 (0.091 before),
# DIS 0.037: within the floor of 0.05, not within 1.1 times DIS.
@pytest.mark.parametrize("kind", KINDS)
def test_the_default_is_no_worse_than_dis_on_this_kind_of_scene(tmp_path, kind) -> None:
    clip = _scene(kind, seed=40 + KINDS.index(kind))
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"{kind}: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} valid {ours[2]:.2f}; "
          f"dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= max(1.1 * base[0], 0.05)
    if kind in ("tiny", "along"):
        # H.264 keeps part of a few tenths of a pixel's motion from every method (DIS reads this
        # clip 4 % short, the default 5.6 %), and part of a faint paint's motion along a member
        # whose edges do not show it (DIS 10 % short, the default 3 %; 60 % short before the
        # paint's own fit read it): no worse than DIS by more than 0.03.
        assert abs(ours[1] - 1.0) <= 0.07 and ours[1] >= base[1] - 0.03
    elif kind == "shadow":
        # A light changing across the frame costs every method a little of the scale here (DIS
        # reads this clip 1.4 % short, the default 1.7 %; three other draws of the kind, 48
        # frames: 0.1-0.9 %, DIS 0.5-1.7 %): no worse than DIS by more than 0.01.
        assert abs(ours[1] - 1.0) <= 0.03 and ours[1] >= base[1] - 0.01
        assert ours[3]["texture_light_blocks"] >= 0.5 * FRAMES
    else:
        assert abs(ours[1] - 1.0) <= 0.015
    assert ours[2] >= 0.95
    # The sidecar says what each reading was taken from, and why each full measurement chose it.
    timings = ours[3]
    assert sum(timings[f"{m}_readings"] for m in ("outline", "affine", "dense")) == FRAMES
    choices = [k for k in timings if k.startswith("why_") and k.removeprefix("why_") not in REFUSALS]
    assert sum(timings[k] for k in choices) == timings["full_frames"]
    assert timings["outline_models_left_out"] == 0  # sharp scenes: every outline model draws them
    if kind in ("panel", "whole-view", "rotation", "windows", "shadow"):  # strong texture: the texture fit
        assert timings["affine_readings"] >= 0.9 * FRAMES and timings["why_texture_fixes_motion"] >= 1
    if kind == "along":
        # The codec copies the unchanged edges of a bar sliding along itself: its paint (4 grey
        # levels, just short of a strong texture) is fitted in the frames they froze (method.
        # FROZEN_TEXTURE_GRADIENT; 0.147 px RMS, DIS 0.194), the outline across and the paint's own
        # fit along in the others (until 2026-12-07 in every frame: 0.187).
        assert timings["why_outline_codec_copied"] >= 1 and timings["affine_readings"] >= 0.25 * FRAMES
        assert timings["outline_readings"] >= 0.25 * FRAMES
    if kind == "stripes":  # the outline (its support grown to it, not into the wall: member._beyond_steps)
        # in part: where the stripes' texture fit says it fixes the motion it is taken (2 of the 4 keys)
        assert timings["outline_readings"] >= 0.5 * FRAMES
    if kind == "round":  # shaded across: the outline not fitted, the dense flow read (method.SHADED_ACROSS_GRADIENT)
        assert timings["why_outline_shaded_across"] == timings["full_frames"] and timings["dense_readings"] == FRAMES
    # The bound can fail: the same reading 5 % short breaks the slope's.
    assert abs(0.95 * ours[1] - 1.0) > 0.015


def _default_and_dis(tmp_path: Path, kind: str, seed: int) -> tuple[tuple, tuple]:
    """:func:`_run`'s scores of the default and of DIS on the scene ``kind`` drawn with ``seed``
    (H.264 CRF 18), printed."""
    clip = _scene(kind, seed)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"{kind} {seed}: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} valid {ours[2]:.2f}; "
          f"dis {base[0]:.4f} / {base[1]:.4f}")
    return ours, base


# A shaded round column (another draw of the kind above): its soft limbs gave key outlines whose
# motion matched the column's shaded pixels 1.7-2.3 times worse than the dense flow's, within the
# 0.5 grey levels of slack of a mismatch of 0.4-0.7, read 0.4-1.0 px off: 0.266 px RMS, every
# frame flagged, before 2026-12-07. Then refused by the ratio of the mismatches
# (method.MATCH_RATIO): 0.083 (DIS 0.078, the paper's dense flow 0.068); since the second change
# below never fitted (a column shaded across), the dense flow read.
def test_a_shaded_round_columns_outline_is_refused_where_it_reads_the_column_worse(tmp_path) -> None:
    ours, base = _default_and_dis(tmp_path, "round", 102)
    assert ours[0] <= 1.2 * base[0] and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["dense_readings"] >= 0.3 * FRAMES


# Other draws of the shaded round column: their limbs, darkening into the wall with no step, gave
# outline models whose readings spread 0.2-1.6 px; the one kept read 0.10-0.19 px RMS on four draws
# (DIS 0.11-0.18, the dense flow 0.06-0.08), one of them with every frame flagged (its outlines'
# disagreement, 0.6-0.9 px, taken as its uncertainty), and 0.30-0.33 px where the mask reaches
# within 2 px of the limbs (DIS 0.07-0.10), before 2026-12-07. A region whose own shading is
# strong across its member (method.SHADED_ACROSS_GRADIENT) though not on both axes, and whose
# outlines no blur model draws (method.SHADED_OUTLINE_MISFIT), is read by the dense flow:
# 0.057-0.085 px on the four draws, 0.060-0.074 with the wide mask.
@pytest.mark.parametrize(("seed", "half_width"), [(201, None), (203, 38)])
def test_a_column_shaded_across_is_read_by_the_dense_flow(tmp_path, seed, half_width) -> None:
    clip = _scene("round", seed)
    if half_width is not None:  # the mask across nearly the whole column (x = 44 ... 124)
        clip.mask[:] = False
        clip.mask[10:150, 84 - half_width:84 + half_width] = True
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"round {seed} (mask half width {half_width}): default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} "
          f"valid {ours[2]:.2f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= max(1.1 * base[0], 0.05) and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["dense_readings"] == FRAMES and ours[3]["outline_readings"] == 0


# The same kind of column, narrower (40 px), sliding +-3 px along its own axis: the dense flow's
# smoothing over its faint texture held it back towards the still wall either side (slope 0.10
# lossless, 0.00 under H.264: 1.90 and 2.10 px RMS; DIS 0.28 and 0.90). Its own texture's fit
# along the member is taken where the POIs match it clearly better (method._dense_along), started
# also from the farthest whole pixel along that the POIs' match keeps improving to
# (method.ALONG_WALK_HOPS): 0.30 px / slope 1.00 lossless, 0.80 / 0.88 under H.264. A second
# H.264 draw (seed 2) still loses to DIS: 1.59 px against 1.02.
# The same column sliding +-12 px, lossless: the dense flow lost it in two frames (read 0.01 of
# 11.9 px), beyond 8 hops of its start: 2.82 px RMS (DIS 0.88); 0.23 with 16 hops.
@pytest.mark.parametrize(("kind", "lossless"), [("column-along", True), ("column-along", False),
                                                ("column-along-far", True)])
def test_a_shaded_column_sliding_along_its_axis_is_read_by_its_texture_along(tmp_path, kind, lossless) -> None:
    clip = _scene(kind, 1)
    video = _png_folder(tmp_path, clip) if lossless else encode(clip, tmp_path / "clip.mp4", crf=18)
    fps = ("--fps", str(FPS)) if lossless else ()
    ours = _run(tmp_path, clip, video, "default", *fps)
    base = _run(tmp_path, clip, video, "dis", *fps, "--method", "dis")
    print(f"{kind} (lossless {lossless}): default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} "
          f"valid {ours[2]:.2f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= 1.2 * base[0] and ours[1] >= (0.97 if lossless else 0.8) and ours[2] >= 0.95
    assert ours[3]["along_texture"] >= 0.5 * FRAMES


# A cable 6 px thick, 3 degrees off level, its mask 5 px across it: no pixel of the mask lies clear
# of the outline, so it has no paint of its own to fit along it (method.ALONG_MIN_CLEAR). Fitted
# all the same, from a walk's start along the cable (method.ALONG_WALK_HOPS), the paint's along
# motion was taken 3.6-5.7 px off in isolated tracked frames (the POIs' match of a mask inside a
# dark member kept improving along it), and the tilt carried that into the motion across: 0.074 px
# RMS where deepflow-dense read 0.055 (bench_scene_kinds' own cable 0.099, its table 0.033).
def test_a_thin_cable_is_not_read_along_from_a_paint_it_does_not_have(tmp_path) -> None:
    clip = _scene("cable", 1)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dense", "--method", "deepflow-dense")
    print(f"cable: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; deepflow-dense {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= max(1.1 * base[0], 0.05) and abs(ours[1] - 1.0) <= 0.03 and ours[2] >= 0.95
    assert ours[3]["along_texture"] == 0


# Not a bar painted in lengthwise stripes, strong across it too, whose outline against the wall is a
# clean step: a first version of the rule above, without the outline's misfit, read such bars by
# the dense flow, 0.057 -> 0.090 and 0.071 -> 0.096 px RMS, 4 % short (a reviewer's find).
def test_a_bar_painted_lengthwise_is_read_by_its_outline(tmp_path) -> None:
    ours, base = _default_and_dis(tmp_path, "lengthwise", 1)
    assert ours[0] <= max(1.1 * base[0], 0.05) and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_readings"] >= 0.9 * FRAMES and ours[3]["why_outline_shaded_across"] == 0


# A dark deck (grey 60, a faint texture) against a bright, flat sky (215), the mask inside its lower
# outline, the upper one 30 px away: two draws where the default read 0.105 and 0.132 px RMS (DIS
# 0.069 and 0.101) before 2026-12-07. The blur models, which cannot draw so sharp an outline,
# read it 0.2-0.5 px short and were kept where their outlines agreed best; and the support's upper
# side, where the grow stopped at its reach 6 px short of that outline, gave profiles straddling
# the deck's texture and the outline. Now 0.040 and 0.037 (member.UNCHOSEN_BLUR_MISFIT,
# MemberEdges._beside_stopped); on six other draws 0.043-0.075 against DIS's 0.069-0.098.
@pytest.mark.parametrize("seed", [55, 56])
def test_a_dark_deck_against_a_bright_sky_is_read_by_its_one_outline_in_reach(tmp_path, seed) -> None:
    ours, base = _default_and_dis(tmp_path, "deck", seed)
    assert ours[0] <= max(1.1 * base[0], 0.05) and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_readings"] >= 0.9 * FRAMES


# A grey deck 40 grey levels darker than a grey sky, its lower outline alone in reach: every profile
# shares the outline's sub-pixel phase, so their spread cannot judge the blur models, and before
# 2026-12-07 it picked models reading 0.1137 and 0.0882 px (DIS 0.0616 and 0.0643); on one outline
# the profiles matched whole are now kept (member.ONE_OUTLINE_WHOLE): 0.0566 and 0.0555. Its slope
# is short as DIS's is (0.984 on 56, DIS 0.979).
@pytest.mark.parametrize("seed", [55, 56])
def test_a_faint_deck_on_its_one_outline_is_read_by_its_profiles_matched_whole(tmp_path, seed) -> None:
    ours, base = _default_and_dis(tmp_path, "deck-faint", seed)
    assert ours[0] <= max(1.1 * base[0], 0.05) and ours[2] >= 0.95
    assert abs(ours[1] - 1.0) <= min(0.03, abs(base[1] - 1.0) + 0.01)
    assert ours[3]["outline_readings"] >= 0.9 * FRAMES


# An I-beam's web between its dark flanges with the lens out of focus (1.5 px): the sharp outline
# model cannot draw outlines that blurred (it misfits the reference's 40-50 times the noise) and
# locks to the pixel grid, every profile of the straight outline alike, so its outlines agree best
# of all and it was read, 0.3-0.45 px off in a third of the frames (0.116 px RMS, DIS 0.087) before
# 2026-12-06; the models that cannot draw the reference's outlines are now left out (0.031).
def test_an_outline_blurred_beyond_the_sharp_model_is_read_by_the_models_that_fit_it(tmp_path) -> None:
    clip = _scene("ibeam-blurred", seed=2)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"ibeam-blurred: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= min(max(1.1 * base[0], 0.05), 0.06)
    assert abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_readings"] >= 0.9 * FRAMES
    # The sidecar says the outline was read without the models the soft reference ruled out.
    assert ours[3]["outline_models_left_out"] == ours[3]["outline_readings"]


# Other draws of the blurred I-beam web: a blur model whose outlines agreed best read a frame in four
# 0.25-0.45 px short (0.114 and 0.174 px RMS on these draws, DIS 0.062 and 0.114) before
# 2026-12-07. The flanges beyond the web's outlines move with it, and the blur models take the
# reference's pixels beyond an outline for a background that stands still: where the dense flow
# and the pixels beyond show the background moving with the member (method.WHOLE), the profiles
# matched whole, which draw what each profile shows, read the outline (0.021 and 0.030).
@pytest.mark.parametrize("seed", [203, 204])
def test_an_ibeam_web_between_flanges_moving_with_it_is_read_by_its_profiles_matched_whole(tmp_path, seed) -> None:
    ours, base = _default_and_dis(tmp_path, "ibeam-blurred", seed)
    assert ours[0] <= max(1.1 * base[0], 0.05) and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_whole_with"] >= 1 and ours[3]["outline_readings"] >= 0.9 * FRAMES


# A few tenths of a pixel under heavy compression: x264 repeats the reference's blocks where the
# motion is below what it codes, up to 64 % of the member's outline. Before 2026-12-06 the texture
# fit counted those pixels and an outline that had them read no motion for 13 frames running
# (CRF 28: 0.153 px, slope 0.42; CRF 33: 0.134 px, slope 0.45; DIS 0.063 / 0.79 and 0.086 /
# 0.72); the copies are now left out of the fits and an outline mostly copied is not read.
@pytest.mark.parametrize(("crf", "seed"), [(28, 3), (33, 1)])
def test_a_tiny_motion_the_codec_mostly_copied_from_the_reference_is_read(tmp_path, crf, seed) -> None:
    clip = _scene("tiny", seed=seed)
    video = encode(clip, tmp_path / "clip.mp4", crf=crf)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"tiny at CRF {crf}: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= max(1.1 * base[0], 0.05)
    assert ours[1] >= base[1] - 0.03 and ours[1] >= 0.8
    assert ours[2] >= 0.95
    timings = ours[3]
    assert timings["codec_copies_left_out"] >= 0.5 * FRAMES


# A faint panel (5 grey levels, its texture's strength 0.98 grey levels per pixel: just short of
# method.MIN_TEXTURE_GRADIENT) moving a few tenths of a pixel at CRF 18, its outline 20 px beyond the
# mask: x264 copied 39-61 % of the outline's profiles from the reference in every frame, and the
# outline, the only reading a texture that faint allowed, read no motion at all for 10 frames
# running (0.199 px RMS, slope 0.08; DIS 0.094 / 0.83) before 2026-12-07. Where the codec froze
# the outline, a texture of at least method.FROZEN_TEXTURE_GRADIENT is fitted and taken instead
# (0.065 / 0.90). Seed 304 draws a texture just strong (1.04 and 1.09): the outline counted as
# frozen only from half its profiles copied on (x264 copied 36 % on average), and read 0.203 px RMS,
# slope 0.05 (DIS 0.079 / 0.75) until a strong texture's outline was judged frozen as a fainter
# one's is (method.FROZEN_TEXTURE_COPIED): 0.068 / 0.75.
@pytest.mark.parametrize("seed", [106, 304])
def test_a_faint_panels_texture_is_read_where_the_codec_froze_its_outline(tmp_path, seed) -> None:
    ours, base = _default_and_dis(tmp_path, "tiny-faint", seed)
    assert ours[0] <= max(1.1 * base[0], 0.05) and ours[1] >= base[1] - 0.03 and ours[2] >= 0.95
    assert ours[3]["why_outline_codec_copied"] >= 1 and ours[3]["affine_readings"] >= 0.5 * FRAMES


# Not where the codec leaves the texture's reading imprecise: faint bars (5 grey levels, strength
# 0.88-0.99) moving +-0.3 px at CRF 28, their codec floors 0.14-0.30 px, x264 copying more than a
# quarter of the outline's profiles in most frames. With their texture taken there (a first version
# of the rule) they read 0.154 -> 0.290 and 0.218 -> 0.379 px RMS (DIS 0.173 and 0.284; a
# reviewer's find); their outline reads them as before.
def test_a_faint_bars_texture_is_not_taken_where_the_codec_leaves_it_imprecise(tmp_path) -> None:
    clip = make_clip(seed=3, frames=40, height=160, width=208, texture=5.0, amplitude=0.3)
    video = encode(clip, tmp_path / "clip.mp4", crf=28)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"faint bar +-0.3 px, CRF 28: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= 1.1 * base[0] and ours[1] >= base[1] and ours[2] >= 0.95
    assert ours[3]["affine_readings"] == 0


# The bench's own kind of painted bar (48 frames, CRF 18), a draw whose outline models disagree: a
# model whose profiles spread 3.3 times the best one's, reading half the motion, counted fully in
# the uncertainty, which came to 0.67 px: the clip was flagged unresolved, every frame invalid,
# though read 0.117 px RMS (before 2026-12-07). The uncertainty reported now weighs each model by
# the inverse of its spread (member.PLAUSIBLE_REPORTED); the readings are those of before.
def test_a_painted_bar_whose_outline_models_disagree_keeps_its_frames_valid(tmp_path) -> None:
    clip = make_clip(seed=2, frames=48)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    rmse, slope, valid, _ = _run(tmp_path, clip, video, "default")
    error, sigma, _ = _error_and_sigma(tmp_path, clip)
    coverage = float(np.mean(np.abs(error[1:]) < 2 * sigma[1:]))
    print(f"painted bar, seed 2: RMSE {rmse:.4f} px, valid {valid:.2f}, median sigma {np.median(sigma):.3f}, "
          f"2-sigma coverage {coverage:.2f}")
    assert rmse <= 0.13 and abs(slope - 1.0) <= 0.03  # (2.3 % short, as before)
    assert valid >= 0.95 and coverage >= 0.9


# The same rule, frame by frame: a faintly painted bar (4 grey levels, strength 0.84-0.90) moving
# +-1.5 px across itself, the codec freezing its outline only in the first frames, where it stands
# nearly still. A first version of the rule let the texture's chain from such a frame read the next
# 30 frames, 0.092 px RMS where the outline reads 0.062 (a reviewer's find); the chain now ends
# where the codec no longer freezes the outline.
def test_a_faint_bar_moving_across_itself_is_read_by_its_outline_where_the_codec_keeps_it(tmp_path) -> None:
    clip = make_clip(seed=2, frames=40, height=160, width=208, texture=4.0, amplitude=1.5)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    print(f"faint bar +-1.5 px: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; readings {ours[3]['outline_readings']:.0f} outline")
    assert ours[0] <= 0.07 and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_readings"] >= 0.9 * len(clip.frames)


# A faint texture (about 1.4 grey levels per pixel) without noise, moving a few tenths of a pixel,
# in lossless frames (a renderer's, a clean camera's): most of its pixels round to the
# reference's grey levels, and the texture fit's robust weights, scaled by the residuals' median
# deviation (nearly 0), cut the pixels that did change as outliers: 0.159 px RMS, slope 0.38
# (DIS 0.026 / 0.91) before 2026-12-06. The scale is now never below the rounding's own spread.
def test_a_clean_faint_textures_motion_of_a_few_tenths_of_a_pixel_is_read_to_scale(tmp_path) -> None:
    clip = _scene("tiny-faint", seed=1, noise=0.0)
    frames = _png_folder(tmp_path, clip)
    ours = _run(tmp_path, clip, frames, "default", "--fps", str(FPS))
    base = _run(tmp_path, clip, frames, "dis", "--fps", str(FPS), "--method", "dis")
    print(f"tiny-faint, lossless: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= 1.1 * base[0]
    assert ours[1] >= base[1] - 0.03 and ours[1] >= 0.9
    assert ours[2] >= 0.95 and ours[3]["affine_readings"] >= 0.9 * FRAMES


# A faint texture filling the view (no member, no background), moving a few tenths of a pixel: the
# member's support grows through pixels that all look like the mask's until grow_px stops it, and
# the texture's random steps of 6 grey levels at that limit were taken for 31 outline profiles:
# the outline model read 0.186 px RMS, slope 0.41 (DIS 0.016 / 1.00) before 2026-12-06. An
# outline is now only where the scene stops the support; here there is none, the dense flow reads.
@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_a_texture_filling_the_view_is_not_read_from_an_outline_it_does_not_have(tmp_path, noise) -> None:
    clip = _scene("tiny-faint-view", seed=1, noise=noise)
    frames = _png_folder(tmp_path, clip)
    ours = _run(tmp_path, clip, frames, "default", "--fps", str(FPS))
    base = _run(tmp_path, clip, frames, "dis", "--fps", str(FPS), "--method", "dis")
    print(f"tiny-faint-view, noise {noise}: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f}; "
          f"dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= max(1.1 * base[0], 0.05)
    assert abs(ours[1] - 1.0) <= abs(base[1] - 1.0) + 0.03 and ours[2] >= 0.95
    assert ours[3]["outline_readings"] == 0


def test_a_paint_too_faint_for_the_codec_to_keep_its_motion_along_says_so(tmp_path) -> None:
    """The bench's paint (2 grey levels) on a bar sliding +-1.5 px along its length, H.264 at CRF
    18: x264 copies much of the paint's blocks unmoved or in whole pixels, so the decoded frames
    hold the motion along the bar only in part (the paint's fit has minima a pixel apart). The
    default reads this clip still along the bar (slope 0.01, 1.04 px RMS; DIS 0.6 of it), and
    before 2026-12-05 said so with a sigma of 0.18 px (2-sigma coverage 0.14): a confident wrong
    reading. Its sigma along the bar now holds what the POIs could not tell apart (every motion
    along fitted that matched them not clearly worse than the one taken, and in a tracked frame
    a pixel either side where the POIs match it at least as well) and, where the paint's fit
    gave it, the paint's codec floor: coverage 0.26, still far from honest (counting every
    position a pixel along that matched not clearly worse read 0.89, but flagged every frame of
    an inclined faint bar: see the README). Across the bar (still) the outline reads as before."""
    clip = _scene("along-faint", seed=53)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    rmse, slope, valid, timings = _run(tmp_path, clip, video, "default")
    error, sigma, rows = _error_and_sigma(tmp_path, clip)
    across = np.array([float(r["dx_px"]) for r in rows])
    coverage = float(np.mean(np.abs(error[1:]) < 2 * sigma[1:]))
    print(f"along-faint: RMSE {rmse:.3f} px, slope {slope:.3f}, 2-sigma coverage {coverage:.2f}, "
          f"median sigma {np.median(sigma):.3f} px, along from the paint {timings['along_texture']:.0f}")
    assert rmse > 0.5  # the along motion is not read (if it is one day, this test says so)
    assert coverage >= 0.2 and valid >= 0.95
    assert np.sqrt(np.mean(across ** 2)) < 0.1  # across the bar (still): the outline, as before
    assert np.median(np.array([float(r["sigma_dx_px"]) for r in rows])) < 0.1


def test_a_faint_bar_at_an_angle_keeps_its_frames_valid(tmp_path) -> None:
    """A faint bar at 30 degrees moving along x (half of that motion along the bar): its readings
    stay valid. (A sigma along the member that counted every position a pixel along matching
    the POIs not clearly worse, tried on 2026-12-05, grew both axes' sigmas past the tool's
    0.35 px limit on an inclined member and flagged every frame of `bench_scene_kinds.py`'s
    `inclined`, its readings unchanged.)"""
    clip = _scene("inclined", seed=61)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    rmse, slope, valid, timings = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"inclined: default RMSE {rmse:.3f} px slope {slope:.3f} valid {valid:.2f}; dis {base[0]:.3f} / {base[1]:.3f}")
    assert valid >= 0.95
    assert rmse <= max(1.1 * base[0], 0.05) and abs(slope - 1.0) <= 0.06


def test_a_videos_frames_exported_to_images_are_read_as_the_video_is(tmp_path) -> None:
    """Frames a lossy codec made keep its error in lossless files (a video exported to PNG images,
    as DIC tools want their input): they are read as a lossy stream of unknown quality (the sidecar
    says so), as well as the video itself, with the codec's error in the sigma (before, read as
    lossless: 0.14 of the frames within 2 sigma). The scene's own frames in PNG stay lossless."""
    clip = _scene("panel", seed=3)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    exported = tmp_path / "exported"
    exported.mkdir()
    for index, frame in enumerate(decode(video)):
        cv2.imwrite(str(exported / f"{index:04d}.png"), frame)
    from_video = _run(tmp_path, clip, video, "video")
    from_images = _run(tmp_path, clip, exported, "images", "--fps", str(FPS))
    sidecar = json.loads((tmp_path / "images.json").read_text())
    assert (sidecar["parameters"]["codec_crf"], sidecar["parameters"]["bias_correction"]) == (DEFAULT_CRF, False)
    assert any("read as a lossy stream" in note for note in sidecar["notes"])
    assert from_images[0] <= 1.1 * from_video[0] + 0.002 and abs(from_images[1] - 1) <= 0.02
    with (tmp_path / "images.csv").open() as handle:
        rows = list(csv.DictReader(handle))
    error = np.array([float(r["dx_px"]) for r in rows]) - (clip.truth_px - clip.truth_px[0])
    sigma = np.array([float(r["sigma_dx_px"]) for r in rows])
    assert np.mean(np.abs(error[1:]) <= 2 * sigma[1:]) >= 0.85
    assert main(["track", str(_png_folder(tmp_path, clip)), "--fps", str(FPS), "--mask", str(tmp_path / "mask.png"),
                 "--max-frames", "6", "--out", str(tmp_path / "lossless.csv"), "--no-progress"]) == 0
    parameters = json.loads((tmp_path / "lossless.json").read_text())["parameters"]
    assert (parameters["codec_crf"], parameters["bias_correction"]) == (None, True)


# The tests' painted bar seen through a lens out of focus (Gaussian blur 1.5 px, H.264 CRF 18): the
# sharp outline model cannot draw the reference's outlines (5-12 times their noise, the 1 px
# model 0.8-1.3), yet its error, common to every profile, made its outlines agree best and it
# was kept, reading the bar short where it moved furthest: 0.375 px RMS on this draw, DIS 0.240,
# before 2026-12-07. Left out where a blur model draws the outlines and the codec keeps a step
# sharp (member.SHARP_BLURRED_MISFIT): 0.205. On the same bar at CRF 30 the codec's smear misfits
# the sharp model as much, and there it reads best: it stays (see test_cli_precision).
def test_a_bar_blurred_by_the_lens_is_not_read_by_the_sharp_outline_model(tmp_path) -> None:
    from flow.methods.deepflow.member import BLURS, MemberEdges

    clip = make_clip(seed=403, blur_px=1.5)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    reference = decode(video)[0]
    edges = {crf: MemberEdges.from_reference(reference, clip.mask, codec_crf=crf) for crf in (18.0, 30.0)}
    sharp = BLURS.index(0.0)
    assert sharp not in edges[18.0].models and sharp in edges[30.0].models
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"blur: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} valid {ours[2]:.2f}; dis {base[0]:.4f} / {base[1]:.4f}")
    assert ours[0] <= 1.1 * base[0] and abs(ours[1] - 1.0) <= 0.015 and ours[2] >= 0.95
    assert ours[3]["outline_models_left_out"] >= 1
    # The run takes the stream's crf to the outline: the same bar at CRF 30 keeps every model
    heavy = tmp_path / "crf30"
    heavy.mkdir()
    video = encode(clip, heavy / "clip.mp4", crf=30)
    assert _run(heavy, clip, video, "default")[3]["outline_models_left_out"] == 0


# The tests' painted bar in a grey (118) close to its wall's (111 +- 35), H.264 CRF 18: where the
# bar stands over the wall's own greys its outline hardly shows, and in 39 frames of 90 the
# outline fit was refused as too imprecise (sigma above 0.5 px on both axes). The dense flow
# read those frames instead, its smoothing holding the faint bar back towards the still wall:
# 1.0-1.7 px short where it stood 4-5.5 px out, the clip 0.924 px RMS, slope 0.770, where DIS
# read 0.245 / 0.944 (before 2026-12-08). The bar's
# own faint paint, fitted over the mask alone, resolves them (sigma 0.14-0.30 px with the
# codec's error) and reads 0.241 / 0.970 (method.FAINT_TEXTURE_MAX_SIGMA_PX).
def test_a_faint_bar_whose_outline_is_refused_is_read_by_its_paint_not_the_dense_flow(tmp_path) -> None:
    clip = make_clip(seed=401, member_grey=118.0)
    video = encode(clip, tmp_path / "clip.mp4", crf=18)
    ours = _run(tmp_path, clip, video, "default")
    base = _run(tmp_path, clip, video, "dis", "--method", "dis")
    print(f"low contrast: default RMSE {ours[0]:.4f} px slope {ours[1]:.4f} valid {ours[2]:.2f}; "
          f"dis {base[0]:.4f} / {base[1]:.4f}; readings {ours[3]['affine_readings']:.0f} by the paint")
    assert ours[0] <= 1.1 * base[0] and abs(ours[1] - 1.0) <= abs(base[1] - 1.0) and ours[2] >= 0.95
    assert ours[3]["why_faint_texture"] >= 0.25 * len(clip.truth_px)
    error, sigma, _ = _error_and_sigma(tmp_path, clip)
    assert 0.85 <= np.mean(np.abs(error[1:]) <= 2 * sigma[1:])
