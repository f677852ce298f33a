"""Sub-pixel motion of a structural member from its edges (mask-aware refinement).

A painted steel member, a concrete deck or a cable has almost no texture: the
information about its motion is at its edges, where it meets what is behind it.
A dense flow with a smoothness term spreads the background's motion (often
zero) across those edges into the member and under-reads it; a window-based
tracker mixes the two. Here the user's POI mask says which pixels belong to the
structure, and its edges are measured as what they are, the boundary between
two layers:

1. *Support.* In the reference frame the mask is grown, through pixels that
   look like the member (grey level and local gradient like the mask's), up to
   where it ends; every row and column that crosses the outline gives one *edge
   profile* (rows where the outline is steeper than 45 degrees, columns
   elsewhere).
2. *Outline position.* A pixel on the outline integrates a fraction of the
   member and the rest of the background: ``I = w + (m - w) Phi(e - j)``, with
   ``Phi`` the member's area coverage of the pixel (a step, optionally blurred),
   ``m`` the member's grey and ``w`` the background hidden under the pixel. ``w``
   is predicted from the visible background pixels beyond the outline by the
   best linear predictor from the background's own autocovariance (measured in
   the reference around the member): predicting it by its neighbour alone
   regresses towards the neighbour and reads the motion about 1.5 % short on a
   textured wall. ``e`` (and ``m``) are fitted by Gauss-Newton, the pixels the
   model uses following ``e`` itself, so the estimate is continuous; it is exact for
   area-sampled images whatever the member's grey, and forgets its starting guess on
   a sharp outline. On an outline a codec has smeared over several pixels it does not:
   the sharp model then fits several positions about equally well (0.5-1.3 px apart)
   and stays near its start (started 1 px off on the bench's CRF 30 clip, it ends
   0.3-0.7 px off). Where the member has moved onto background that the reference shows
   (by more than a few pixels), that background is not predicted but known: the
   outline is located by its area, the member coverage summed over a window, which no
   spread of the outline biases (a compressed clip's smoothed outlines read 1 % short
   otherwise).
3. *Motion field.* Every profile measures the outline's displacement along its
   row (``u - s v``, ``s`` the outline's slope) or column (``v - s u``). A beam's
   kinematics, translation, rotation and bending across the member, translation,
   stretch and rotation along it, is fitted to all profiles by iteratively
   re-weighted least squares (Tukey's biweight: profiles where the hidden
   background was not predictable, or something crosses the outline, drop out),
   each profile weighted by its variance from the outline fit. Directions the
   outline does not constrain (motion along a straight member) keep the dense
   flow's value through a weak prior.
4. *Blur.* The outline's spread (lens focus, motion blur, a codec's smoothing)
   is not known and a key frame differs from the frames predicted from it, so
   each frame is measured under several blur models and the one under which all
   outlines agree best on one motion is kept.

The dense flow only starts it: a coarse step finds each outline within a few
pixels of the dense flow's guess (a jump, an under-read), the fit of all
profiles then predicts every outline to a few hundredths of a pixel for the
fine fit.

Uncertainty: the fit's covariance, scaled by the robust spread of the
standardised residuals and by the design effect of neighbouring profiles'
correlated errors (they share a blob of background texture, a codec block),
plus the spread of the blur models' answers (a systematic error all profiles
of a straight outline share, which their scatter cannot show).

Frames stay independent: each frame is compared with the reference only.

References
----------
.. [1] P. J. Huber, *Robust Statistics*, Wiley 1981 (M-estimation, IRLS).
.. [2] A. J. Tabatabai, O. R. Mitchell, "Edge location to subpixel values in
   digital imagery", IEEE TPAMI 6(2), 1984 (edge location from area and moments).
.. [3] N. Cressie, *Statistics for Spatial Data*, Wiley 1993 (best linear
   prediction from the covariance, kriging).
.. [4] L. Kish, *Survey Sampling*, Wiley 1965 (the design effect of correlated samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit

from flow.measure.photometric import sample
from flow.measure.robust import MAD_TO_SIGMA
from flow.methods.deepflow.checks import check_shape

# Visible background pixels the hidden ones under the outline are predicted from.
N_PREDICT = 3
# Farthest pixel (from the first visible background pixel) a predictor is made for.
MAX_DISTANCE = 10
# A blur model whose outlines misfit the reference (their median weighted mean squared residual,
# about 1 where a model explains a profile to its noise) this many times as badly as the best
# model's, or the noise's, is not used for the frames (see MemberEdges._plausible_models).
# Measured, the sharp model's ratio: the bench's painted bars 0.15-3.0, its shaded column 1.7, the
# workbench's beam 0.6-9.2 (its averaged, undistorted references), the scene kinds of the tests
# and of bench_scene_kinds 0-1.1; an I-beam's web blurred 1.5 px 38-50 and a bar over a swaying
# background blurred so 21, where it read 0.3-0.5 px off; a textured panel 27 (read by its
# texture). A thin cable (3 px) leaves out the 0.7 and 1 px models. (Taking the sharp model out
# everywhere costs the bench's bars: compressed 0.187 -> 0.277 px, edge-on-thin 0.054 -> 0.087.)
IMPLAUSIBLE_MISFIT = 16.0
# Where the sharp model draws the reference's outlines to their noise (its misfit at most 1), a
# blur model that misfits them more than this many times the noise measures the frames but is
# never the one kept (see MemberEdges.fit): the outline is sharp, and the blur models' wider
# transition, unable to draw it, pulls it towards whole pixels, where their outlines may agree
# best. A dark deck against a bright sky (155 grey levels of contrast, H.264 CRF 18), the mask
# inside its one outline in view: the sharp model's misfit 0.15, the blur models' 2.5-9.3; they
# read it 0.2-0.5 px short (0.23-0.30 px RMS, the sharp model 0.025) and were kept in 4 of 48
# frames (0.123 px RMS, DIS 0.072). Their disagreement still enters the reading's uncertainty.
# The bench's clips whose sharp model draws the reference so: the blur models 0.44-1.48.
UNCHOSEN_BLUR_MISFIT = 2.0
# The mirror case, a lens's blur: where a blur model draws the reference's outlines to about their
# noise (misfit at most BLURRED_DRAWN_MISFIT) and the sharp model misfits them more than
# SHARP_BLURRED_MISFIT times as badly, the outline is blurred beyond a step and the sharp model,
# locked to the pixel grid by it, is not used for the frames, on a stream whose codec keeps a
# step sharp (lossless, or H.264 at a crf of at most SHARP_CODEC_CRF: a phone's quality). A
# heavier codec smears a sharp outline just so (the tests' bar at CRF 30: sharp 8.3, the 1 px
# model 0.84), and there the sharp model reads it best (0.226 px RMS; 0.245 without it). A
# stream that does not state its crf (a phone's hardware encoder, x264 at a bit rate) is taken
# at the tool's default, 23 (flow.pipeline.DEFAULT_CRF), and counts as one that keeps a step
# sharp: the workbench's 0.01 bit-per-pixel stream so read 1.205 px RMS instead of 1.191 (its
# readings are the codec's either way).
BLURRED_DRAWN_MISFIT = 1.5
SHARP_BLURRED_MISFIT = 5.0
SHARP_CODEC_CRF = 23.0
# Where the profiles lie on one outline (ONE_OUTLINE_SHARE of them on one side of the member, in
# one scan direction; a few may lie on the side the grow's reach stopped at, see OVERRUN_LINES), they share
# its sub-pixel phase, and a blur model's phase-dependent error is common to all of them: their
# spread cannot judge the models. There the profiles matched whole (no model) are kept, unless
# every blur model is unchosen (UNCHOSEN_BLUR_MISFIT: the outline is sharper than they draw, and
# the sharp model's is exact). A deck against a sky 40 grey levels brighter, its lower outline
# alone in reach, H.264 CRF 18, two draws: 0.096 and 0.080 px RMS -> 0.058 and 0.053 (DIS 0.075,
# 0.079); a sky with a texture of 8 grey levels 0.098 -> 0.062 (DIS 0.075). At 155 grey levels of
# contrast the blur models are unchosen and the spread still chooses (0.038 px, and 0.036-0.039
# with a textured sky), where the whole-profile match read 0.051 (0.042-0.048). On lossy frames
# only: on lossless ones (an area-sampled outline, as a camera file's) the sharp model draws the
# outline exactly and the whole-profile match has an error of its own, common to every profile
# (the same faint deck, lossless: the sharp model 0.002-0.026 px off, the whole-profile match
# 0.064-0.095).
ONE_OUTLINE_WHOLE = True
ONE_OUTLINE_SHARE = 0.9
# ... and only in front of a uniform background: the whole-profile match is biased by a textured
# one, which does not move (see _shift). Uniform: the reference's pixels beyond the outline
# (from 2 px plus three times the blur model that draws it best, 3-4 px on, see
# _background_uniform) vary (their standard deviation, the median over the profiles) by at most this share
# of the outline's contrast. The decks' skies above: 0-0.023 (a texture of 0-12 grey levels); a
# wide painted bar in front of a wall of 110 +- 25 grey levels, the mask near its one outline in
# reach: 0.10-0.24, where the whole-profile match read 0.14-0.81 px RMS and the spread's choice
# 0.086-0.17 (DIS 0.10-0.14).
UNIFORM_BACKGROUND = 0.05
# Half length of a profile strip (pixels on each side of its centre).
HALF = 9
# Pixels either side of the guess where the coarse step looks for the outline.
SEARCH = 3
# Blur (Gaussian sigma, px, on top of the pixel's own area) tried for the outline's spread.
BLURS = (0.0, 0.3, 0.5, 0.7, 1.0)
# Parameters of the motion field across and along the member (see _Field).
N_ACROSS = 3
N_PARAMS = 6
# Outline models whose profiles agree within this factor of the best one's are plausible: what
# they disagree on decides whether an outline reading is precise enough to be taken.
PLAUSIBLE = 4.0
# What a reading reports of that disagreement: the models within this factor, each weighted by the
# inverse of its profiles' spread. Counted alike within a factor of 4, a model whose profiles
# spread 3.3 times the best one's and read half the motion counted fully: on two of twelve draws of
# the bench's kind of painted bar (48 frames, CRF 18), read 0.117 and 0.086 px RMS, the typical
# uncertainty came to 0.67 and 0.40 px and every frame was flagged (see
# flow.measure.quality.MAX_TYPICAL_SIGMA_PX); reported this way 0.28 and 0.34, none flagged, the
# 2-sigma coverage of the twelve draws as before (0.87-1.00). Used for the decisions too, it let a
# shaded round column's imprecise outline be taken (0.083 -> 0.161 px RMS): they keep PLAUSIBLE's.
PLAUSIBLE_REPORTED = 3.0
# The member's axes follow its usable outlines where their normals lie this many times as much
# along the mask's longer side as across it (see MemberEdges._orient_by_outline).
ORIENT_RATIO = 4.0
# The support's edge is an outline where at least this share of its profiles were stopped by
# the scene (see MemberEdges._profiles); below it, those where only grow_px stopped the grow are
# left out. A texture filling the view has none stopped; the workbench's heavily compressed beam
# has 247 of 250 (its 3 others, where the grow overran the beam's edge by a few pixels, are its
# edge all the same: leaving them out read the scenario 0.058 -> 0.071 mm RMSE).
SCENE_STOPPED = 0.5
# Where most are, those the grow's limit stopped are kept within this many lines of one the scene
# stopped on the same side of the support (the grow overran the outline here and there); farther,
# left out (the grow stopped at its limit along a whole side, on no outline: a dark deck wider
# than the grow's reach, its far outline 6 px beyond the limit, gave 67-80 profiles straddling the
# deck's texture and that outline, and the sharp model read it 0.15-0.18 px RMS, lossless and on
# H.264, where the one outline in reach read 0.017-0.039).
OVERRUN_LINES = 4
# Floor of the robust scale of the standardised profile residuals.
MIN_SCALE = 0.5
# A reference profile whose model misfit exceeds this many times the median is not used.
MISFIT_RATIO = 4.0
# Half length of the window (pixels either side of the outline's) over which an outline that has
# moved onto background the reference shows is located by its area (see MemberEdges._known).
KNOWN_HALF = 2
# Reference pixels within this distance (px) of the reference's outline are not pure background.
KNOWN_MARGIN = 2.0
# A window whose background beyond differs from the reference's by more than this many times the
# median such difference (something moved there: an occlusion, a shadow) is not used.
KNOWN_STATIC = 4.0
# Half length of the profile a frame is matched to the reference over, whole: SHIFT_HALF px on the
# member's side of the reference's outline and as many beyond it; on lossless frames SHIFT_BEYOND
# beyond it. The background beyond does not move: over a textured wall its pixels pulled the match
# towards no motion. The tests' lossless bar over a wall of +-35 grey levels, moved 0.1-0.3 px,
# read 0.56-0.63 of it with 5 px beyond, 0.91-0.97 with 2 (the outline's pixel and its blur's
# reach) and the sampling of _shift_steps; 1 px lost the bench's `compressed` (CRF 30), 0.187 ->
# 0.390 px RMSE. Not on a lossy stream: there both read the workbench's rendered beam worse
# (config/ci.yaml's ambient scene 0.0162 -> 0.0213 mm RMSE, occlusion 0.0149 -> 0.0183; the
# bench's `tiny` 0.0646 -> 0.0705 px, g4-cylinder 0.041 -> 0.048, g9-large-motion 0.123 ->
# 0.131), though other bars moving 0.3 px read better (four of the tests' at CRF 18: 0.070-0.124
# -> 0.050-0.083 px).
SHIFT_HALF = 5
SHIFT_BEYOND = 2
# Gauss-Newton steps of one outline fit (at most: the fine fit stops at convergence, see CONVERGED_PX).
N_STEPS = 8
# Rounds of each blur model's outline fit: the first from the coarse outlines, the next from the
# outlines the fitted motion predicts (2 since 2026-12-05, 3 before). Dropping the third round
# made no bench clip read worse and some better (g9-large-motion 0.157 -> 0.124 px RMSE,
# compressed 0.191 -> 0.187) and saved a third of the fit's time; a synthetic faint bar reads
# about 0.005 px shorter across with two (tests/unit/test_deepflow_models.py).
OUTLINE_ROUNDS = 2
# A Gauss-Newton step below this (px; and relative, of the member's grey) ends the fine fit's steps.
CONVERGED_PX = 1e-7
# Farthest neighbour (lines apart) whose error correlation the uncertainty accounts for.
MAX_LAG = 32
# A support grown more than this (px) beyond a straight step of the mean grey beside the mask
# has crossed the member's outline (see _beyond_steps).
STEP_LEAK_PX = 2
# ... looked for across a mask at least this many times longer than wide only (along a member
# the support rightly grows beyond the mask's ends, and a sagging cable leaves the mask's band).
STEP_ELONGATION = 2.0
# ... a step the mean grey stays off the member's level for this many px (a band inside the
# member comes back), found in the same bin (+-1) in each of STEP_PARTS parts of the mask's length.
STEP_STAY_PX = 6
STEP_PARTS = 4
# A mask drawn past its member's outlines onto the background (see inner_outline): the step of the
# mean grey that ends the member inside the mask takes at least RIM_STEP_SHARE of its change within
# RIM_SPAN_PX, changes at least RIM_CONTRAST likeness tolerances (of the mean grey of the mask's
# lines along it, or across it at an end: see _cut_ends), and at least RIM_MIN_PX of the mask lie
# beyond its first pixel (a mask drawn on the outline reads as one drawn inside it).
RIM_STEP_SHARE = 0.6
RIM_SPAN_PX = 3
RIM_CONTRAST = 2.0
RIM_MIN_PX = 2
# A mask of more pixels is taken whole (its statistics across would cost about 0.5 GB and 5 s on a
# whole 4K frame's mask; a band round a member in a 4K frame holds a few hundred thousand).
MAX_CUT_PIXELS = 2_000_000
# A mask drawn past its member's end (see _cut_ends): the member ends after the last bin across the
# band where at least END_SHARE of the pixels look like it (of the middle half's share), at most
# END_SPAN_PX after a bin where at least END_BEFORE_SHARE did; only the band's lines along it of which
# at least END_BEFORE_SHARE look like it over its middle half count.
END_SHARE = 0.5
END_BEFORE_SHARE = 0.75
END_SPAN_PX = 4


@dataclass(frozen=True)
class MemberParams:
    """Parameters of :class:`MemberEdges` (defaults for any member; none is per clip).

    grow_px : how far beyond the mask the support may grow (pixels).
    like_k : a pixel looks like the member when its grey is within
        ``like_k`` robust standard deviations of the mask's (at least ``like_floor``
        grey levels) and its gradient is below ``like_k`` times the mask's typical gradient.
    min_contrast : smallest member-background contrast of a usable profile (grey levels).
    ridge : grey levels^2 added to the background covariance's diagonal before the
        predictor is solved (at least 0.1 % of its variance): noise the pixels have beyond
        what the covariance estimate shows, and what keeps a smooth background's nearly
        singular covariance solvable.
    prior_weight : weight of the dense-flow prior per parameter, as a fraction of
        the total weight of the edge profiles.
    tukey_c : biweight tuning constant (in robust standard deviations).
    min_profiles : fewer usable profiles in a frame and the dense flow is kept.
    """

    grow_px: int = 24
    like_k: float = 4.0
    like_floor: float = 6.0
    min_contrast: float = 6.0
    ridge: float = 4.0
    prior_weight: float = 1e-3
    tukey_c: float = 4.685
    min_profiles: int = 12


@dataclass
class MemberFit:
    """Outcome of :meth:`MemberEdges.fit` for one frame."""

    ok: bool
    params: np.ndarray  # (N_PARAMS,) across coefficients, then along (see _Field)
    cov: np.ndarray  # (N_PARAMS, N_PARAMS)
    n_used: int  # profiles with a non-zero final weight
    n_profiles: int
    scale: float  # robust spread of the standardised profile residuals (1 when the variances are right)
    systematic: np.ndarray = field(default_factory=lambda: np.zeros(2))  # (2,) px, x and y
    model: int = -1  # the outline model kept: an index of BLURS, or len(BLURS) (the profiles matched whole)
    spread: float = float("nan")  # px: how well its outlines agree on one motion (robust)
    every_model: bool = True  # every outline model measured the frame (see MemberEdges.fit)
    reported_systematic: np.ndarray | None = None  # (2,) px: the disagreement reported (see PLAUSIBLE_REPORTED)


def context_px(params: MemberParams | None = None) -> int:
    """How far beyond the mask :meth:`MemberEdges.from_reference` reads the reference: the
    support grows ``grow_px`` beyond the mask and its background predictors read ``2 grow_px``
    beyond the support (a window solved around the mask needs this much to give the numbers
    of the whole frame)."""
    return 3 * (params or MemberParams()).grow_px


def _grow(reference: np.ndarray, mask: np.ndarray,
          params: MemberParams) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mask grown through member-like pixels, at most ``grow_px`` beyond it; the pixels
    within that reach; and the same grow let go SEARCH + 1 px further (without the cut of
    :func:`_beyond_steps`): where that one goes on past an edge of the first at its reach, the
    first was stopped by its reach, not by the scene (see :meth:`MemberEdges._profiles`)."""
    grey_like, smooth = _member_like(reference, _one_sided_gradient(reference), mask, params)
    like = grey_like & smooth
    reach = _reach(mask, params.grow_px)
    allowed = (like & reach) | mask
    support = _connected_to(mask, allowed)
    further = _connected_to(mask, (like & _reach(mask, params.grow_px + SEARCH + 1)) | mask)
    beyond = _beyond_steps(reference, mask, support, params)
    if beyond.any():
        support = _connected_to(mask, allowed & ~beyond)
    # Close pinholes of noise inside the member (a pixel of the paint that failed the test).
    closed = cv2.morphologyEx(support.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)) > 0
    return (support | closed) & (reach | mask), reach, further


def _one_sided_gradient(image: np.ndarray) -> np.ndarray:
    """Each pixel's larger one-sided grey difference on x and y, the smaller of each pair: a
    member pixel next to its outline keeps a small one (towards the member), a textured
    background pixel has large ones on both sides."""
    pad = np.pad(image, 1, mode="edge")
    centre_px = pad[1:-1, 1:-1]
    step_x = np.minimum(np.abs(pad[1:-1, 2:] - centre_px), np.abs(centre_px - pad[1:-1, :-2]))
    step_y = np.minimum(np.abs(pad[2:, 1:-1] - centre_px), np.abs(centre_px - pad[:-2, 1:-1]))
    return np.maximum(step_x, step_y)


def _reach(mask: np.ndarray, grow_px: int) -> np.ndarray:
    """The pixels within ``grow_px`` of the mask."""
    return cv2.dilate(mask.astype(np.uint8), cv2.getStructuringElement(
        cv2.MORPH_ELLIPSE, (2 * grow_px + 1, 2 * grow_px + 1))) > 0


def _connected_to(mask: np.ndarray, allowed: np.ndarray) -> np.ndarray:
    """The ``allowed`` pixels connected to the mask: flooded from it (4-neighbours)."""
    n, labels = cv2.connectedComponents(allowed.astype(np.uint8), connectivity=4)
    keep = np.zeros(n, bool)
    keep[np.unique(labels[mask])] = True
    keep[0] = False
    return keep[labels]


def _beyond_steps(reference: np.ndarray, mask: np.ndarray, support: np.ndarray,
                  params: MemberParams) -> np.ndarray:
    """Pixels the grown ``support`` took beyond a straight step of the mean grey: where a
    member's pixels look like its background's one by one (hazard stripes over a textured wall:
    their grey levels overlap), the grow crosses its outline. Averaged along the mask's side,
    the grey still steps there. Across an elongated mask (STEP_ELONGATION), on each side, the
    mean grey of the pixels beside the mask is taken 1 px at a time outwards; the first one that
    differs from the mask's own edge by more than the likeness tolerance (``like_k`` times the
    inner profile's noise, at least ``like_floor``) and stays off for STEP_STAY_PX is where the
    member ends, where each of STEP_PARTS parts of the mask's length finds it in the same bin
    (+-1: a mask drawn a few degrees off the member's edges finds no such step); what the
    support holds more than STEP_LEAK_PX beyond it (at least half the side's length) is returned
    from that bin on (to be left out). A support that stops at its outline is not touched."""
    beyond = np.zeros(mask.shape, bool)
    ys, xs = np.nonzero(mask)
    found = _band_axes(xs, ys)
    if found is None:
        return beyond
    centre, normal, along = found
    # Only the mask's box grown by grow_px is looked at (the support cannot reach beyond it).
    pad = params.grow_px + 1
    y0, y1 = max(int(ys.min()) - pad, 0), min(int(ys.max()) + pad + 1, mask.shape[0])
    x0, x1 = max(int(xs.min()) - pad, 0), min(int(xs.max()) + pad + 1, mask.shape[1])
    box = (slice(y0, y1), slice(x0, x1))
    mask, support, reference = mask[box], support[box], reference[box]
    grid_y, grid_x = np.mgrid[y0:y1, x0:x1]
    s_all, t_all = _coordinate(grid_x, grid_y, centre, normal), _coordinate(grid_x, grid_y, centre, along)
    s_mask, t_mask = s_all[mask], t_all[mask]
    beside = (t_all >= t_mask.min()) & (t_all <= t_mask.max())
    lo, hi = float(s_mask.min()), float(s_mask.max())
    inner_bins = np.rint(s_all[mask] - lo).astype(np.int64)
    inner = np.bincount(inner_bins, weights=reference[mask]) / np.maximum(np.bincount(inner_bins), 1)
    if len(inner) < 4:
        return beyond
    noise = MAD_TO_SIGMA * float(np.median(np.abs(inner - np.median(inner))))
    tolerance = max(params.like_k * noise, params.like_floor)
    length = float(t_mask.max() - t_mask.min()) + 1.0
    # The mask's length in STEP_PARTS parts: a straight outline parallel to the mask steps in
    # the same bin in each of them (a mask drawn a few degrees off the member's edges does not).
    part = np.minimum(((t_all - t_mask.min()) / length * STEP_PARTS).astype(np.int64), STEP_PARTS - 1)
    for side, edge, level in ((1.0, hi, float(np.median(inner[-3:]))), (-1.0, lo, float(np.median(inner[:3])))):
        out = np.rint(side * (s_all - edge)).astype(np.int64)  # bins outwards from the mask's side
        near = beside & (out >= 1) & (out <= params.grow_px)
        steps = [_first_step(out[near & (part == k)], reference[near & (part == k)], level, tolerance,
                             params.grow_px, length / STEP_PARTS) for k in range(STEP_PARTS)]
        step = _first_step(out[near], reference[near], level, tolerance, params.grow_px, length)
        if step is None or None in steps or max(steps + [step]) - min(steps + [step]) > 1:
            continue
        leak = support & (out > step + STEP_LEAK_PX)
        if np.count_nonzero(leak & beside) >= 0.5 * length:
            beyond[box] |= support & (out >= step)
    return beyond


def _coordinate(xs: np.ndarray, ys: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The coordinates of the points ``xs, ys`` along the unit vector ``axis`` from ``centre``."""
    return (xs - centre[0]) * axis[0] + (ys - centre[1]) * axis[1]


def _band_axes(xs: np.ndarray, ys: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The centre of the mask pixels ``xs, ys`` and their axes, across and along the mask (unit
    vectors), where the mask is a band, STEP_ELONGATION times longer than wide; None otherwise."""
    if len(xs) < 3:
        return None
    centre = np.array([xs.mean(), ys.mean()])
    evals, axes = np.linalg.eigh(np.cov(np.stack([xs, ys]).astype(np.float64)))
    if evals[1] < STEP_ELONGATION ** 2 * max(evals[0], 1e-9):
        return None
    return centre, axes[:, 0], axes[:, 1]


def inner_outline(reference: np.ndarray, mask: np.ndarray,
                  params: MemberParams | None = None) -> tuple[np.ndarray, int] | None:
    """The member's part of a ``mask`` drawn past the member's outlines onto the
    background, and how many px it reaches past them (its pixels across it off the member's grey,
    the outline's mixed pixel included, on the wider side); None where the mask
    shows no such outline inside it (the mask drawn inside the member, or on its outline).

    Across the mask, the mean grey of its pixels is taken 1 px at a time (averaged along the
    mask, as :func:`_beyond_steps` does beside it), from the middle outwards on each side. The
    member ends inside the mask where that mean leaves the middle half's level by more than the
    likeness tolerance and stays off it to the mask's edge for at least RIM_MIN_PX, a sharp step
    (at least RIM_STEP_SHARE of the change within RIM_SPAN_PX: a shaded round member's ramp is
    no outline) of at least RIM_CONTRAST tolerances, seen on the same side in all of STEP_PARTS
    parts of the mask's length but one at most (a mark on the member is not; a background that
    looks like the member in one part is). The part returned leaves out the
    step's first pixel and the one before it (the outline's mixed pixels, a blurred outline's
    too); the support grows from it to the outline (see _grow).

    Grown from the whole mask, the member's grey and texture would hold the background's, the
    support would take the background beyond, and its profiles would lie on no outline: a faint
    bar read through a mask 6 px wider on each side than the bar went 0.066 -> 0.56 px RMSE,
    slope 0.67 (the dense flow over the faint paint, and the background's pixels averaged in).

    A mask that is no band (a box about as wide as long, drawn round a stretch of a member) is
    looked at across each image axis in turn, and cut where the member ends inside it on both
    sides: 24 px past each edge of that bar, 0.69 px RMSE, slope 0.60 before.

    Along the member's part (a band), a mask drawn past the member's end (a cantilever's tip)
    is cut there too (see :func:`_cut_ends`)."""
    params = params or MemberParams()
    if np.count_nonzero(mask) > MAX_CUT_PIXELS:
        return None
    core, past = _outlines_inside(reference, mask, params) or (mask, 0)
    ends = _cut_ends(reference, core, params)
    if ends is not None:
        core, past = ends[0], max(past, ends[1])
        # Across again without the background beyond the end, which a part of the mask's length held.
        core, again = _outlines_inside(reference, core, params) or (core, 0)
        past = max(past, again)
    return (core, past) if past else None


def _outlines_inside(reference: np.ndarray, mask: np.ndarray,
                     params: MemberParams) -> tuple[np.ndarray, int] | None:
    """:func:`inner_outline`'s cut across the member: the mask's part between the member's
    outlines found inside it, and how far it reaches past them; None where it finds none."""
    ys, xs = np.nonzero(mask)
    found = _band_axes(xs, ys)
    if found is not None:
        return _cut_across(reference, mask, xs, ys, *found, params, both=False)
    if len(xs) < 3:
        return None
    # No band: a box drawn round a stretch of a member that crosses it. Across either image axis,
    # where both of the member's outlines are found inside it (a lone step could be any edge).
    centre = np.array([xs.mean(), ys.mean()])
    for normal, along in ((np.array([1.0, 0.0]), np.array([0.0, 1.0])), (np.array([0.0, 1.0]), np.array([1.0, 0.0]))):
        cut = _cut_across(reference, mask, xs, ys, centre, normal, along, params, both=True)
        if cut is not None:
            return cut
    return None


def _cut_across(reference: np.ndarray, mask: np.ndarray, xs: np.ndarray, ys: np.ndarray, centre: np.ndarray,
                normal: np.ndarray, along: np.ndarray, params: MemberParams, *,
                both: bool) -> tuple[np.ndarray, int] | None:
    """:func:`inner_outline` across ``normal`` (the mask's pixels ``xs, ys`` about ``centre``);
    ``both``: only where the member ends inside the mask on both sides."""
    s, t = _coordinate(xs, ys, centre, normal), _coordinate(xs, ys, centre, along)
    bins = np.rint(s - s.min()).astype(np.int64)
    n = int(bins.max()) + 1
    if n < 2 * RIM_MIN_PX + 2 * RIM_SPAN_PX + 3:
        return None
    length = float(t.max() - t.min()) + 1.0
    counts = np.bincount(bins, minlength=n)
    grey = reference[ys, xs].astype(np.float64)
    means = np.bincount(bins, weights=grey, minlength=n) / np.maximum(counts, 1)
    middle = means[n // 4:n - n // 4]
    level = float(np.median(middle))
    noise = MAD_TO_SIGMA * float(np.median(np.abs(middle - level)))
    tolerance = max(params.like_k * noise, params.like_floor)
    part = np.minimum(((t - t.min()) / length * STEP_PARTS).astype(np.int64), STEP_PARTS - 1)
    # Each part's level and likeness tolerance, from its own middle half: a textured member's
    # greys wander across it from part to part (a step must stand out of that in each).
    cells = bins + n * part
    sums = np.bincount(cells, weights=grey, minlength=n * STEP_PARTS).reshape(STEP_PARTS, n)
    part_means = sums / np.maximum(np.bincount(cells, minlength=n * STEP_PARTS).reshape(STEP_PARTS, n), 1)
    part_middle = part_means[:, n // 4:n - n // 4]
    part_level = np.median(part_middle, axis=1)
    part_noise = MAD_TO_SIGMA * np.median(np.abs(part_middle - part_level[:, None]), axis=1)
    part_tolerance = np.maximum(params.like_k * part_noise, params.like_floor)
    ends = [0, n - 1]  # the member's first and last bin across the mask
    past = 0  # px of the mask beyond the member's outline (the wider side)
    for index, side in ((1, 1), (0, -1)):
        walk = range(n // 2, n) if side > 0 else range(n // 2, -1, -1)
        first = next((b for b in walk if abs(means[b] - level) > tolerance), None)
        if first is None or np.any(counts[list(walk)] < 0.5 * length):
            continue  # no step, or a ragged side (not a band's edge)
        rim = np.arange(first, n if side > 0 else -1, side)
        if len(rim) < RIM_MIN_PX + 1:
            continue
        off = means[rim] - level
        change = float(np.median(off[min(RIM_SPAN_PX, len(rim) - 1):])) if len(rim) > RIM_SPAN_PX else float(off[-1])
        sign = np.sign(change)
        if abs(change) < RIM_CONTRAST * tolerance or np.any(sign * off <= tolerance):
            continue
        before = first - side
        after = rim[min(RIM_SPAN_PX - 1, len(rim) - 1)]
        if abs(means[after] - means[before]) < RIM_STEP_SHARE * abs(change):
            continue  # a ramp, not an outline
        beyond = side * (bins - first) >= 0
        seen = sum(sign * (grey[beyond & (part == k)].mean() - part_level[k]) > part_tolerance[k]
                   for k in range(STEP_PARTS) if (beyond & (part == k)).any())
        if seen < STEP_PARTS - 1:
            continue  # (one part may miss it: a background that looks like the member there)
        ends[index] = first - 2 * side
        past = max(past, len(rim))
    if not past or ends[1] - ends[0] < 2 or (both and (ends[0] == 0 or ends[1] == n - 1)):
        return None
    return _keep(mask.shape, ys, xs, (bins >= ends[0]) & (bins <= ends[1])), past


def _cut_ends(reference: np.ndarray, core: np.ndarray, params: MemberParams) -> tuple[np.ndarray, int] | None:
    """The part of a band ``core`` (the member's part of a mask, see :func:`inner_outline`)
    before the member's ends inside it, and how far it reaches past them (px, the longer side);
    None where the member runs through the band's ends, or where less than half the band would
    be left.

    Along the band, its pixels are taken 1 px at a time from the middle outwards on each side.
    A pixel looks like the member as in :func:`_grow` (its grey and its one-sided gradient
    against the middle half's); only the band's lines along it that look like the member over
    its middle half count (a strip of the background beside the member, left where the cut
    across found no outline, does not). The member ends after the last run of END_SPAN_PX bins,
    from the middle outwards, whose shares of member-like pixels reach END_SHARE of the middle
    half's (a mark, a bolt or a weld before the end comes back to it), where (see
    :func:`_falls_at`) one of the END_SPAN_PX bins before held at least END_BEFORE_SHARE of it (a
    blurred or a coded edge), each half of the band's width falls there too (a member that
    leaves the band sideways falls in one half first; not asked of a band of fewer than 4
    lines), at least RIM_MIN_PX + 1 bins lie beyond, and the bins' mean grey steps there
    (:func:`_grey_steps`: at least RIM_CONTRAST likeness tolerances of the middle half's bins'
    means) or the pixels beyond are rougher than the member's (:func:`_rougher`): a slow change
    of the light along the member is neither. An end slanting across the band is cut where half
    of it has gone (an end 10 rows aslant across a 32 px band keeps a wedge of the background up
    to 3 rows deep; 11 rows or more, the halves refuse it). The step's first pixel and the one
    before are left out. The member's level is the middle half's: a mask reaching past the end
    by more than about 40 % of its length is not cut.

    A faint bar read through a mask 6 px past its tip, on a still wall with texture, read 0.30
    px RMSE, slope 0.87 (12 px past: 0.39 px, slope 0.76); the mask ending at the tip, 0.08
    px: the region's texture fit took the still wall in."""
    ys, xs = np.nonzero(core)
    found = _band_axes(xs, ys)
    if found is None:
        return None
    centre, normal, along = found
    s, t = _coordinate(xs, ys, centre, normal), _coordinate(xs, ys, centre, along)
    bins = np.rint(t - t.min()).astype(np.int64)
    n = int(bins.max()) + 1
    if n < 2 * RIM_MIN_PX + 2 * END_SPAN_PX + 3:
        return None
    y0, x0 = max(int(ys.min()) - 1, 0), max(int(xs.min()) - 1, 0)
    box = reference[y0:int(ys.max()) + 2, x0:int(xs.max()) + 2].astype(np.float64)
    grey = box[ys - y0, xs - x0]
    middle = (bins >= n // 4) & (bins < n - n // 4)
    grey_like, smooth = _member_like(grey, _one_sided_gradient(box)[ys - y0, xs - x0], middle, params)
    like = grey_like & smooth
    lines = np.rint(s - s.min()).astype(np.int64)
    on_member = _share(lines, like, middle)[lines] >= END_BEFORE_SHARE
    if np.count_nonzero(on_member) < 0.5 * len(bins):
        return None
    half = s > np.median(s[on_member])
    halves = [on_member & ~half, on_member & half] if len(np.unique(lines[on_member])) >= 4 else []
    shares = [_share(bins, like, sel, n) for sel in [on_member] + halves]
    means = _share(bins, grey, on_member, n)
    # The member's level and the likeness tolerance of a bin's mean grey along it, from the
    # middle half's bins (a textured member's pixels spread far more than its bins' means).
    middle_means = means[n // 4:n - n // 4]
    middle_means = middle_means[np.isfinite(middle_means)]
    level = float(np.median(middle_means))
    tolerance = max(params.like_k * MAD_TO_SIGMA * float(np.median(np.abs(middle_means - level))), params.like_floor)
    ends = [0, n - 1]
    past = 0
    for index, side in ((1, 1), (0, -1)):
        first = _end_step(shares[0], n, side)
        if first is None or not all(_falls_at(share, first, side) for share in shares[1:]):
            continue
        beyond = on_member & (side * (bins - first) >= 0)
        if not (_grey_steps(means, first, side, level, tolerance) or _rougher(smooth, beyond, middle & on_member)):
            continue  # a slow change of the light, no end
        ends[index] = first - 2 * side
        past = max(past, (n - first) if side > 0 else first + 1)
    if not past or ends[1] - ends[0] < n // 2:
        return None
    return _keep(core.shape, ys, xs, (bins >= ends[0]) & (bins <= ends[1])), past


def _share(bins: np.ndarray, values: np.ndarray, sel: np.ndarray, n: int | None = None) -> np.ndarray:
    """The mean of ``values`` (a share where they are bools) over the pixels ``sel`` of each of
    the ``bins`` (``n`` of them; NaN where a bin holds none of them)."""
    n = int(bins.max()) + 1 if n is None else n
    counts = np.bincount(bins[sel], minlength=n)
    sums = np.bincount(bins[sel], weights=values[sel].astype(np.float64), minlength=n)
    return np.divide(sums, counts, out=np.full(n, np.nan), where=counts > 0)


def _middle_share(share: np.ndarray) -> float:
    """The median of the middle half's bins of ``share`` that hold pixels (NaN where none does)."""
    middle = share[len(share) // 4:len(share) - len(share) // 4]
    middle = middle[np.isfinite(middle)]
    return float(np.median(middle)) if middle.size else float("nan")


def _rougher(smooth: np.ndarray, beyond: np.ndarray, member: np.ndarray) -> bool:
    """Whether the pixels ``beyond`` an end are rougher than the ``member``'s: the share of them
    passing the gradient test (``smooth``) is below END_SHARE of the member's share."""
    return bool(np.mean(smooth[beyond]) < END_SHARE * np.mean(smooth[member]))


def _end_step(share: np.ndarray, n: int, side: int) -> int | None:
    """:func:`_cut_ends`'s end on one ``side`` of the band (``share``: each bin's share of
    member-like pixels): the bin after the last run of END_SPAN_PX bins, from the middle
    outwards, whose shares reach END_SHARE of the middle half's, where the share falls
    (:func:`_falls_at`) and at least RIM_MIN_PX + 1 bins lie beyond; None where there is none."""
    walk = np.arange(n // 2, n) if side > 0 else np.arange(n // 2, -1, -1)
    member = _middle_share(share)
    liked = share[walk] >= END_SHARE * member
    # Only runs of END_SPAN_PX such bins are the member's (on a narrow band a few of the
    # background's pixels that happen to look like the member fill a bin now and then).
    runs = np.nonzero(np.convolve(liked, np.ones(END_SPAN_PX), "valid") >= END_SPAN_PX)[0]
    if not runs.size:
        return None
    last = int(runs[-1]) + END_SPAN_PX - 1
    if len(walk) - last - 1 < RIM_MIN_PX + 1:
        return None
    first = int(walk[last + 1])
    return first if _falls_at(share, first, side) else None


def _falls_at(share: np.ndarray, first: int, side: int) -> bool:
    """Whether the member-like ``share`` of the bins falls at bin ``first`` going ``side``
    (+1, -1): one of the END_SPAN_PX bins before held at least END_BEFORE_SHARE of the middle
    half's share, and the bins from ``first`` on hold on average less than END_SHARE of it."""
    n = len(share)
    member = _middle_share(share)
    before = share[[b for b in first - side * np.arange(1, END_SPAN_PX + 1) if 0 <= b < n]]
    after = share[first::side] if side > 0 else share[first::-1]
    before, after = before[np.isfinite(before)], after[np.isfinite(after)]
    return bool(np.isfinite(member) and member > 0 and before.size and after.size
                and before.max() >= END_BEFORE_SHARE * member and after.mean() < END_SHARE * member)


def _grey_steps(means: np.ndarray, first: int, side: int, level: float, tolerance: float) -> bool:
    """Whether the band's mean grey (``means``, per bin) steps at bin ``first`` going ``side``:
    beyond END_SPAN_PX it lies at least RIM_CONTRAST ``tolerance`` off the member's ``level``,
    and RIM_STEP_SHARE of that change happens between END_SPAN_PX before ``first`` and
    END_SPAN_PX - 1 after (a shading's ramp, or a spotlight's falloff, changes the grey slowly)."""
    n = len(means)
    rim = np.arange(first, n) if side > 0 else np.arange(first, -1, -1)
    far = means[rim[min(END_SPAN_PX, len(rim) - 1):]]
    far = far[np.isfinite(far)]
    if not far.size:  # (no pixel of the member's lines there: the rim's nearer bins, or none)
        far = means[rim][np.isfinite(means[rim])]
        if not far.size:
            return False
    change = float(np.median(far)) - level
    before = means[int(np.clip(first - side * END_SPAN_PX, 0, n - 1))]
    after = means[rim[min(END_SPAN_PX - 1, len(rim) - 1)]]
    return bool(abs(change) >= RIM_CONTRAST * tolerance
                and abs(after - before) >= RIM_STEP_SHARE * abs(change))


def _member_like(grey: np.ndarray, gradient: np.ndarray, sample: np.ndarray,
                 params: MemberParams) -> tuple[np.ndarray, np.ndarray]:
    """Which pixels (``grey``, their ``gradient``: :func:`_one_sided_gradient`) look like the
    member's pixels ``sample`` (an index of them): their grey within ``like_k`` robust standard
    deviations of the sample's (at least ``like_floor``), and their gradient below ``like_k`` times
    the sample's typical one (at least 0.5 grey levels); the two tests apart."""
    values = grey[sample]
    centre = float(np.median(values))
    spread = MAD_TO_SIGMA * float(np.median(np.abs(values - centre)))
    typical = float(np.median(gradient[sample]))
    return (np.abs(grey - centre) <= max(params.like_k * spread, params.like_floor),
            gradient <= params.like_k * max(typical, 0.5))


def _keep(shape: tuple[int, int], ys: np.ndarray, xs: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """A mask of ``shape`` holding the pixels ``ys, xs`` where ``keep``."""
    cut = np.zeros(shape, bool)
    cut[ys[keep], xs[keep]] = True
    return cut


def _first_step(out: np.ndarray, grey: np.ndarray, level: float, tolerance: float, grow_px: int,
                length: float) -> int | None:
    """The first bin (``out``: 1 .. grow_px px outwards) whose mean ``grey`` leaves ``level`` by
    more than ``tolerance`` and stays off it for STEP_STAY_PX bins (a band inside the member, a
    weld or a stiffener's shadow, comes back to it); None where none does, or where a bin holds
    fewer than half of ``length`` pixels first (the frame's border)."""
    counts = np.bincount(out, minlength=grow_px + 1)
    means = np.bincount(out, weights=grey, minlength=grow_px + 1) / np.maximum(counts, 1)
    for b in range(1, grow_px + 1):
        if counts[b] < 0.5 * length:
            return None
        if abs(means[b] - level) > tolerance:
            stay = range(b, min(b + STEP_STAY_PX, grow_px + 1))
            if all(counts[k] >= 0.5 * length and abs(means[k] - level) > tolerance for k in stay):
                return b
            return None
    return None


@dataclass(frozen=True)
class _Predictor:
    """Best linear predictors of a background pixel from :data:`N_PREDICT` visible ones beyond it."""

    coef: np.ndarray  # (MAX_DISTANCE + 1, N_PREDICT): row d predicts from pixels d, d+1, ... away
    mean: float
    error: np.ndarray  # (MAX_DISTANCE + 1,) prediction error variance (row 0 unused)


def _predictor(reference: np.ndarray, background: np.ndarray, ridge: float) -> _Predictor:
    """Predictors from the autocovariance of the background pixels along rows (of
    ``reference`` as given; transpose it for columns)."""
    values = reference[background]
    mean = float(values.mean()) if values.size else float(reference.mean())
    n_lags = MAX_DISTANCE + N_PREDICT
    cov = np.zeros(n_lags)
    width = reference.shape[1]
    for lag in range(n_lags):
        both = background[:, :width - lag] & background[:, lag:] if lag < width else np.zeros((1, 1), bool)
        if both.sum() < 50:
            cov[lag] = cov[lag - 1] * 0.5 if lag else 1.0
            continue
        a = reference[:, :width - lag][both] - mean
        b = reference[:, lag:][both] - mean
        cov[lag] = float(np.mean(a * b))
    var = max(cov[0], 1e-6)
    K = np.array([[cov[abs(i - j)] for j in range(N_PREDICT)] for i in range(N_PREDICT)])
    K += max(ridge, 1e-3 * var) * np.eye(N_PREDICT)
    coef = np.zeros((MAX_DISTANCE + 1, N_PREDICT))
    error = np.full(MAX_DISTANCE + 1, var)
    for d in range(1, MAX_DISTANCE + 1):
        k = cov[d:d + N_PREDICT]
        coef[d] = np.linalg.solve(K, k)
        error[d] = min(max(var - float(coef[d] @ k), 0.02 * var), var)
    return _Predictor(coef, mean, error)


_SQRT_HALF = np.sqrt(0.5)
_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


@njit(cache=True, nogil=True)
def _coverage(x: float, blur: float) -> tuple[float, float]:
    """Member coverage ``Phi`` of a pixel whose centre lies ``x`` px inside the outline
    (positive: on the member's side), and ``dPhi/dx``: the pixel's area integral of a step
    blurred by a Gaussian of ``blur`` px."""
    if blur < 0.05:
        return min(max(x + 0.5, 0.0), 1.0), 1.0 if -0.5 < x < 0.5 else 0.0
    hi, lo = (x + 0.5) / blur, (x - 0.5) / blur
    nhi, nlo = 0.5 * math.erfc(-hi * _SQRT_HALF), 0.5 * math.erfc(-lo * _SQRT_HALF)
    phi_hi = hi * nhi + _INV_SQRT_2PI * math.exp(-0.5 * hi * hi)
    phi_lo = lo * nlo + _INV_SQRT_2PI * math.exp(-0.5 * lo * lo)
    return blur * (phi_hi - phi_lo), nhi - nlo


@njit(cache=True, nogil=True)
def _boundary(b: float) -> tuple[float, float]:
    """``(N(b), b N(b) + n(b))`` of a pixel boundary ``b`` blurs inside the outline: the
    standard normal's distribution and its integral, which :func:`_coverage` differences
    between a pixel's two boundaries (neighbouring pixels share one)."""
    nb = 0.5 * math.erfc(-b * _SQRT_HALF)
    return nb, b * nb + _INV_SQRT_2PI * math.exp(-0.5 * b * b)


@njit(cache=True, nogil=True)
def _same_pixels(before: float, after: float, reach: float, sharp: bool) -> bool:
    """Whether the outline fit at ``after`` uses the pixels it used at ``before``: the same
    member and background pixels, and on a sharp outline the same pixel in transition (a
    converged step that crosses a pixel's boundary is not a fixed point)."""
    for b in (before, after):
        if b != b:
            return False
    same = (int(np.floor(before - 0.5 - reach)) == int(np.floor(after - 0.5 - reach))
            and int(np.ceil(before + 0.5 + reach)) == int(np.ceil(after + 0.5 + reach)))
    if sharp:
        same = same and int(np.floor(before + 0.5)) == int(np.floor(after + 0.5))
    return same


@njit(cache=True, nogil=True)
def _fine_steps(values, e_in, ok_in, vertical, row_coef, col_coef, row_error, col_error, mean,
                blur, member_var):
    """Gauss-Newton steps of :meth:`MemberEdges._fine`, profile by profile (see there): the
    outline ``e`` (strip coordinate) and the member's grey ``m`` of each profile.

    Returns ``(e, var_e, misfit, contrast, ok)``."""
    n, length = values.shape
    last = length - 1
    reach = 2.5 * blur
    n_member = 2
    width = int(np.ceil(2 * reach)) + 2 + n_member  # member pixels, transition, none beyond
    e_out = e_in.copy()
    var_out = np.full(n, np.nan)
    misfit_out = np.full(n, np.nan)
    contrast_out = np.zeros(n)
    ok_out = ok_in.copy()
    wall = np.empty(width)
    sharp = blur < 0.05
    for i in range(n):
        coef = col_coef if vertical[i] else row_coef
        error = col_error if vertical[i] else row_error
        mu = mean[i]
        e = e_in[i]
        start = int(np.floor(e - 0.5 - reach)) - (n_member - 1)
        m = values[i, min(max(start + n_member - 1, 0), last)]
        ok = ok_in[i]
        var_e = np.nan
        misfit = np.nan
        contrast = 0.0
        for _ in range(N_STEPS):
            start = int(np.floor(e - 0.5 - reach)) - (n_member - 1)  # first member pixel
            first_bg = int(np.ceil(e + 0.5 + reach))  # first pure background pixel
            ok = ok and start >= 0 and first_bg + N_PREDICT <= last
            start = min(max(start, 0), last)
            first_bg = min(max(first_bg, 0), last - N_PREDICT)
            h11 = h12 = h22 = g1 = g2 = rr = 0.0
            n_used = 0
            if sharp:
                n_hi = phi_hi = 0.0
            else:  # the first member pixel's inner boundary (later ones: the previous pixel's)
                n_hi, phi_hi = _boundary((e - start + 0.5) / blur)
            for k in range(width):
                j = start + k
                used = j < first_bg
                j = min(j, last)
                distance = min(max(first_bg - j, 1), MAX_DISTANCE)
                w = mu
                for t in range(N_PREDICT):
                    w += coef[distance, t] * (values[i, first_bg + t] - mu)
                wall[k] = w
                if not used:
                    continue
                if sharp:
                    phi, dphi = _coverage(e - j, blur)
                else:  # _coverage(e - j, blur), each boundary's functions computed once
                    n_lo, phi_lo = _boundary((e - j - 0.5) / blur)
                    phi, dphi = blur * (phi_hi - phi_lo), n_hi - n_lo
                    n_hi, phi_hi = n_lo, phi_lo
                r = values[i, j] - (w + (m - w) * phi)
                wgt = 1.0 / (member_var + (1.0 - phi) ** 2 * error[distance])
                je = (m - w) * dphi
                h11 += wgt * je * je
                h12 += wgt * je * phi
                h22 += wgt * phi * phi
                g1 += wgt * je * r
                g2 += wgt * phi * r
                rr += wgt * r * r
                n_used += 1
            det = h11 * h22 - h12 * h12
            good = det > 1e-12 * max(h11 * h22, 1e-30)
            member = m
            before = e
            de = dm = 0.0
            if good:
                de = min(max((h22 * g1 - h12 * g2) / det, -0.5), 0.5)
                dm = (h11 * g2 - h12 * g1) / det
                e += de
                m += dm
                var_e = h22 / det
            else:
                var_e = np.nan
            misfit = rr / max(n_used, 1)
            near = min(max(int(np.floor(e + 0.5)), 0), last)
            contrast = member - wall[min(max(near - start, 0), width - 1)]
            ok = ok and good
            if (good and abs(de) < CONVERGED_PX and abs(dm) < CONVERGED_PX * max(abs(m), 1.0)
                    and _same_pixels(before, e, reach, sharp) and _same_pixels(e, e + de, reach, sharp)):
                break  # converged: the steps left would repeat this one (on these pixels)
        e_out[i] = e
        var_out[i] = var_e
        misfit_out[i] = misfit
        contrast_out[i] = contrast
        ok_out[i] = ok
    return e_out, var_out, misfit_out, contrast_out, ok_out


@njit(cache=True, nogil=True)
def _gather_strips(image, centre, lines, sides, vertical):
    """:meth:`MemberEdges._strips`: each profile's ``2 HALF + 1`` pixels along its line from
    ``centre - HALF`` (member side) outwards, as float64, clamped to the image, and whether
    all of them lie inside it."""
    n = centre.shape[0]
    height, width = image.shape
    values = np.empty((n, 2 * HALF + 1))
    inside = np.ones(n, np.bool_)
    for i in range(n):
        vert = vertical[i]
        line = lines[i]
        for k in range(2 * HALF + 1):
            along = centre[i] + sides[i] * (k - HALF)
            r, c = (along, line) if vert else (line, along)
            if r < 0 or r >= height or c < 0 or c >= width:
                inside[i] = False
            values[i, k] = np.float64(image[min(max(r, 0), height - 1), min(max(c, 0), width - 1)])
    return values, inside


@njit(cache=True, nogil=True)
def _lerp_line(image, line, vertical, pos, length):
    """``image`` along one profile's line at position ``pos`` (linear interpolation, clamped
    to the line's ``length`` as :meth:`MemberEdges._shift` samples it), as float64."""
    pos = min(max(pos, 0.0), length - 1.001)
    lo = int(np.floor(pos))
    frac = pos - lo
    hi = min(lo + 1, length - 1)
    if vertical:
        a, b = image[lo, line], image[hi, line]
    else:
        a, b = image[line, lo], image[line, hi]
    return (1.0 - frac) * np.float64(a) + frac * np.float64(b)


@njit(cache=True, nogil=True)
def _shift_steps(image, reference, along, d_in, ok_in, lines, vertical, scale, member_var, share):
    """Gauss-Newton steps of :meth:`MemberEdges._shift`, profile by profile (see there): the
    displacement ``d`` of each profile of the reference image ``reference`` (pixels ``along``
    its line) that matches the frame ``image`` best, the reference sampled at
    ``along - share d`` and the frame at ``along + (1 - share) d`` (``share`` 0: the reference's
    own pixels; 0.5: half of ``d`` each way).

    Linear interpolation smooths a profile by an amount that depends on the sampling's fraction
    of a pixel, least at whole pixels: a frame sampled alone against the reference's own pixels
    matches best nearer a whole-pixel displacement than the true one (the tests' lossless bar
    moved 0.1-0.3 px over a uniform wall read 0.85-0.88 of it; 0.91-1.02 so). Sampled half each
    way, the two fractions are f and 1 - f, smoothed alike, and the pull cancels (used on lossless
    frames, see SHIFT_BEYOND).

    Returns ``(d, var, misfit, ok)``."""
    n, width = along.shape
    height_img, width_img = image.shape
    d_out = d_in.copy()
    var_out = np.full(n, np.nan)
    misfit_out = np.full(n, np.nan)
    ok_out = ok_in.copy()
    for i in range(n):
        line = lines[i]
        vert = vertical[i]
        length = height_img if vert else width_img
        d = d_in[i]
        ok = ok_in[i]
        var = np.nan
        misfit = np.nan
        for _ in range(N_STEPS):
            h = 0.0
            g = 0.0
            rr = 0.0
            for k in range(width):
                at_frame = along[i, k] + (1.0 - share) * d
                at_reference = along[i, k] - share * d
                value = _lerp_line(image, line, vert, at_frame, length) / scale
                r = value - _lerp_line(reference, line, vert, at_reference, length)
                # d(r)/d(d): the frame's slope and the reference's, each by its share (central
                # differences).
                slope = ((1.0 - share) * ((_lerp_line(image, line, vert, at_frame + 0.5, length)
                                           - _lerp_line(image, line, vert, at_frame - 0.5, length)) / scale)
                         + share * (_lerp_line(reference, line, vert, at_reference + 0.5, length)
                                    - _lerp_line(reference, line, vert, at_reference - 0.5, length)))
                h += slope * slope
                g += slope * r
                rr += r * r
            good = h > 1e-9
            step = -g / h if good else 0.0
            d += min(max(step, -0.5), 0.5)
            if d != d:  # a NaN displacement would index far outside the image (no bounds check)
                ok = False
                break
            resid = rr / width
            var = (resid + member_var) / h if good else np.nan
            misfit = resid
            ok = ok and good
        d_out[i] = d
        var_out[i] = var
        misfit_out[i] = misfit
        ok_out[i] = ok
    return d_out, var_out, misfit_out, ok_out


@njit(cache=True, nogil=True)
def _irls(A, d, w0, prior, lam, tukey_c, min_scale):
    """Tukey-biweight iteratively reweighted least squares of ``A theta = d`` (weights ``w0``)
    with a ridge ``lam`` towards ``prior``, 8 steps. Returns ``(theta, weights, z, scale)``:
    ``z`` the standardised residuals of the last step, ``scale`` their robust spread (never
    below ``min_scale``: exact data must not make every profile an outlier)."""
    n, k = A.shape
    weights = w0.copy()
    theta = prior.copy()
    z = np.zeros(n)
    scale = 1.0
    root = np.sqrt(w0)
    for _ in range(8):
        H = lam * np.eye(k)
        b = lam * prior
        for i in range(n):
            wi = weights[i]
            if wi == 0.0:
                continue
            for p in range(k):
                api = A[i, p] * wi
                b[p] += api * d[i]
                for q in range(k):
                    H[p, q] += api * A[i, q]
        theta = np.linalg.solve(H, b)
        z = (d - A @ theta) * root
        scale = max(MAD_TO_SIGMA * np.median(np.abs(z - np.median(z))), min_scale)
        for i in range(n):
            u = z[i] / (tukey_c * scale)
            weights[i] = w0[i] * (1.0 - u * u) ** 2 if abs(u) < 1.0 else 0.0
    return theta, weights, z, scale


class _Field:
    """The member's motion field at a set of points, as beam kinematics.

    Across the member (along the mask's minor axis) the displacement is
    ``a0 + a1 xi + a2 xi^2``: translation, rotation, bending; along it
    ``b0 + b1 xi + b2 eta``: translation, axial stretch, rotation (``xi`` along the
    member, ``eta`` across it, both scaled to about [-1, 1]). A cross-section keeps its
    width; any shape's rigid motion is included.
    """

    def __init__(self, x: np.ndarray, y: np.ndarray, centre: np.ndarray, axes: np.ndarray,
                 half: np.ndarray) -> None:
        d = np.stack([np.asarray(x, float) - centre[0], np.asarray(y, float) - centre[1]], axis=-1)
        xi = (d @ axes[:, 0]) / half[0]
        eta = (d @ axes[:, 1]) / half[1]
        one = np.ones_like(xi)
        self.across = np.stack([one, xi, xi * xi], axis=-1)
        self.along = np.stack([one, xi, eta], axis=-1)
        self.n_dir = axes[:, 1]  # unit vector across (x, y)
        self.t_dir = axes[:, 0]  # unit vector along

    def design(self, cx: np.ndarray, cy: np.ndarray) -> np.ndarray:
        """Rows mapping the parameters to ``cx u + cy v`` at each point."""
        ca = cx * self.n_dir[0] + cy * self.n_dir[1]
        cl = cx * self.t_dir[0] + cy * self.t_dir[1]
        return np.hstack([self.across * np.asarray(ca)[..., None], self.along * np.asarray(cl)[..., None]])

    def uv(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(u, v)`` at the points."""
        across = self.across @ theta[:N_ACROSS]
        along = self.along @ theta[N_ACROSS:]
        return (across * self.n_dir[0] + along * self.t_dir[0], across * self.n_dir[1] + along * self.t_dir[1])

    def mean_gradient(self) -> tuple[np.ndarray, np.ndarray]:
        """Gradients of the points' mean u and mean v with respect to the parameters."""
        across, along = self.across.mean(axis=0), self.along.mean(axis=0)
        return (np.concatenate([across * self.n_dir[0], along * self.t_dir[0]]),
                np.concatenate([across * self.n_dir[1], along * self.t_dir[1]]))


@dataclass
class _Outline:
    """Outline positions along the profiles' lines in one frame."""

    edge: np.ndarray  # (N,) image coordinate along the line, NaN where not found
    var: np.ndarray  # (N,) its variance, px^2
    contrast: np.ndarray  # (N,) member minus background grey at the outline
    misfit: np.ndarray  # (N,) weighted mean squared residual of the outline model


@dataclass
class _Solution:
    """One robust fit of the motion field (see :meth:`MemberEdges._solve`)."""

    theta: np.ndarray  # (N_PARAMS,)
    design: np.ndarray  # (U, N_PARAMS) rows of the usable profiles
    weights: np.ndarray  # (U,) final robust weights
    lam: float  # the prior's weight
    used: int  # profiles with a non-zero weight
    scale: float  # robust spread of the standardised residuals
    spread: float  # px: how well the outlines agree
    z: np.ndarray  # (U,) standardised residuals
    usable: np.ndarray  # (N,) bool: the profiles the rows are


class MemberEdges:
    """Edge profiles of the member selected by a POI mask in a reference frame.

    Build with :meth:`from_reference`; :meth:`fit` measures a frame.
    """

    def __init__(self) -> None:
        self.params = MemberParams()
        self.lossless = False  # the frames are (see from_reference)
        self.codec_crf: float | None = None  # a lossy stream's quality (see from_reference)
        self.n_profiles = 0
        self.models: tuple[int, ...] = tuple(range(len(BLURS) + 1))  # see _plausible_models
        self.unchosen: frozenset[int] = frozenset()  # see _unchosen_models
        self.one_outline = False  # the profiles on one side, one scan direction (see ONE_OUTLINE_WHOLE)
        self.uniform_background = False  # behind the outline (see UNIFORM_BACKGROUND)

    @classmethod
    def from_reference(cls, reference: np.ndarray, mask: np.ndarray, *,
                       params: MemberParams | None = None, lossless: bool = False,
                       codec_crf: float | None = None) -> MemberEdges:
        """Analyse ``reference`` (grey, any dtype) and the bool POI ``mask`` of the same shape;
        ``lossless``: the frames are (see :meth:`_shift`); ``codec_crf``: a lossy stream's quality
        (see SHARP_CODEC_CRF)."""
        if reference.ndim != 2 or mask.shape != reference.shape:
            raise ValueError(f"reference {reference.shape} and mask {mask.shape} must be 2-D of one shape")
        self = cls()
        self.params = params or MemberParams()
        self.lossless = bool(lossless)
        self.codec_crf = codec_crf
        ref = reference.astype(np.float32)
        mask = mask.astype(bool)
        if mask.sum() < 3:
            raise ValueError("the mask holds fewer than 3 pixels")
        self.shape = ref.shape
        self._ref_image = ref
        self.support, reach, further = _grow(ref, mask, self.params)
        # Variance of a member pixel about its neighbours (paint texture and noise).
        inner = cv2.erode(self.support.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        diffs = np.concatenate([(ref[:, 1:] - ref[:, :-1])[inner[:, 1:] & inner[:, :-1]],
                                (ref[1:, :] - ref[:-1, :])[inner[1:, :] & inner[:-1, :]]])
        self.member_var = max(float(np.median(diffs ** 2)) / 0.455 / 2.0 if diffs.size else 2.0, 0.5)
        ring = cv2.dilate(self.support.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        near = cv2.dilate(self.support.astype(np.uint8),
                          np.ones((4 * self.params.grow_px + 1,) * 2, np.uint8)) > 0
        background = near & ~ring
        self.predict = (_predictor(ref, background, self.params.ridge),
                        _predictor(np.ascontiguousarray(ref.T), np.ascontiguousarray(background.T),
                                   self.params.ridge))
        ys, xs = np.nonzero(mask)
        pts = np.stack([xs, ys], axis=1).astype(np.float64)
        self.centre = pts.mean(axis=0)
        evals, axes = np.linalg.eigh(np.cov(pts.T) if len(pts) > 2 else np.eye(2))
        order = np.argsort(evals)[::-1]
        self.axes = axes[:, order]
        self.half = np.maximum(2.0 * np.sqrt(np.maximum(evals[order], 0.0)), 1.0)
        self._profiles(ref, reach, further)  # (which may turn the axes: _orient_by_outline)
        self.poi_field = _Field(pts[:, 0], pts[:, 1], self.centre, self.axes, self.half)
        return self

    # -- reference analysis ------------------------------------------------------------------------

    def _orient_by_outline(self) -> None:
        """The member's long axis from its outline where the mask's shape says otherwise: the
        mask's longer side is taken as the member's length (its axes, see :meth:`build`), but a
        patch drawn wider than tall inside a column has its outlines (the column's edges, the
        usable profiles) on its short sides. Where the usable profiles' normals lie more than
        ORIENT_RATIO times as much along that axis as across it, the axes are swapped: the
        outlines then measure the motion across the member, and along it the dense flow and the
        paint do (before 2026-12-05 such a patch read its motion across the column from the
        dense flow: bench_window's 720p bar, frame 1 0.19 px of 0.40)."""
        if len(self.px) == 0:
            return
        norm = np.sqrt(1.0 + self.slope ** 2)
        normals = np.where(self.vertical[:, None], np.column_stack([-self.slope, np.ones_like(norm)]),
                           np.column_stack([np.ones_like(norm), -self.slope])) / norm[:, None]
        along, across = np.sum((normals @ self.axes) ** 2, axis=0)
        if along > ORIENT_RATIO * across:
            self.axes = self.axes[:, ::-1].copy()
            self.half = self.half[::-1].copy()

    def _beside_stopped(self, stopped: np.ndarray) -> np.ndarray:
        """Which profiles lie within OVERRUN_LINES lines of a ``stopped`` one on the same side of
        the support, scanned the same way: where the grow overran a member's outline here and
        there. Elsewhere the grow stopped at its limit along a whole side of the support (a
        member wider than the grow's reach, its far outline out of it), on no outline."""
        near = np.zeros(stopped.shape, bool)
        for vertical in (False, True):
            for side in (-1, 1):
                group = (self.vertical == vertical) & (self.side == side)
                lines = np.sort(self.line[group & stopped])
                if lines.size == 0:
                    continue
                at = np.clip(np.searchsorted(lines, self.line[group]), 1, lines.size) - 1
                gap = np.minimum(np.abs(self.line[group] - lines[at]),
                                 np.abs(self.line[group] - lines[np.minimum(at + 1, lines.size - 1)]))
                near[group] = gap <= OVERRUN_LINES
        return near

    def _profiles(self, ref: np.ndarray, reach: np.ndarray, further: np.ndarray) -> None:
        """The edge profiles across the support's boundary: those where the scene stopped the
        support (the pixel beyond it is within the grow's ``reach``: the member's outline, or
        the cut at a step of :func:`_beyond_steps`) or would stop it within the outline search's
        SEARCH px past the reach (``further``, the grow let go SEARCH + 1 px further, does not
        hold the pixel SEARCH + 1 px beyond), not where only grow_px stopped it, its pixels
        looking like the member's on past it; those are left out only where they are more
        than 1 - SCENE_STOPPED of the candidates (a member's outline that the grow overran here
        and there keeps them, as before). A texture that fills the view has no outline there:
        taken for one, its random steps of 6 grey levels (31 profiles) read a faint texture
        moving 0.3 px 0.186 px RMS, slope 0.41, where DIS read 0.016 px."""
        support = self.support
        smooth = cv2.GaussianBlur(support.astype(np.float32), (0, 0), 1.5)
        nx = cv2.Sobel(smooth, cv2.CV_32F, 1, 0, ksize=3)
        ny = cv2.Sobel(smooth, cv2.CV_32F, 0, 1, ksize=3)
        lines, pos, side, axis, slope = [], [], [], [], []
        for vertical in (False, True):
            sup = support.T if vertical else support
            gnx, gny = (ny.T, nx.T) if vertical else (nx, ny)
            inner = sup[:, :-1] & ~sup[:, 1:]  # member at x, outside at x + 1: outline to the right
            outer = ~sup[:, :-1] & sup[:, 1:]  # outside at x, member at x + 1: outline to the left
            for found, direction in ((inner, 1), (outer, -1)):
                ly, lx = np.nonzero(found)
                member_x = lx if direction == 1 else lx + 1
                # Steep enough for this scan direction (within 45 degrees of across it).
                along = np.abs(gnx[ly, member_x])
                across = np.abs(gny[ly, member_x])
                good = (along >= across) & (along > 1e-3)
                ly, member_x = ly[good], member_x[good]
                lines.append(ly)
                pos.append(member_x)
                side.append(np.full(len(ly), direction))
                axis.append(np.full(len(ly), int(vertical)))
                slope.append(-gny[ly, member_x] / gnx[ly, member_x])
        self.line = np.concatenate(lines).astype(np.intp)
        self.side = np.concatenate(side).astype(np.intp)  # +1: background at the higher index
        self.vertical = np.concatenate(axis).astype(bool)  # True: a column profile (measures y)
        self.slope = np.concatenate(slope).astype(np.float64)  # dX/dy (rows), dY/dx (columns)
        member_px = np.concatenate(pos).astype(np.intp)  # the support's last pixel along the line
        # Sign of the member-to-background step, from that pixel and the one two beyond it.
        height, width = ref.shape

        def at(offset: int) -> tuple[np.ndarray, np.ndarray]:
            """(row, column) of the pixel ``offset`` px beyond the support along each profile's
            line, towards the background (the frame's last where the frame ends before it)."""
            along = member_px + offset * self.side
            return (np.clip(np.where(self.vertical, along, self.line), 0, height - 1),
                    np.clip(np.where(self.vertical, self.line, along), 0, width - 1))

        self.polarity = np.where(ref[at(0)] >= ref[at(2)], 1.0, -1.0)
        guess = self._coarse(ref, member_px + 0.5 * self.side, None)
        # The outline in the reference under each blur model (see fit for the choice).
        outlines = [self._fine(ref, guess, None, blur) for blur in BLURS]
        sharp = outlines[0]
        # (A grow that runs on to the frame's edge met no outline either: see at.)
        stopped = reach[at(1)] | ~further[at(SEARCH + 1)]
        keep = np.isfinite(sharp.edge) & (np.abs(sharp.contrast) >= self.params.min_contrast)
        if keep.any() and np.mean(stopped[keep]) < SCENE_STOPPED:
            keep &= stopped  # (a member's outline keeps the few the grow overran: see SCENE_STOPPED)
        else:
            keep &= stopped | self._beside_stopped(stopped & keep)
        boundary = np.where(keep, sharp.edge, 0.0)
        self.px = np.where(self.vertical, self.line, boundary).astype(np.float64)
        self.py = np.where(self.vertical, boundary, self.line).astype(np.float64)
        for name in ("line", "side", "vertical", "slope", "polarity", "px", "py"):
            setattr(self, name, getattr(self, name)[keep])
        self._orient_by_outline()
        self.field = _Field(self.px, self.py, self.centre, self.axes, self.half)
        ones = np.ones(len(self.px))
        # Outline displacement along its line: u - s v (rows) or v - s u (columns).
        self.design = self.field.design(np.where(self.vertical, -self.slope, ones),
                                        np.where(self.vertical, ones, -self.slope))
        self.ref_by_blur = []
        for o in outlines:
            # A profile the model does not explain in the reference (a smooth mark on the
            # member, two outlines in one strip) is left out of that model's fits.
            misfit = o.misfit[keep]
            typical = float(np.nanmedian(misfit)) if np.isfinite(misfit).any() else np.inf
            good = np.isfinite(misfit) & (misfit <= MISFIT_RATIO * max(typical, 1.0))
            self.ref_by_blur.append(_Outline(np.where(good, o.edge[keep], np.nan), o.var[keep],
                                             o.contrast[keep], misfit))
        self.ref = self.ref_by_blur[0]
        self.n_profiles = int(keep.sum())
        self.models = self._plausible_models()
        self.unchosen = self._unchosen_models()
        groups = np.unique(self.side * 2 + self.vertical, return_counts=True)[1]
        self.one_outline = bool(groups.size) and groups.max() >= ONE_OUTLINE_SHARE * self.n_profiles
        self.uniform_background = self._background_uniform(ref)

    def _background_uniform(self, ref: np.ndarray) -> bool:
        """Whether what lies behind the reference's outlines is uniform (see UNIFORM_BACKGROUND):
        beyond the reach of their blur (three times that of the blur model that draws them best)."""
        edge = self.ref.edge
        located = np.isfinite(edge)
        if not located.any():
            return False
        values, _ = self._strips(ref, np.floor(np.where(located, edge, 0.0) + 0.5).astype(np.intp))
        misfits = self._reference_misfits()
        blur = BLURS[int(np.argmin([misfits[i] if i in self.models else np.inf for i in range(len(BLURS))]))]
        start = 2 + math.ceil(3.0 * blur)
        behind = values[located, HALF + start:HALF + min(max(SHIFT_HALF, start + 3), HALF) + 1]
        spread = float(np.nanmedian(np.nanstd(behind, axis=1)))
        return spread <= UNIFORM_BACKGROUND * float(np.nanmedian(np.abs(self.ref.contrast)))

    def _plausible_models(self) -> tuple[int, ...]:
        """The outline models the frames are measured under (indices of :data:`BLURS`, then the
        whole-profile match, ``len(BLURS)``): every blur model but those whose outlines misfit
        the reference (their median weighted mean squared residual, about 1 where a model explains
        a profile to its noise) IMPLAUSIBLE_MISFIT times as badly as the best one's, or the noise's.

        The outline's blur is the optics' and the codec's, the reference's as much as a frame's:
        a model that cannot draw the reference's outlines does not measure the frames' either.
        The sharp one on an outline blurred beyond it (a lens out of focus, 1.5 px) locks to the
        pixel grid: every profile of a straight outline shares that error, so its outlines agree
        best of all and it was kept, 0.3-0.5 px off (an I-beam's web so blurred, bench_scene_kinds'
        `ibeam`: 0.31 px RMS where DIS read 0.16; 0.030 without it); it misfit that reference 48
        times the noise, the 1 px model 0.7 times. The whole-profile match draws no model and
        always stays.

        Nor the sharp model where a blur model draws the reference's outlines to about their
        noise and the sharp one misfits them SHARP_BLURRED_MISFIT times as badly, on a stream whose
        codec keeps a step sharp (``codec_crf`` None or at most SHARP_CODEC_CRF): a lens's blur,
        short of IMPLAUSIBLE_MISFIT (the tests' bar blurred 1.5 px: 5-12 times, the 1 px model
        0.8-1.3)."""
        typical = self._reference_misfits()
        bound = IMPLAUSIBLE_MISFIT * max(min(typical), 1.0)
        plausible = [i for i, misfit in enumerate(typical) if misfit <= bound]
        sharp = BLURS.index(0.0)
        blurred = min((m for i, m in enumerate(typical) if i != sharp), default=np.inf)
        if ((self.codec_crf is None or self.codec_crf <= SHARP_CODEC_CRF) and blurred <= BLURRED_DRAWN_MISFIT
                and typical[sharp] > SHARP_BLURRED_MISFIT * max(blurred, 1.0) and sharp in plausible):
            plausible.remove(sharp)  # a lens's blur (see SHARP_BLURRED_MISFIT)
        return tuple(plausible) + (len(BLURS),)

    def best_reference_misfit(self) -> float:
        """How well the blur model that draws the reference's outlines best draws them (its
        median misfit, about 1 where it explains a profile to its noise; inf where none located
        any): well above 1 where the outline is no blurred step (a round column's limb)."""
        return min(self._reference_misfits())

    def _reference_misfits(self) -> list[float]:
        """Each blur model's median misfit of the reference's outlines (about 1 where it explains
        a profile to its noise; inf where it located none)."""
        return [float(np.nanmedian(o.misfit)) if np.isfinite(o.misfit).any() else np.inf for o in self.ref_by_blur]

    def _unchosen_models(self) -> frozenset[int]:
        """The blur models (indices of :data:`BLURS`) that measure the frames but are never kept:
        where the sharp model draws the reference's outlines to their noise, those misfitting
        them more than UNCHOSEN_BLUR_MISFIT times the noise (see there)."""
        typical = self._reference_misfits()
        sharp = BLURS.index(0.0)
        if sharp not in self.models or not typical[sharp] <= 1.0:
            return frozenset()
        return frozenset(i for i in self.models if i < len(BLURS) and i != sharp and typical[i] > UNCHOSEN_BLUR_MISFIT)

    # -- outline location --------------------------------------------------------------------------

    def _strip_pixels(self, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rows and columns ``(N, 2 HALF + 1)`` of each profile's strip along its line, ordered
        from the member outwards (index ``HALF`` at the pixel ``centre``); not clipped to the image."""
        offsets = np.arange(-HALF, HALF + 1)
        along = centre[:, None] + self.side[:, None] * offsets[None, :]
        line = np.broadcast_to(self.line[:, None], along.shape)
        return np.where(self.vertical[:, None], along, line), np.where(self.vertical[:, None], line, along)

    def _strips(self, image: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pixel values along each profile's line, ordered from the member outwards.

        Returns ``(values (N, 2 HALF + 1), inside)``; strip index ``HALF`` is the pixel
        ``centre`` (integer, along the line).
        """
        return _gather_strips(image, np.asarray(centre, np.intp), self.line, self.side, self.vertical)

    def _moved_strips(self, image: np.ndarray, centre: np.ndarray, motion: np.ndarray) -> np.ndarray:
        """:meth:`_strips` of ``image`` as it shows after moving by ``motion`` (u, v) px: each
        pixel sampled (bilinear) where that motion brought it from; NaN from outside it."""
        rows, cols = self._strip_pixels(centre)
        return sample(image, cols - motion[0], rows - motion[1]).astype(np.float64)

    def _centre(self, guess: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(finite, guess with NaN replaced, strip centre pixel)`` for outline guesses."""
        finite = np.isfinite(guess)
        g = np.where(finite, guess, 0.0)
        return finite, g, np.floor(g + 0.5).astype(np.intp)

    def _coarse(self, image: np.ndarray, guess: np.ndarray, gain: float | None) -> np.ndarray:
        """Outline positions to about a pixel: where the profile falls most steeply from
        member to background (with the outline's polarity) within :data:`SEARCH` px of the
        guess. A feature of the profile itself, for guesses that may be off by pixels."""
        finite, g, centre = self._centre(guess)
        values, _ = self._strips(image, centre)
        steps = np.stack([self.polarity * (values[:, t - 1] - values[:, t + 1])
                          for t in range(HALF - SEARCH, HALF + SEARCH + 1)], axis=1)
        t = HALF - SEARCH + np.argmax(steps, axis=1)
        # The steepest fall is at the outline: the boundary coordinate of pixel t's centre.
        return np.where(finite, centre + self.side * (t - HALF), np.nan).astype(np.float64)

    def _shift(self, image: np.ndarray, guess: np.ndarray, gain: float | None) -> _Outline:
        """Outline positions by matching each profile of the reference as a whole.

        The reference's pixels within :data:`SHIFT_HALF` of its outline are compared with the
        frame's along the same line, displaced by ``d`` (linear interpolation), and ``d`` is
        fitted by Gauss-Newton: exact when what is behind the member is uniform, whatever the
        outline's blur and the member's shading; a textured background, which does not move,
        biases it (the two-layer models are then the ones that agree). On lossless frames only
        :data:`SHIFT_BEYOND` px beyond the outline are taken and the two images are sampled half
        of ``d`` each way from the pixels midway between their outlines (see
        :func:`_shift_steps`).
        """
        ref_edge = self.ref.edge
        finite = np.isfinite(guess) & np.isfinite(ref_edge)
        d = np.where(finite, guess - ref_edge, 0.0)
        share = 0.5 if self.lossless else 0.0
        offsets = np.arange(-SHIFT_HALF, (SHIFT_BEYOND if self.lossless else SHIFT_HALF) + 1)
        # The window's pixels: about the point each image is sampled from (lossless, midway
        # between the reference's outline and the guessed one).
        base = np.floor(np.where(np.isfinite(ref_edge), ref_edge + share * d, 0.0) + 0.5).astype(np.intp)
        along = base[:, None] + self.side[:, None] * offsets[None, :]
        height, width = image.shape
        length = np.where(self.vertical, height, width)[:, None]
        ok = finite & np.all((along >= 1) & (along < length - 2), axis=1)
        along = np.clip(along, 0, length - 1)
        scale = 1.0 if gain is None else gain
        # The images are sampled in place (not copied whole: a 4K frame is 66 MB of float64).
        d, var, misfit, ok = _shift_steps(image, self._ref_image, along, d, ok, self.line, self.vertical,
                                          float(scale), float(self.member_var), share)
        edge = np.where(ok, ref_edge + d, np.nan)
        return _Outline(edge, var, self.ref.contrast.copy(), misfit)

    def _known(self, image: np.ndarray, guess: np.ndarray, gain: float | None,
               camera: np.ndarray | None = None) -> _Outline:
        """Outline positions, where the member has moved onto background the reference shows,
        from the outline's area over the background copied from the reference.

        The background is static: where every pixel within :data:`KNOWN_HALF` of the outline's
        guess lay beyond the reference's outline (by :data:`KNOWN_MARGIN`), the background
        hidden under them is the reference's pixel (times ``gain``), not a prediction. Each
        pixel's member coverage is then ``(I - w) / (m - w)`` (``m`` the member's grey from the
        pure member pixels before the window) and the outline lies the summed coverage beyond
        the window's start: exact whatever the outline's spread (lens, motion blur, a codec's
        smoothing) within the window, where one pixel's coverage locks to the pixel grid.
        Elsewhere NaN. The background just beyond the window must match the reference's (a
        robust test over all profiles): what moved in front of it is not background. Where the
        camera moved (``camera``: its image motion (u, v) px at the member, from a background
        the user marked), the reference's background is taken where the camera's motion brought
        it from (the wall 2 px off along the member: a median outline 0.9 px off otherwise).
        """
        n = len(self.line)
        scale = 1.0 if gain is None else gain
        finite, _, centre = self._centre(guess)
        finite &= np.isfinite(self.ref.edge)
        values, inside = self._strips(image, centre)
        if camera is None:
            ref_values, _ = self._strips(self._ref_image, centre)
        else:
            ref_values = self._moved_strips(self._ref_image, centre, camera)
            inside &= np.all(np.isfinite(ref_values), axis=1)
            ref_values = np.nan_to_num(ref_values)
        ref_values = ref_values * scale
        ref_e = HALF + self.side * (np.where(finite, self.ref.edge, 0.0) - centre)
        first = HALF - KNOWN_HALF
        last = HALF + KNOWN_HALF
        ok = finite & inside & (first - 0.5 >= ref_e + KNOWN_MARGIN)
        # The member's grey: the two pure member pixels before the window (as the outline fit's).
        m = 0.5 * (values[:, max(first - 1, 0)] + values[:, max(first - 2, 0)])
        wall = ref_values[:, first:last + 1]
        contrast = m[:, None] - wall
        ok &= np.all(self.polarity[:, None] * contrast >= self.params.min_contrast, axis=1)
        safe = np.where(np.abs(contrast) > 1e-6, contrast, 1e-6)
        coverage = (values[:, first:last + 1] - wall) / safe
        edge_strip = first - 0.5 + coverage.sum(axis=1)
        # Pixel noise in both frames, over each pixel's contrast.
        var = 2.0 * self.member_var * np.sum(1.0 / safe ** 2, axis=1)
        beyond = slice(last + 1, min(last + 1 + N_PREDICT, 2 * HALF + 1))
        moved = np.mean(np.abs(values[:, beyond] - ref_values[:, beyond]), axis=1)
        if ok.any():
            ok &= moved <= KNOWN_STATIC * max(float(np.median(moved[ok])), 1.0)
        edge = np.where(ok, centre + self.side * (edge_strip - HALF), np.nan)
        near = np.clip(np.floor(edge_strip + 0.5).astype(np.intp), first, last) - first
        return _Outline(edge, np.where(ok, var, np.nan), contrast[np.arange(n), near],
                        np.where(ok, 0.0, np.nan))

    def _fine(self, image: np.ndarray, guess: np.ndarray, gain: float | None, blur: float) -> _Outline:
        """Outline positions to a fraction of a pixel: a two-layer model of the profile fitted
        by Gauss-Newton.

        Pixel ``j`` of a profile (strip coordinate, member on the low side) sees
        ``w_j + (m - w_j) Phi(e - j)``: ``Phi`` the member's blurred area coverage (see
        :func:`_coverage`), ``m`` the member's grey (fitted, with the two pure member
        pixels inside the outline), ``w_j`` the background hidden under pixel ``j``,
        predicted from the first :data:`N_PREDICT` pure background pixels beyond the
        outline. The pixels the model uses are chosen from the outline estimate itself,
        so on a sharp outline the estimate does not stick to the guess (on a smeared one
        it may: see the module's notes); pixels where the model changes hands have
        coverage 0 or 1 and weigh nothing in it, so the estimate is continuous.
        """
        finite, g, centre = self._centre(guess)
        values, inside = self._strips(image, centre)
        rows, cols = self.predict
        mean = np.where(self.vertical, cols.mean, rows.mean) * (1.0 if gain is None else gain)
        # Strip coordinate of the outline (pixel j spans [j - 0.5, j + 0.5]).
        e = HALF + self.side * (g - centre)
        e, var_e, misfit, contrast, ok = _fine_steps(
            values, e.astype(np.float64), (finite & inside), self.vertical, rows.coef, cols.coef,
            rows.error, cols.error, mean.astype(np.float64), float(blur), float(self.member_var))
        ok &= np.isfinite(e) & (np.sign(contrast) == self.polarity)
        edge = np.where(ok, centre + self.side * (e - HALF), np.nan)
        return _Outline(edge, np.where(ok, var_e, np.nan), contrast, np.where(ok, misfit, np.nan))

    # -- per frame ---------------------------------------------------------------------------------

    def fit(self, current: np.ndarray, prior_uv: np.ndarray, *, gain: float | None = None,
            camera: np.ndarray | None = None, first: tuple[int, ...] | None = None,
            enough_spread: float = float("inf"), systematic: np.ndarray | None = None,
            skip: np.ndarray | None = None, reported_systematic: np.ndarray | None = None) -> MemberFit:
        """Fit the member's motion in ``current`` (same shape as the reference).

        ``prior_uv``: ``(n_profiles, 2)`` dense-flow displacement at each profile's outline,
        the starting guess and the weak prior. ``gain``: the frame's brightness relative to
        the reference (lighting changes), for the background predictor's mean. ``camera``: the
        camera's own image motion (u, v) px at the member where known (see :meth:`_known`).
        Raises ``ValueError`` naming the shapes if ``current`` is not the reference's shape or
        ``prior_uv`` not ``(n_profiles, 2)`` (the numba kernels do not bounds-check).

        Every plausible outline model (:data:`BLURS`, then the whole-profile match: index
        ``len(BLURS)``; those that draw the reference's outlines, see :meth:`_plausible_models`)
        measures the frame and the one whose outlines agree best is kept. With ``first`` only
        those of them measure it, and the rest only where the best of them has a
        spread above ``enough_spread`` px; where the rest are not needed, the models'
        disagreement is ``systematic`` (px, x and y: a chain key's, see :meth:`mean_sigma`).
        ``skip``: ``(n_profiles,)`` bool, profiles left out of the fits (a codec copied their
        pixels from the reference: see :func:`~flow.methods.deepflow.codecfloor.codec_copies`).
        """
        check_shape("current", current, self.shape)
        if first is not None and not set(first) <= set(range(len(BLURS) + 1)):
            raise ValueError(f"first={tuple(first)}: outline models are 0..{len(BLURS)} "
                             f"({len(BLURS)} blur models, then the whole-profile match)")
        if np.shape(prior_uv) != (self.n_profiles, 2):
            raise ValueError(f"prior_uv has shape {np.shape(prior_uv)} but the member has "
                             f"{self.n_profiles} edge profiles: prior_uv must have shape "
                             f"({self.n_profiles}, 2)")
        empty = MemberFit(False, np.zeros(N_PARAMS), np.full((N_PARAMS, N_PARAMS), np.nan), 0,
                          self.n_profiles, float("nan"))
        if self.n_profiles < self.params.min_profiles:
            return empty
        cur = current.astype(np.float32)
        pu, pv = prior_uv[:, 0].astype(np.float64), prior_uv[:, 1].astype(np.float64)
        # The dense flow's own field (least squares over the profiles): guess and weak prior.
        stacked = np.vstack([self.field.design(1.0, 0.0), self.field.design(0.0, 1.0)])
        prior, *_ = np.linalg.lstsq(stacked, np.concatenate([pu, pv]), rcond=None)
        # The dense flow's guess may be off by pixels (it under-reads, a jump outruns it):
        # the coarse step finds each outline near it, the fit of all profiles predicts every
        # outline to a few hundredths of a pixel, and the fine fit starts from there.
        start = self._coarse(cur, self.ref.edge + self._normal(pu, pv), gain)
        # The outline's blur is not known (lens focus, motion blur, a codec's smoothing and
        # ringing): each blur model measures the frame, and the one under which all the
        # outlines agree best on one motion is kept; the profiles matched whole are the last
        # model (for outlines over a uniform background).
        every = self.models
        tried = every if first is None else sorted(set(first) & set(every)) or every
        fitted = {index: self._model_fit(index, cur, start, gain, camera, prior, skip) for index in tried}
        found = [r for r in fitted.values() if r is not None]
        if first is not None and (not found or min(r.spread for r in found) > enough_spread):
            fitted.update({index: self._model_fit(index, cur, start, gain, camera, prior, skip)
                           for index in every if index not in fitted})
            systematic = reported_systematic = None
        results = [(index, fitted[index]) for index in sorted(fitted) if fitted[index] is not None]
        if not results:
            return empty
        index, chosen = self._chosen(results)
        best = chosen.spread
        if systematic is None:
            # What the plausible outline models (their outlines agree within PLAUSIBLE times the
            # best one's spread) disagree on is a systematic error the fit's scatter cannot
            # show: every profile of a straight outline shares its sub-pixel phase, so a
            # model's phase-dependent error is common to all of them. Their spread enters the
            # uncertainty; what a reading reports of it, see PLAUSIBLE_REPORTED.
            systematic = self._disagreement(results, PLAUSIBLE * best)
            reported_systematic = self._disagreement(results, PLAUSIBLE_REPORTED * best, weighted=True)
        return MemberFit(True, chosen.theta, self._covariance(chosen), chosen.used, self.n_profiles,
                         chosen.scale, np.array(systematic, np.float64), index, best,
                         len(fitted) == len(every),
                         None if reported_systematic is None else np.array(reported_systematic, np.float64))

    def _disagreement(self, results: list[tuple[int, _Solution]], reach: float, *,
                      weighted: bool = False) -> np.ndarray:
        """What the outline models of ``results`` whose profiles spread at most ``reach`` px
        disagree on (px, x and y): the standard deviation of their mean readings, each weighted
        by the inverse of its spread where ``weighted``; zero with fewer than two (one model, or
        a spread not finite)."""
        plausible = [r for _, r in results if r.spread <= reach + 1e-3]
        if len(plausible) < 2:
            return np.zeros(2)
        gu, gv = self.poi_field.mean_gradient()
        means = np.array([[gu @ r.theta, gv @ r.theta] for r in plausible])
        if not weighted:
            return means.std(axis=0)
        weights = np.array([1.0 / max(r.spread, 1e-3) for r in plausible])
        weights /= weights.sum()
        return np.sqrt(weights @ (means - weights @ means) ** 2)

    def _chosen(self, results: list[tuple[int, _Solution]]) -> tuple[int, _Solution]:
        """The outline model kept of ``results`` ((index, solution) pairs, see :meth:`fit`): the
        one whose outlines agree best, of those not :attr:`unchosen`; on one outline of lossy
        frames, in front of a uniform background, the profiles matched whole (see ONE_OUTLINE_WHOLE)."""
        whole = [r for r in results if r[0] == len(BLURS)]
        blurs = {i for i in self.models if i < len(BLURS) and BLURS[i] > 0.0}
        if (ONE_OUTLINE_WHOLE and self.one_outline and self.uniform_background and not self.lossless and whole
                and not blurs <= self.unchosen):
            return whole[0]
        return min([r for r in results if r[0] not in self.unchosen] or results, key=lambda r: r[1].spread)

    def _model_fit(self, index: int, cur: np.ndarray, start: np.ndarray, gain: float | None,
                   camera: np.ndarray | None, prior: np.ndarray, skip: np.ndarray | None = None) -> _Solution | None:
        """The motion as outline model ``index`` measures it (see :meth:`fit`): a blur model's
        fine fit in OUTLINE_ROUNDS rounds, or the profiles matched whole in two."""
        if index == len(BLURS):
            guess = start
            result = None
            for _ in range(2):
                found = self._shift(cur, guess, gain)
                usable = np.isfinite(found.edge) & np.isfinite(self.ref.edge)
                if skip is not None:
                    usable &= ~skip
                if usable.sum() < self.params.min_profiles:
                    return None
                d = (found.edge - self.ref.edge)[usable]
                result = self._solve(d, usable, 1.0 / np.maximum(found.var[usable], 1e-8), prior)
                if result is None:
                    return None
                guess = self.ref.edge + self.design @ result.theta
            return result
        blur, ref = BLURS[index], self.ref_by_blur[index]
        guess = start
        result = None
        for round_ in range(OUTLINE_ROUNDS):
            found = self._fine(cur, guess, gain, blur)
            if blur == 0.0 and round_ > 0:
                # Outlines that moved onto background the reference shows: from their area.
                known = self._known(cur, guess, gain, camera)
                use = np.isfinite(known.edge)
                for name in ("edge", "var", "contrast", "misfit"):
                    getattr(found, name)[use] = getattr(known, name)[use]
            usable = (np.isfinite(found.edge) & np.isfinite(ref.edge)
                      & (np.abs(found.contrast) >= self.params.min_contrast))
            if skip is not None:
                usable &= ~skip
            if usable.sum() < self.params.min_profiles:
                return None
            d = (found.edge - ref.edge)[usable]
            var = found.var[usable] + ref.var[usable]
            result = self._solve(d, usable, 1.0 / np.maximum(var, 1e-8), prior)
            if result is None:
                return None
            guess = ref.edge + self.design @ result.theta
        return result

    def _normal(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Displacement of each outline along its line for a motion (u, v) at the profiles:
        ``u - s v`` along a row, ``v - s u`` along a column (``s``: the outline's slope)."""
        return np.where(self.vertical, v - self.slope * u, u - self.slope * v)

    def _solve(self, d: np.ndarray, usable: np.ndarray, w0: np.ndarray,
               prior: np.ndarray) -> _Solution | None:
        """Robust weighted least squares of the motion field from outline displacements ``d``."""
        A = np.ascontiguousarray(self.design[usable])
        if not (np.isfinite(prior).all() and np.isfinite(d).all() and np.isfinite(w0).all()):
            return None  # (a NaN prior: the dense flow had none there; the frame keeps it)
        lam = self.params.prior_weight * float(np.sum(w0))
        theta, weights, z, scale = _irls(A, d, w0, prior, lam, float(self.params.tukey_c), MIN_SCALE)
        kept = weights > 0
        used = int(kept.sum())
        if used < self.params.min_profiles:
            return None
        r = (d - A @ theta)[kept]
        spread = MAD_TO_SIGMA * float(np.median(np.abs(r - np.median(r))))  # px: how well the outlines agree
        return _Solution(theta, A, weights, lam, used, scale, spread, z, usable)

    def _covariance(self, solution: _Solution) -> np.ndarray:
        """The parameters' covariance of ``solution``."""
        A, weights = solution.design, solution.weights
        H = A.T @ (A * weights[:, None]) + solution.lam * np.eye(N_PARAMS)
        # Neighbouring profiles see the same blob of background texture and the same codec
        # block, so their errors are correlated: the covariance of independent profiles is
        # scaled by the design effect 1 + 2 sum(rho) of the residuals along the outlines.
        return (np.linalg.inv(H) * solution.scale ** 2
                * self._design_effect(solution.z, solution.usable, weights > 0))

    def _design_effect(self, z: np.ndarray, usable: np.ndarray, kept: np.ndarray) -> float:
        """``1 + 2 sum_lag rho(lag)`` of the standardised residuals ``z`` of neighbouring
        profiles (same outline direction and side, lines ``lag`` apart), summed while the
        correlation stays positive."""
        group = (self.vertical[usable].astype(np.int64) * 2 + (self.side[usable] > 0)) * (1 << 20)
        key = group + self.line[usable]
        order = np.argsort(key)
        key, zz, ok = key[order], z[order], kept[order]
        zz = np.where(ok, zz - np.mean(z[kept]), 0.0)
        var = float(np.mean(zz[ok] ** 2)) if ok.any() else 0.0
        if var <= 0:
            return 1.0
        total = 1.0
        for lag in range(1, MAX_LAG + 1):
            pair = np.searchsorted(key, key + lag)
            pair = np.minimum(pair, len(key) - 1)
            both = ok & ok[pair] & (key[pair] == key + lag)
            if both.sum() < 10:
                break
            rho = float(np.mean(zz[both] * zz[pair[both]])) / var
            if rho <= 0.0:
                break
            total += 2.0 * rho
        return total

    def displacement(self, fit: MemberFit) -> tuple[np.ndarray, np.ndarray]:
        """``(u, v)`` of ``fit`` at the POIs."""
        return self.poi_field.uv(fit.params)

    def mean_sigma(self, fit: MemberFit, *, reported: bool = False) -> tuple[float, float]:
        """Standard uncertainty (px) of the mean displacement over the POIs, x and y: the fit's
        covariance and the blur models' disagreement (see :meth:`fit`; ``reported``: the one a
        reading reports, see PLAUSIBLE_REPORTED)."""
        gu, gv = self.poi_field.mean_gradient()
        systematic = fit.reported_systematic if reported and fit.reported_systematic is not None else fit.systematic
        sx = max(float(gu @ fit.cov @ gu), 0.0) + float(systematic[0]) ** 2
        sy = max(float(gv @ fit.cov @ gv), 0.0) + float(systematic[1]) ** 2
        return float(np.sqrt(sx)), float(np.sqrt(sy))
