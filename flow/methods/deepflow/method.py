"""``deepflow`` (DeepMatching + variational refinement) and ``deepmatching``.

Both are clean-room implementations from the papers (see
:mod:`flow.methods.deepflow.deepmatching` and :mod:`flow.methods.deepflow.variational`).

References
----------
.. [1] P. Weinzaepfel, J. Revaud, Z. Harchaoui, C. Schmid, "DeepFlow: Large
   displacement optical flow with deep matching", ICCV 2013.
.. [2] J. Revaud et al., "DeepMatching: Hierarchical Deformable Dense
   Matching", IJCV 2016.
"""

from __future__ import annotations

import dataclasses
import time
from typing import Any

import cv2
import numpy as np
from scipy import ndimage

from flow.io.errors import InputError
from flow.measure.photometric import sample
from flow.methods.base import CROP, CROP_MARGIN_PX, DenseMethod, check_pair, register
from flow.methods.deepflow.codecfloor import codec_copies, codec_floor
from flow.methods.deepflow.deepmatching import (
    ATOMIC,
    MatchParams,
    deep_matching,
    densify,
    response_bytes,
    search_radius,
)
from flow.methods.deepflow.hidden import SceneCheck
from flow.methods.deepflow.localfit import (
    WIDER_WINDOWS_PX,
    WINDOW_PX,
    refine_adaptively,
    refine_locally,
)
from flow.methods.deepflow.member import BLURS, MemberEdges, MemberFit, context_px, inner_outline
from flow.methods.deepflow.regionfit import RegionFit, RegionMotion, affine_departure
from flow.methods.deepflow.variational import VariationalParams, Workspace, refine
from flow.methods.params import Param, declared, with_defaults

_MATCH_FIELDS = {f.name for f in dataclasses.fields(MatchParams)}
_VAR_FIELDS = {f.name for f in dataclasses.fields(VariationalParams)}

# Presets in the spirit of DeepFlow's published settings; "fast" trades a few
# hundredths of a pixel for speed (coarser pyramid, fewer sweeps).
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "fast": {"eta": 0.8, "n_outer": 4, "n_sor": 15},
    "large-displacement": {"ngh_rad": 96.0, "max_patch": 64},
}


def _split(params: dict[str, Any]) -> tuple[MatchParams, VariationalParams]:
    unknown = set(params) - _MATCH_FIELDS - _VAR_FIELDS
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {sorted(unknown)}; valid: {sorted(_MATCH_FIELDS | _VAR_FIELDS)}"
        )
    match = MatchParams(**{k: v for k, v in params.items() if k in _MATCH_FIELDS})
    var = VariationalParams(**{k: v for k, v in params.items() if k in _VAR_FIELDS})
    return match, var


def _resolve(preset: str, overrides: dict[str, Any]) -> dict[str, Any]:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    merged = dict(PRESETS[preset])
    merged.update(overrides)
    return merged


# The matching's reach (its search radius, full-resolution px) follows the motion, not the
# frame: a member's motion decides how far a match must look, and the window solved (the POIs'
# bounding box plus the reach) and the matching's memory (which grows with the window's area
# times the reach squared) follow it. A measurement starts at BASE_REACH_PX, or where its chain
# has seen the POIs move (twice their latest motion, in doublings of the base); where the POIs'
# median motion found comes past WIDEN_SHARE of the reach, the motion may be leaving it, and
# the frame is solved again with the reach doubled (up to MAX_REACH_PX). A 4K frame then costs
# what its member's motion costs: with the old reach (a tenth of the frame's longer side, 384
# px at 4K) a 500x300 px member took 23 GB and 100 s a frame. The chain's own frames only:
# what earlier chains saw would make a frame's numbers depend on --jobs and --frames.
BASE_REACH_PX = 32.0
# A frame that shows nothing of the scene (flow.methods.deepflow.hidden) is solved at this
# fraction of the resolution (see DeepFlow._glimpse).
GLIMPSE_SCALE = 4
GLIMPSE_MIN_PX = 32  # the glimpse's shorter side at least (else a finer scale)
MEMBER_CONTEXT_PX = context_px()
WIDEN_SHARE = 0.5
MAX_REACH_PX = 256.0
# The matching's response volumes (both directions, all levels) are held under this many bytes
# per solve: a reach that would take more is searched at a coarser downscale (each doubling
# divides them by 16), so memory stays bounded whatever the motion.
MATCH_BUDGET_BYTES = 384 * 2**20
# The variational solver's scratch (see Workspace) is kept between solves up to this size.
WORKSPACE_KEEP_BYTES = 512 * 2**20


def _reach_for(motion_px: float | None) -> float:
    """The reach a measurement starts from: the base, doubled until it holds twice the motion."""
    reach = BASE_REACH_PX
    while motion_px is not None and reach < 2.0 * motion_px and reach < MAX_REACH_PX:
        reach *= 2.0
    return reach


def _matching_margin(match: MatchParams, shape: tuple[int, ...]) -> int | None:
    """Context a matching needs around the pixels asked for in a frame of ``shape``, at the
    start: its explicit search radius (``ngh_rad``), or the base reach (None where the whole
    image is searched: it is solved whole)."""
    radius = BASE_REACH_PX if match.ngh_rad is None else search_radius(match, shape)
    return _margin(radius) if radius > 0 else None


def _margin(reach: float) -> int:
    """The window's margin around the POIs for a matching of ``reach`` px: room for the
    matching and for the pyramid and smoothing to settle (CROP_MARGIN_PX)."""
    return max(CROP_MARGIN_PX, int(np.ceil(reach)))


def _match_at(match: MatchParams, reach: float | None, window_shape: tuple[int, ...],
              whole_shape: tuple[int, ...]) -> MatchParams:
    """``match`` with its search radius made explicit (``reach``; None: the frame's default,
    for a frame solved without POIs to follow) and a downscale coarse enough for a
    ``window_shape`` matching to fit :data:`MATCH_BUDGET_BYTES`."""
    explicit = match.ngh_rad is not None
    if not explicit:
        match = dataclasses.replace(match, ngh_rad=search_radius(match, whole_shape) if reach is None else reach)
    # (ngh_rad 0, the whole image, too: before 2026-12-05 it was exempt, and a 741x500 pair
    # took 24 GB and was killed.)
    while match.downscale < 8 and response_bytes(window_shape, match) > MATCH_BUDGET_BYTES:
        match = dataclasses.replace(match, downscale=min(8, 2 * match.downscale))
    needed = response_bytes(window_shape, match)
    if explicit and needed > MATCH_BUDGET_BYTES:
        # Even the coarsest matching of the user's radius would pass the budget (the default's
        # reach passes it only past a 4K window: MAX_REACH_PX at downscale 8 fits one; it goes
        # on there, as before).
        fits = _radius_within_budget(window_shape, match)
        raise InputError(
            f"ngh_rad={match.ngh_rad:g} searches {'the whole' if match.ngh_rad == 0 else 'so far in the'} "
            f"{window_shape[1]}x{window_shape[0]} px image that DeepMatching would need "
            f"{needed / 2**30:.1f} GB even at downscale {match.downscale} (budget "
            f"{MATCH_BUDGET_BYTES / 2**20:.0f} MB); give a search radius of at most {fits} px "
            f"(--param ngh_rad={fits}), or leave ngh_rad out to follow the motion")
    return match


def _radius_within_budget(window_shape: tuple[int, ...], match: MatchParams) -> int:
    """The longest search radius (full-resolution px, at least 1) whose matching of a
    ``window_shape`` image at ``match``'s downscale stays within MATCH_BUDGET_BYTES."""
    radius = 1
    while response_bytes(window_shape, dataclasses.replace(match, ngh_rad=float(2 * radius))) <= MATCH_BUDGET_BYTES:
        radius *= 2
    step = radius // 2
    while step >= 1:
        if response_bytes(window_shape, dataclasses.replace(match, ngh_rad=float(radius + step))) <= MATCH_BUDGET_BYTES:
            radius += step
        step //= 2
    return radius


# Frames of one chain (see the driver, :func:`flow.measure.driver.track_dense`) are measured in order.
# The first frame of a chain gets the full measurement: DeepMatching + DeepFlow, the member's
# edges fitted from the dense flow, and the check that they match the POIs better. Where the
# member's edges won, the next frames are tracked from the previous frame's member motion
# alone (still against the reference: no drift; no dense flow), as long as the POIs' mean
# photometric mismatch under that motion stays within WARM_RATIO times (and above 1 /
# WARM_RATIO times) the chain's last full measurement's, plus MATCH_SLACK grey levels; any
# other frame (an occlusion starting or ending, a jump, a knock, a failed fit) gets the full
# measurement, which becomes the chain's new key where the edges win it (where the dense
# flow wins, the chain's next frames are measured in full too).
# 32 frames (16 before 2026-12-05): the 16 bench clips read the same on their measured axis
# (RMSE within 0.001 px; bend 0.0386 -> 0.0378) with half the frames measured in full
# (lowtex-wide 14 -> 7); along a bar, where only a key's dense flow reads the motion, the error
# moved both ways (edge-on-thin 0.122 -> 0.135 px, lighting 0.106 -> 0.092). Longer chains
# balance worse over --jobs on short clips and make a --frames part re-solve more of its chain.
CHAIN_LENGTH = 32
WARM_RATIO = 1.3
# A tracked texture fit's plain rms residual at most this factor of its key's (plus MATCH_SLACK):
# wider than WARM_RATIO, since a lossy stream's residual varies with the motion between frames.
WARM_RMS_RATIO = 2.0
# An outline tracked from its previous frame that moved more than this (px, the POIs' mean)
# since then is measured in full: the outline fit finds each edge within a few pixels of its
# start, and a member swinging tens of pixels (motion-blurred, jittering) lost its edges in
# tracked frames (2 px RMS on a +-35 px swing where full measurements read 0.2 px). At 1.5 px
# the bench's lowtex-wide bar (4.5 px at a few Hz) was measured in full in 46 frames of 180
# instead of 14, for no gain.
MAX_WARM_STEP_PX = 3.0
# A tracked frame's outline is measured first by its chain key's outline model and the blur
# models either side of it, the sharp one and the profiles matched whole (the key's choice, or
# its neighbour's, holds through most chains: five blur models cost two thirds of a tracked
# frame), and by every model only where the best of those has a spread above this factor of
# the key's: a member swinging tens of pixels changes its outlines' look from frame to frame
# (g9-large-motion: its keys chose four different models, and without the fall-back a tracked
# frame read up to 6 px off). At 1.2 every bench clip reads as with all of them on every frame
# (dx_px, dy_px to 1e-6 px; only sigma moves, by the key's disagreement standing in for the
# frame's). Without the neighbours (the key's, the sharp one and the whole-profile match only)
# g9 read 0.1244 px against 0.1241 at 1.2 and 0.1265 at 1.5, and the workbench's `compression`
# scenario (a blurred outline whose frames choose the key's model or the next) 0.064 mm RMSE
# against 0.058 with every model, `low-light` 0.0228 against 0.0224.
TRACKED_SPREAD_RATIO = 1.2


# The edge refinement is kept when the POIs' mean photometric mismatch under it is at most
# this factor of the dense flow's plus MATCH_SLACK grey levels (sensor noise moves both alike).
MATCH_TOLERANCE = 1.1
MATCH_SLACK = 0.5
# ... and at most MATCH_RATIO times it plus MATCH_RATIO_SLACK grey levels: where the POIs' pixels
# are smooth (a shaded round column, its shading the member's own texture) the two mismatches are
# a fraction of a grey level and MATCH_SLACK alone let an outline read 0.4-0.6 px off through
# (its mismatch 1.7-2.3 times the dense flow's; 0.266 and 0.193 px RMS on two draws, 0.083 and
# 0.176 now, against the dense flow's 0.068 and 0.055). On the bench's clips the outlines'
# mismatch is at most 1.15 times the dense flow's where the outline is read (the painted bars,
# the cylinder, g8, g9); 1.4-3.3 on the textured panels, which are read by their texture.
MATCH_RATIO = 1.3
MATCH_RATIO_SLACK = 0.05
# On a lossy stream the affine texture fits (the region's, the background's, and the codec floor's
# that measures them) smooth both frames by CODEC_PRESMOOTH_PX first (see
# flow.methods.deepflow.regionfit): x264 rings about sharp edges and rebuilds each block's finest
# detail its own way, which the fit reads as motion of the whole region. Measured (defaults, H.264
# CRF 18-23, scene kinds drawn outside the bench): a panel of sharp-edged windows (16 px period)
# 0.097 -> 0.037 px RMS, slope 1.036 -> 1.004 (DIS 0.037); its fit started at the truth, periods 16 /
# 12 / 8 (CRF 23) 0.069 / 0.036 / 0.059 -> 0.037 / 0.034 / 0.054, sharp-edged random tiles 0.047 ->
# 0.031 (0.5 px of smoothing: 0.043 / 0.033 / 0.052 / 0.035). The bench's textured clips move by a
# few thousandths: g1 0.0302 -> 0.0308, g2 0.0442 -> 0.0447, g5 0.0318 -> 0.0332, g7 0.0186 ->
# 0.0187, g8 0.0371 -> 0.0367 (slope 0.911 -> 0.916); lossless frames (DIC images) are fitted as
# they are. Not the paint's quick fit along a member (ALONG_POINTS): smoothed, more of the bench's
# faint paints converged and their chains tried them in every frame, for the same readings and
# 17-19 % of the painted bars' time (a faint paint sliding along its bar read 0.166 instead of
# 0.190 px).
CODEC_PRESMOOTH_PX = 0.7

# An outline fixes a member's motion across it; along the member (a column settling, a deck
# moving lengthwise, a bar sliding along its axis) it has only the ends of its grown mask, and
# the dense flow's smoothing over a faint paint reads that motion about half (a painted bar of
# 4 grey levels moving +-2 px along its length, H.264: slope 0.40, RMSE 0.90 px; DIS 0.88 /
# 0.22). The region's own texture, however faint, is a third witness: a translation fit over
# ALONG_POINTS of its pixels (a regular subsample: the cost), to ALONG_TOLERANCE_PX, started at
# the better of the other two motions in a full measurement (the fit's whole budget) and at the motion the
# chain's texture readings predict in a tracked frame (ALONG_ITERATIONS steps at most; a chain
# whose key's fit did not converge, the bench's painted bars mostly, does not try). Its
# along-member motion is taken where the POIs match it clearly better than the other two's, its
# mismatch below ALONG_CLEAR times the better one's: the bar sliding along its length matched
# it 1.3-2.5x better (read now 0.19 px, slope 0.93-0.97); the bench's painted bars, whose paint a
# codec rebuilds in every frame, a few per cent better at most, where its along-member reading
# is the worse (against the truth, taken wherever it matched better at all: bend 0.21 -> 0.28 px,
# edge-on-thin 0.12 -> 0.41, tiny 0.07 -> 0.23).
ALONG_POINTS = 1000
# ... only where at least this share of the region's pixels lie clear of the outline (see
# OUTLINE_CLEAR_PX): a thin cable's mask (5 px across a 6 px cable, 2-4 % of it clear) has no
# paint of its own, only the outline's step and the codec's blocks, and the POIs' match with it
# (a mask inside a dark member matches it a fraction of a pixel off across as well as on) kept
# improving along the cable in isolated frames: its fit from a walk's start 3.6-5.7 px along was
# taken, and through the cable's 3 degree tilt read its motion 0.2-0.3 px off (two draws of
# bench_scene_kinds' cable, 0.039 and 0.036 px RMS before the walk, 0.054 and 0.076 with it).
ALONG_MIN_CLEAR = 0.5
ALONG_ITERATIONS = 20
ALONG_TOLERANCE_PX = 2e-3
ALONG_CLEAR = 0.9
# The paint's fit also starts this far (px) either side of its start along the member (the
# minima a codec's whole-pixel copies of a faint paint leave: see _Region.motion), with at most
# HOP_ITERATIONS steps in a tracked frame (a minimum that near is reached in a few; 20 cost the
# bench's painted bars 13-26 % of their time, 8 cost 10 %).
ALONG_HOP_PX = 1.0
HOP_ITERATIONS = 8
# Where the POIs match a start two hops along better than one, and so on, the paint's fit also
# starts from the farthest hop the match improved to, up to this many (a member sliding along
# itself farther than a hop in a frame, which the dense flow over its faint paint did not see).
ALONG_WALK_HOPS = 16
# A region's texture fit leaves out the pixels a codec copied from the reference (see
# flow.methods.deepflow.codecfloor.codec_copies: a member moving +-0.3 px at CRF 28 read slope
# 0.57 with them, DIS 0.68), where at least this share of its pixels stays.
COPY_MIN_KEPT = 0.1
# An outline more than this share of whose profiles a codec copied from the reference is not read
# where a strong texture's fit (the copies left out) reads the region: the codec froze the
# member's edges, and the rest were copied from frames near the reference (a textured member
# moving +-0.3 px at CRF 28: 64 % of its profiles the reference's, the outline read no motion in
# 13 frames running, 0.15 px RMS where DIS read 0.06). Not where the texture is faint: a bar
# sliding along itself shows its edges unchanged, and the codec copies them (a faint paint
# sliding +-2 px: up to 100 % of its profiles; its outline, right across the bar, is read).
COPY_OUTLINE_MAX = 0.5


def _mismatch(reference: np.ndarray, current: np.ndarray, cols: np.ndarray, rows: np.ndarray,
              u: np.ndarray, v: np.ndarray) -> float:
    """Mean |current(x + d) - reference(x)| over the points (bilinear, grey levels; points
    whose position leaves the frame are clamped to its edge). Any number of points (OpenCV's
    remap refuses maps wider than 32767)."""
    height, width = current.shape
    x = np.clip(cols + u, 0, width - 1)
    y = np.clip(rows + v, 0, height - 1)
    warped = sample(current, x, y)
    before = reference[rows, cols].astype(np.float32)
    if abs(_exposure(reference, current) - 1.0) > MISMATCH_GAIN_BAND:
        # The exposure changed: the points' own gain (their grey, as this motion brings it
        # back, against the reference's) is taken out, to the fraction of a grey level a faint
        # paint needs (the whole image's is a grey level or two off at the points).
        gain = float(np.nanmedian(warped)) / max(float(np.median(before)), 1e-6)
        if np.isfinite(gain) and gain > 0:
            warped = warped / np.float32(gain)
    return float(np.nanmean(np.abs(warped - before)))


# A frame whose brightness differs from the reference's by more than this fraction over the
# whole image (a phone's exposure stepping) is compared after the points' gain is taken out (see
# _mismatch). Told over the whole image, not the points: a member moving across its own shading
# (the bench's shaded column, +-10 % at its points) is no exposure change; a bar moving over its
# wall moves the whole image's mean by 0.4 % at most on the bench.
MISMATCH_GAIN_BAND = 0.01


def _exposure(reference: np.ndarray, current: np.ndarray) -> float:
    """The frame's brightness relative to the reference's: the ratio of their means over
    every 4th pixel of each 4th row (1 where it is not finite and positive)."""
    mean_ref = float(np.mean(reference[::4, ::4], dtype=np.float64))
    gain = float(np.mean(current[::4, ::4], dtype=np.float64)) / max(mean_ref, 1e-6)
    return gain if np.isfinite(gain) and gain > 0 else 1.0


# Which reading a region takes in a full measurement (see :func:`_choose`). The texture fit
# assumes least (no straight edges, no background standing still): where it fixes the motion
# to TEXTURE_ENOUGH_PX (standard uncertainty) on both axes, it is taken. A fainter texture
# is not trusted over a member's outline: a codec rebuilds a painted member's faint texture
# differently in every frame and lays its fixed block pattern over it, which biases the whole
# region alike (0.2-0.4 px on the bench's thin bar, where the fit's own uncertainty said
# 0.01-0.04 px and the outline read 0.05 px RMS). Measured on the bench's textured clips
# (panel, whole view, bolted plate, girder): 0.003-0.006 px; a wide painted bar at CRF 12
# (the bench's lowtex-wide): down to 0.01-0.02 in some frames, where the outline is better.
TEXTURE_ENOUGH_PX = 0.012
# ... and only where the texture is strong: an rms grey-level gradient over the region of at
# least MIN_TEXTURE_GRADIENT grey levels per pixel on both axes (a codec rebuilds about a
# grey level of a texture differently from frame to frame, so a fainter texture carries no
# displacement a codec leaves alone). Measured on the reference frames of the bench: painted
# bars 0.23-0.67; textured panel, whole view, bolted plate, slab, girder 1.5-7.7; the shaded
# column 4.1 across and 0.2 along.
MIN_TEXTURE_GRADIENT = 1.0
# ... over the region's pixels more than OUTLINE_CLEAR_PX from the member's outline in the
# reference: an outline's step is the outline model's to read, and its pixels change layer as
# the member moves over what is behind it. A thin cable's mask (5 px across a 6 px cable) is all
# outline: its step made the texture 'strong', and the texture fit over it read 0.12 px RMS
# where the outline and the dense flow read 0.04.
OUTLINE_CLEAR_PX = 3.0
# Where the region's shading or texture is strong (SHADED_ACROSS_GRADIENT: the rms of its gradient
# across the member, the axis its outline fixes) but not on both axes, and no blur model draws the
# reference's outlines within SHADED_OUTLINE_MISFIT times their noise (the member.MemberEdges.
# best_reference_misfit: no blurred step there), the dense flow sees the motion across and the
# outline is not fitted. A round column's limb darkens into the wall (the tests' `round` kind: best
# misfit 2.2-4.0, the bench's g4-cylinder 3.0): the outline models' readings of a frame spread 0.2-
# 1.6 px, the one kept read four draws 0.10-0.19 px RMS where the dense flow read 0.06-0.08. A
# bar painted in lengthwise stripes in front of a textured wall has a clean step for an outline
# (misfit 1.3) and reads better by it (0.057 px against the dense flow's 0.090; a reviewer's
# find on a first version of the rule without the misfit); the painted bars of the bench and of
# the tests misfit 0.2-0.6.
SHADED_ACROSS_GRADIENT = MIN_TEXTURE_GRADIENT
SHADED_OUTLINE_MISFIT = 2.0
# Where the codec froze the member's outline (more than COPY_OUTLINE_MAX of its profiles copied
# from the reference, see _copied_profiles) the outline reads little or no motion. A texture of at
# least FROZEN_TEXTURE_GRADIENT, on a stream whose codec leaves its reading within
# FROZEN_TEXTURE_FLOOR_PX (its codec floor, both axes), is then fitted (the copies left out) and
# taken as a strong one is, in that frame; beside it an outline is frozen from FROZEN_TEXTURE_COPIED
# of its profiles copied on. A faint panel (5 grey levels) moving +-0.3 px at CRF 18, its outline
# 20 px beyond the mask, strength 0.95-0.99 on three draws of six, x264 copying 39-61 % of its
# profiles in every frame: the outline read them 0.193, 0.147 and 0.199 px RMS, slope 0.14, 0.41
# and 0.08, where DIS read 0.103 / 0.77, 0.118 / 0.84, 0.094 / 0.83; now 0.100 / 0.89, 0.084 /
# 0.93, 0.065 / 0.90 (codec floors 0.08-0.11 px). Two reviewers' finds on the first versions: a
# chain of the texture's readings went on from one frozen frame (a faint bar moving +-1.5 px,
# frozen in its nearly still first frames, read 0.062 -> 0.092 px; it ends now where the outline
# is no longer frozen); and faint bars moving +-0.3 px at CRF 23-28 (codec floors 0.13-0.30 px)
# read 0.154 -> 0.290 and 0.218 -> 0.379 px (DIS 0.173, 0.284) with the texture taken: read as
# before now. Above the bench's painted bars (0.23-0.67), read as before. Since 2026-12-07 (night)
# a strong texture's outline is frozen from FROZEN_TEXTURE_COPIED on too, where its codec floor is
# as small (before: from COPY_OUTLINE_MAX): four draws of that panel whose texture came out just
# strong (1.04-1.13), x264 copying 27-50 % of the outline's profiles, read the outline in most
# frames, 0.094 / 0.89, 0.183 / 0.24, 0.203 / 0.05 and 0.089 / 0.75 px RMS / slope, where the
# weaker draws read their texture and DIS read 0.095 / 0.83, 0.091 / 0.80, 0.079 / 0.75 and
# 0.084 / 0.75; now 0.070 / 0.95, 0.084 / 0.84, 0.068 / 0.75 and 0.069 / 0.80.
FROZEN_TEXTURE_GRADIENT = 0.75
FROZEN_TEXTURE_FLOOR_PX = 0.12
FROZEN_TEXTURE_COPIED = 0.25
# The outline model needs an outline between two layers: the member and a background that
# either stands still behind it or moves with it (a plate fixed to the member, a whole view
# moving), not one that the dense flow drags part of the way. In a full measurement the dense
# flow is read on the member side of every outline and beyond it, at BACKGROUND_OFFSET_PX plus
# BACKGROUND_DRAG times the member's motion (the dense flow's smoothing drags a fast member's
# motion into the background in proportion). Where the member moves by more than
# STATIC_MIN_MOTION_PX, on each side of the member the background's median motion must stay
# within STATIC_RATIO of the member's motion (plus STATIC_SLACK_PX) of zero, or within
# WITH_RATIO of it (plus the slack) of the member's median motion; else the outline is not an
# edge the dense flow can tell (a round column's dark side against a wall, dragged 0.3-0.6 of
# the way: the outline read 0.13 px RMS there, the dense flow 0.04). WITH_RATIO is the
# stricter: for a motion of a pixel or less the slack would let such a drag, 0.6-0.75 of the
# way there, pass as moving with. A background moving with the member is the workbench's own
# scene: the logo plate behind the beam's edge (and the plain wall beside it, which the
# smoothing drags 0.9 of the way) moves with the beam; refusing its outline left an 8 px
# strip's imprecise texture fit, 0.080 mm RMS where the outline reads 0.013 (DIS 0.016).
# Where the background beyond the outline moves with the member on every side (an I-beam's web
# between its flanges: the profiles' window, SHIFT_HALF px either side of the outline, lies on the
# member), the profiles matched whole (the last outline model, WHOLE) are the one model that draws
# what each profile shows: the blur models take the reference's pixels beyond the outline for a
# background that stands still. On the tests' blurred I-beam (a web 60 px wide between flanges 10
# px wide, 1.5 px out of focus) a blur model whose outlines agreed best read 0.25-0.45 px short
# in a frame in four (0.079-0.174 px RMS on four draws, DIS 0.062-0.121), the profiles matched
# whole 0.021-0.060 px RMS. Not where one side stands still (the workbench's beam: a plate fixed
# to it behind one edge, the wall beyond the other). The dense flow alone is not enough: over the
# flat sky beside the tests' dark deck it is dragged with the deck, and the profiles matched whole
# read it 0.048 -> 0.059 px; the pixels beyond most of the profiles (WITH_SHOWN_SHARE) must show it
# too, from 3 px beyond the outline (its blur) plus the member's motion (what it moved over or
# uncovered) to the profiles' reach of 9 px: their two predictions, the reference's pixels where
# they are and where the member's motion brought them from, differ by at least WITH_EVIDENCE
# (2 grey levels rms: a flat sky shows nothing either way) and the moved one fits them
# WITH_SEEN_RATIO times better (the I-beam's: 0.02-0.1 of the still one's misfit). Counted
# beyond all the profiles, not per side: a deck's spurious profiles inside it, 6 of 43, showed
# its own outline moving (0.040 -> 0.050 px).
WHOLE = (len(BLURS),)
WITH_BAND_PX = (3, 9)  # the pixels beyond the outline that must show it (member.HALF, a profile's reach)
WITH_EVIDENCE = 4.0  # grey levels squared: the predictions' mean square difference there
WITH_SEEN_RATIO = 0.25
WITH_SHOWN_SHARE = 0.5
BACKGROUND_OFFSET_PX = 6
BACKGROUND_DRAG = 0.5
STATIC_MIN_MOTION_PX = 0.5
STATIC_RATIO = 0.3
STATIC_SLACK_PX = 0.1
WITH_RATIO = 0.15
# A side whose dense flow says part of the way keeps its outline where its pixels clearly show
# the background still or moving with the member (see _background_seen): the better of the two
# predictions fits within 1/CLEAR_RATIO of their difference and SEEN_RATIO of the other's misfit.
CLEAR_RATIO = 10.0
SEEN_RATIO = 0.25
# A background moving on its own (foliage, traffic, water behind a member) is no drag either:
# where a side's pixels beyond the outline clearly show the reference moved by a motion of
# their own (fitted to them, started at the dense flow's there) that is no fraction of the
# member's (its part across the member's motion more than OWN_ACROSS of the member's, or along
# it beyond the member's motion, each past STATIC_SLACK_PX), the side keeps its outline: the
# member fit predicts the background under the outline from the frame's own pixels beyond it.
# A faint bar before foliage swaying 3 px on its own: refused in 44 of 60 frames, whose dense
# flow read 0.17 px RMS (DIS 0.11); the outline is now taken in 56 and the bar reads 0.045. (The
# dense flow's own motion there will not do: it is the smoothing's blend, and the member's
# motion read at its outline carries a third of the background's.) Every bench clip, the shaded
# column's limb (dragged a fraction of the way) included, reads what it read.
OWN_ACROSS = 0.3
OWN_BAND_PX = 4  # the pixels fitted: this many more along each profile beyond its sample
OWN_STEPS = 5
# A background sample within this of the member's advanced outline counts as hidden (blur).
HIDDEN_MARGIN_PX = 2.0
HIDDEN_SHARE = 0.25

# A strong texture's region is read by the dense flow where the dense flow shows it deforming
# beyond an affine field (see _deforms): its departure from its own affine fit, smoothed over
# a few pixels, more than DEFORM_RATIO times the robust scale of the departure's pixel-scale
# rest plus a floor: DEFORM_FLOOR_PX on lossless frames, DEFORM_CODEC_FLOOR_PX on a lossy
# codec's, whose error in a dense flow is correlated over its macroblocks (16 px) and passes
# the smoothing as a deformation would, dozens of times the rest (the bench's H.264 clips with
# a strong texture: up to 0.10 px smoothed, on the rotating slab; whole view 0.038, bolted
# plate 0.074, textured panel 0.063). Lossless, DIC Challenge Sample 14 (a 0.1 px sine)
# reads 0.06-0.07 px on its right half (the rest below 0.01), Star 1 (a 0.5 px wave) 0.32 px,
# 15 times its rest.
DEFORM_RATIO = 4.0
DEFORM_FLOOR_PX = 0.005
DEFORM_CODEC_FLOOR_PX = 0.25
# A region the dense flow shows deforming is read from that field (refined, see localfit) unless
# the texture's affine fit matches the region's pixels (mean |difference|, see _mismatch) below
# DEFORM_MATCH_RATIO times the refined field's: a deforming region's field matches at least as
# well as any affine one. Measured: DIC Challenge Sample 14's sine and Sample 12's plate (true
# deformations) 1.02-1.52 times the field's mismatch; a facade of sharp-edged windows whose dense
# flow tore across its grid (bench_scene_kinds' windows, two keys read 1.08 and 0.71 px off) 0.28
# and 0.51.
DEFORM_MATCH_RATIO = 0.9

# An outline whose own standard uncertainty exceeds this (px) on both axes cannot resolve a
# sub-pixel motion by its own account (the tool's limit for a clip's typical uncertainty is
# 0.35 px): it is not taken, in a full measurement or a tracked frame. A shaded round column
# (its limb darkens into the wall: no step to fit) read 0.3-1.8 px this way and 0.19 px RMS,
# 6 % long, where the dense flow read 0.06; the bench's painted bars stay below 0.4.
OUTLINE_MAX_SIGMA_PX = 0.5
# Where it is refused so and the region's texture is too faint to be trusted over an outline
# (MIN_TEXTURE_GRADIENT), the texture's affine fit is read in place of the dense flow if it
# resolves the motion by its own account on both axes (its sigma, the codec's error counted,
# within FAINT_TEXTURE_MAX_SIGMA_PX) and matches the region's pixels at least as well as the
# dense flow (see _faint_texture; such a reading keys no chain: the next frame is measured in
# full). Both read the same faint paint, but the dense flow's smoothing also holds a member whose
# outline hardly shows back towards the still wall around it: a bar of grey 118 over a wall of
# 111 +- 35 (bench_bar_extremes' low-contrast, seed 401, H.264 CRF 18), its outline refused in 39
# frames of 90, read them 1.0-1.7 px short where it stood 4-5.5 px out (the clip: 0.924 px RMS,
# slope 0.770; DIS 0.245 / 0.944) where the paint's fit, sigma 0.14-0.30 px, reads 0.241 / 0.970.
FAINT_TEXTURE_MAX_SIGMA_PX = OUTLINE_MAX_SIGMA_PX

# Why a full measurement took its model: the sidecar's timings count each (``why_<reason>``,
# a region in a frame), beside the readings of each model and the outlines refused (REFUSALS):
# because the background beyond them moved with the member (``why_outline_background_moves``),
# because they were too imprecise (``why_outline_imprecise``), or because a strong texture was
# more precise (``why_outline_background_unseen``, ``why_outline_texture_sharper``).
REASONS = {
    "texture_fixes_motion": "the texture is strong and fixes the motion on both axes",
    "outline_no_texture": "the outline; no strong texture fit",
    "outline_texture_imprecise": "the outline; the strong texture fit is not precise enough",
    "texture_no_outline": "the strong texture however imprecise; no outline against a still background",
    "dense_only": "the dense flow; neither a strong texture nor an outline against a still background",
    "dense_deforms": "the dense flow; the strong texture shows the region deforming beyond an affine field",
    "texture_matches_better": "the strong texture's affine fit; the dense flow showed the region deforming, "
                              "but its refined field matched the region's pixels clearly worse",
    "faint_texture": "the faint texture's affine fit; the outline was refused as too imprecise, and the fit "
                     "resolves the motion on both axes and matches the region's pixels at least as well "
                     "as the dense flow",
    "outline_matches_better": "the outline; the dense flow showed the region deforming and the texture's "
                              "fit failed or matched no better, but the refined field matched the region's "
                              "pixels clearly worse than the outline's motion",
    "outline_background_unseen": "an outline refused: a strong texture more precise than it, and the "
                                 "background never seen still or moving with the member while it moved",
    "outline_background_moves": "an outline refused: the background beyond it moves part of the way "
                                "with the member (neither still nor with it)",
    "outline_imprecise": "an outline refused: its own uncertainty exceeds OUTLINE_MAX_SIGMA_PX on both axes",
    "outline_texture_sharper": "an outline refused: a strong texture's fit is at least as precise as it "
                               "on both axes (its background seen still)",
    "outline_codec_copied": "an outline refused: the codec copied most of its pixels from the reference "
                            "unchanged (a motion below what it codes: the edges show none)",
    "outline_shaded_across": "an outline not fitted: the region's own shading or texture is strong across "
                             "the member, though not along it, and the dense flow reads it",
}
# The reasons that count a refusal, not the choice a full measurement made.
REFUSALS = ("outline_background_moves", "outline_imprecise", "outline_background_unseen", "outline_texture_sharper",
            "outline_codec_copied", "outline_shaded_across")


def _choose(affine: tuple | None, outline: tuple | None, strong: bool,
            deforms: bool = False) -> tuple[tuple | None, str, str]:
    """The reading a region takes from its affine texture fit and its outline fit (each
    ``(u, v, (sigma_x, sigma_y))`` or None; ``strong``: the region's texture is strong enough
    to be trusted over an outline; ``deforms``: the dense flow shows the region deforming
    beyond any affine field, see :func:`_deforms`), the model's name and why (a key of
    :data:`REASONS`)."""
    if strong and deforms:
        return None, "dense", "dense_deforms"
    affine = affine if strong else None
    if affine is not None and max(affine[2]) <= TEXTURE_ENOUGH_PX:
        return affine, "affine", "texture_fixes_motion"
    if outline is not None:
        return outline, "outline", "outline_no_texture" if affine is None else "outline_texture_imprecise"
    if affine is not None:
        return affine, "affine", "texture_no_outline"
    return None, "dense", "dense_only"


class _TextureSigma(tuple):
    """A texture fit's own sigma ``(sigma_x, sigma_y)``: the reading it goes with came from the
    texture, whose codec floor (see :meth:`_Region.reported_sigma`) is added once it is chosen."""


class _OutlineSigma(tuple):
    """An outline fit's own sigma ``(sigma_x, sigma_y)`` with what it cannot see of the motion
    along the member (see :meth:`_Region.motion`), added once the reading is reported:
    ``ambiguity`` (px), half the farthest along-member motion that matched the POIs about as
    well as the one taken, and ``texture``, whether the taken one is the paint's own fit (its
    codec floor then counts along the member); ``reported``, the own sigma reported (see
    member.PLAUSIBLE_REPORTED; the decisions take the tuple's)."""

    def __new__(cls, sigma: tuple[float, float], ambiguity: float = 0.0, texture: bool = False,
                reported: tuple[float, float] | None = None) -> _OutlineSigma:
        made = super().__new__(cls, (float(sigma[0]), float(sigma[1])))
        made.ambiguity, made.texture = float(ambiguity), bool(texture)
        made.reported = made if reported is None else (float(reported[0]), float(reported[1]))
        return made


def _matches(edges: float, dense: float) -> bool:
    """Whether an outline's motion matches the POIs' pixels (their mean photometric mismatch
    ``edges``) about as well as the dense flow's (``dense``; see MATCH_TOLERANCE, MATCH_RATIO)."""
    return edges <= MATCH_TOLERANCE * dense + MATCH_SLACK and edges <= MATCH_RATIO * dense + MATCH_RATIO_SLACK


def _first_models(key: int) -> tuple[int, ...]:
    """The outline models a tracked frame tries first (see TRACKED_SPREAD_RATIO): its chain
    key's ``key`` and the blur models either side of it, the sharp one and the whole-profile
    match (index ``len(BLURS)``); of them, the member measures a frame under the plausible ones
    only (see :meth:`MemberEdges.fit`)."""
    near = {key - 1, key, key + 1} if key < len(BLURS) else {key}
    return tuple(sorted({0, len(BLURS)} | (near & set(range(len(BLURS) + 1)))))


@dataclasses.dataclass
class _Region:
    """One region of the POI mask: its member's edges, its texture, and where its chain stands."""

    label: int  # the region's value in the mask (1 for a bool mask)
    member: MemberEdges | None  # None: the outline is not used
    texture: RegionFit | None  # the region as one correlation subset (None: not used or no texture)
    rows: np.ndarray  # the region's POIs
    cols: np.ndarray
    prior_rows: np.ndarray  # where the dense flow is read for each outline: its member-side pixel
    prior_cols: np.ndarray
    ref_level: float  # the reference's median grey at the POIs
    model: str | None = None  # what the chain's key chose ("outline", "affine"; None: measure in full)
    theta: np.ndarray | None = None  # the outline's motion of the chain's last frame
    key_mismatch: float = float("nan")  # the POIs' mismatch at the chain's last full measurement
    key_along: np.ndarray | None = None  # the along-member motion the chain's key took from elsewhere
    key_outline: tuple | None = None  # the key's outline model, its models' disagreement and its spread
    affine: np.ndarray | None = None  # the texture's affine motion of the chain's last frame
    affine_before: np.ndarray | None = None  # and of the frame before it
    key_residual: float = float("nan")  # the texture fit's residual at the chain's key
    key_rms: float = float("nan")  # and its plain rms over the region's pixels (those in the frame)
    static_known: bool = False  # the chain's key saw the background still or moving with the member
    reference: np.ndarray | None = None  # kept for the codec floor (None: the frames are lossless)
    codec_crf: float | None = None  # the lossy stream's quality (see flow.methods.deepflow.codecfloor)
    codec_floor_px: tuple[float, float] | None = None  # measured on the first texture reading
    along_floor_px: tuple[float, float] | None = None  # the paint's, on its first along reading (see _codec_floor)
    along_fit: RegionFit | None = None  # the quick translation fit of the along-member motion
    last_mean: tuple[float, float] | None = None  # the POIs' mean motion in the part's last frame
    last_step_px: float = 0.0  # how far it moved from the frame before (see DeepFlow._track)
    texture_strength: tuple[float, float] = (0.0, 0.0)  # the texture's strength away from the outline
    texture_across: float = 0.0  # and across the member (see SHADED_ACROSS_GRADIENT)
    along_tried: bool = False  # the chain's key's texture along fit converged: its frames try it too
    along_texture: bool = False  # and the key took its along-member motion: its frames take theirs
    along_seen: tuple | None = None  # the texture's along-member motion of the last two frames taking it
    along_ambiguity: float = 0.0  # px, the last motion's (see motion): what the POIs could not tell apart along
    key_ambiguity: float = 0.0  # and the chain key's
    key_with: bool = False  # whether the key's background moved with the member (see WHOLE)
    # The mask's POIs beyond the member's outline (a mask drawn past it onto the background, see
    # member.inner_outline): they take the member's mean motion where its outline read it (its
    # background seen standing still), their own dense flow otherwise; rows and cols above are
    # the member's part. A region with a rim is not tracked by its texture (a tracked frame has
    # no dense flow for the rim's own pixels).
    rim_rows: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    rim_cols: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.intp))
    rim_px: int = 0  # how far the mask reaches past the outline (px, its wider side)
    read_by: str | None = None  # what read the region's last frame ("outline", "affine"; None: the dense flow)

    @classmethod
    def of(cls, reference: np.ndarray, mask: np.ndarray, label: int, *, member: bool,
           texture: bool, bias_correction: bool = True, codec_crf: float | None = None) -> _Region:
        height, width = reference.shape
        inner = inner_outline(reference, mask) if member else None
        rim = np.zeros(mask.shape, bool)
        if inner is not None:
            rim = mask & ~inner[0]
            mask = inner[0]
        rows, cols = np.nonzero(mask)
        edges = MemberEdges.from_reference(reference, mask, lossless=codec_crf is None, codec_crf=codec_crf) if member else None
        presmooth = _presmooth(codec_crf)
        fit = (RegionFit(reference, rows, cols, bias_correction=bias_correction, presmooth_px=presmooth,
                         rounding_floor=codec_crf is None)
               if texture and rows.size >= 8 else None)
        if fit is not None and not fit.textured:
            fit = None
        prior_rows = prior_cols = np.zeros(0, np.intp)
        if edges is not None:
            inward_x = np.where(edges.vertical, edges.px, edges.px - 0.5 * edges.side)
            inward_y = np.where(edges.vertical, edges.py - 0.5 * edges.side, edges.py)
            prior_rows = np.clip(np.rint(inward_y).astype(np.intp), 0, height - 1)
            prior_cols = np.clip(np.rint(inward_x).astype(np.intp), 0, width - 1)
        lossy = fit is not None and codec_crf is not None
        clear = None if fit is None else _clear_of(edges, fit.rows, fit.cols)
        # The paint's own along fit, where the region has paint of its own: most of its pixels
        # clear of the outline (see ALONG_MIN_CLEAR).
        along_fit = None if fit is None or edges is None or not clear.mean() >= ALONG_MIN_CLEAR else RegionFit(
            reference, rows, cols, bias_correction=bias_correction, max_points=ALONG_POINTS,
            tolerance_px=ALONG_TOLERANCE_PX, rounding_floor=codec_crf is None)
        strength = (0.0, 0.0) if fit is None else fit.gradient_rms_of(clear)
        across = 0.0 if fit is None or edges is None else fit.gradient_rms_along(clear, edges.axes[:, 1])
        rim_rows, rim_cols = np.nonzero(rim)
        return cls(label, edges, fit, rows, cols, prior_rows, prior_cols,
                   float(np.median(reference[mask])) or 1.0, reference=reference if lossy else None,
                   codec_crf=codec_crf if lossy else None, along_fit=along_fit, texture_strength=strength,
                   texture_across=across,
                   rim_rows=rim_rows, rim_cols=rim_cols, rim_px=0 if inner is None else inner[1])

    @property
    def strong_texture(self) -> bool:
        """Whether the region's texture is strong enough to be fitted and taken (see
        MIN_TEXTURE_GRADIENT; a weaker one is never fitted)."""
        return self.texture is not None and min(self.texture_strength) >= MIN_TEXTURE_GRADIENT

    @property
    def shaded_across(self) -> bool:
        """Whether the region's own shading or texture is strong across its member, not a strong
        texture on both axes, and its outline no blurred step (see SHADED_ACROSS_GRADIENT)."""
        return (self.member is not None and self.texture is not None and not self.strong_texture
                and self.texture_across >= SHADED_ACROSS_GRADIENT
                and self.member.best_reference_misfit() >= SHADED_OUTLINE_MISFIT)

    def restart(self) -> None:
        self.model, self.theta, self.key_mismatch, self.key_along = None, None, float("nan"), None
        self.static_known, self.along_tried, self.along_texture, self.along_seen = False, False, False, None
        self.affine, self.affine_before, self.key_residual = None, None, float("nan")
        self.key_rms, self.key_outline, self.key_with = float("nan"), None, False

    def motion(self, reference: np.ndarray, current: np.ndarray, fit: MemberFit,
               along: np.ndarray | None = None, *, texture: bool = False, texture_first: bool = False,
               tracked: bool = False) -> tuple[np.ndarray, np.ndarray, float, np.ndarray | None, str | None]:
        """The POIs' motion from a member fit, its photometric mismatch, the along-member
        motion it took from elsewhere (None: the fit's own), and what became of the texture's
        along fit (see below): None (not tried, or not converged), "converged" or "taken".

        The outline measures the motion across the member along its long edges; along the
        member it has only the ends of the grown mask, which are no edges where the member
        runs on beyond the mask, and the low-order field extrapolates them over the POIs.
        Given the POIs' along-member motion from elsewhere (``along``: the dense flow's in
        a full measurement, the chain key's in a tracked frame), the POIs also try the
        field's across-member motion with that along-member motion, and take whichever of
        the two matches them better. With ``texture``, the region's own texture's along-member
        motion (a quick translation fit, see ALONG_CLEAR) is taken where the POIs match it
        clearly better than the better of those two; with ``texture_first`` too, wherever it
        converges (a chain whose key took it: its key's along-member motion is a past frame's).
        A ``tracked`` frame's fit starts from the motion the chain's texture readings predict
        (see :attr:`along_seen`) and takes ALONG_ITERATIONS steps at most; a full measurement's
        from the better of the other two, with the fit's full budget; each also from ALONG_HOP_PX
        either side of its start along the member (HOP_ITERATIONS steps at most in a tracked
        frame) and from the farthest hop the POIs' match keeps improving to (see :meth:`_walk`; the
        first start's budget), the best match of them the texture's motion (see
        :meth:`texture_along`). What the POIs could not tell apart
        along the member is left in :attr:`along_ambiguity` (see :meth:`outline_sigma`).
        """
        u, v = self.member.displacement(fit)
        best = (u, v, _mismatch(reference, current, self.cols, self.rows, u, v), None)
        tried = [(best[2], float(np.mean(self.along(u, v))))]  # every along-member motion matched
        if along is not None:
            mixed = self._with_along(reference, current, u, v, along)
            tried.append((mixed[2], float(np.mean(along))))
            if mixed[2] < best[2]:
                best = mixed
        best, state = self.texture_along(reference, current, u, v, best, tried, texture=texture,
                                          texture_first=texture_first, tracked=tracked)
        # What the POIs cannot tell apart along the member: every motion tried that matched them
        # not clearly worse than the one taken (within 1 / ALONG_CLEAR of its mismatch).
        taken = float(np.mean(self.along(best[0], best[1])))
        self.along_ambiguity = max((abs(a - taken) / 2.0 for m, a in tried if m * ALONG_CLEAR <= best[2]),
                                   default=0.0)
        return (*best, state)

    def texture_along(self, reference: np.ndarray, current: np.ndarray, u: np.ndarray, v: np.ndarray,
                       best: tuple, tried: list, *, texture: bool, texture_first: bool,
                       tracked: bool) -> tuple[tuple, str | None]:
        """The better of ``best`` (a motion at the POIs, its mismatch and the along-member motion
        it took from elsewhere) and the region's own texture's along-member motion with the
        across-member motion of ``(u, v)`` (see :meth:`motion`), and what became of that fit
        (None, "converged" or "taken"); every motion fitted or sampled is added to ``tried``."""
        state = None
        if (texture or texture_first) and self.along_fit is not None:
            start_u, start_v = best[0], best[1]
            if tracked and self.along_seen is not None:
                last, before = self.along_seen
                start_u, start_v = self._mix(u, v, last if before is None else 2.0 * last - before)
            start = self.along_fit.params_from_flow(start_u, start_v, self.rows, self.cols)
            starts = [] if start is None else [start]
            walked = []  # the starts a walk along reached (see _walk): fitted as the first is
            at_hop = {}  # the POIs' match at each first hop (the walk's first step), by its index
            if start is not None:
                # A faint paint a codec rebuilt holds its motion along the member in part only:
                # the fit has minima a pixel or so apart (the codec's whole-pixel copies), and
                # the one next to a start the dense flow froze need not be the POIs' best match
                # (whether the chain's frames try the paint is its own start's, as before).
                for sign in (-1.0, 1.0):
                    first = self._hop(start, sign)
                    at_hop[len(starts)] = self._with_fit_along(reference, current, u, v, first)
                    farther = self._walk(reference, current, u, v, start, sign, at_hop[len(starts)][2])
                    starts.append(first)
                    if farther is not None:
                        walked.append(len(starts))
                        starts.append(farther)
            candidate = None
            for index, begin in enumerate(starts):
                hop = index > 0 and index not in walked
                if hop and tracked and not texture_first:
                    # A tracked frame of a chain that does not take the paint's motion samples the
                    # POIs' match at a hop instead of fitting from it (a fit from each cost the
                    # bench's painted bars 10-15 % of their time: their faint paint matches a pixel
                    # along about as well, and is not taken).
                    sampled = at_hop[index]
                    if sampled[2] <= best[2]:
                        # (An unrefined position counts only where it matches at least as well:
                        # a faint paint matches a pixel along nearly as well almost everywhere.)
                        tried.append((sampled[2], float(np.mean(sampled[3]))))
                    continue
                budget = HOP_ITERATIONS if hop else (ALONG_ITERATIONS if tracked else None)
                found = self.along_fit.fit_translation(current, begin, max_iterations=budget)
                if not found.converged and (index not in walked or not np.isfinite(found.rms)):
                    continue
                mixed = self._with_fit_along(reference, current, u, v, found.params)
                own = mixed[3]
                if not found.converged and not mixed[2] < ALONG_CLEAR * best[2]:
                    # A fit over a faint paint closes in on its minimum by a near-constant ratio
                    # of steps and may end its budget short of converging, near the motion: from
                    # a walk's start (a column sliding 12 px along read 0.6 px in one frame, its
                    # fit ending at 10.92 of 10.86), its end counts where the POIs match it clearly
                    # better (from any start, a bar moving across under a changing light took a
                    # wrong along motion: 0.06 -> 0.31 px off).
                    continue
                if index == 0 and found.converged:
                    state = "converged"
                tried.append((mixed[2], float(np.mean(own))))
                if candidate is None or mixed[2] < candidate[2]:
                    candidate = mixed
            if candidate is not None and (texture_first or candidate[2] < ALONG_CLEAR * best[2]):
                best, state = candidate, "taken"
                own = candidate[3]
                self.along_seen = (own, None if self.along_seen is None else self.along_seen[0])
        return best, state

    def _hop(self, start: np.ndarray, sign: float, hops: int = 1) -> np.ndarray:
        """The texture fit's ``start`` moved ``hops`` times ALONG_HOP_PX along the member (``sign``)."""
        t_dir = self.member.axes[:, 0]
        other = start.copy()
        other[0] += sign * hops * ALONG_HOP_PX * t_dir[0]
        other[3] += sign * hops * ALONG_HOP_PX * t_dir[1]
        return other

    def _walk(self, reference: np.ndarray, current: np.ndarray, u: np.ndarray, v: np.ndarray,
              start: np.ndarray, sign: float, first: float) -> np.ndarray | None:
        """The farthest start ALONG_HOP_PX apart along the member (``sign``) beyond the first hop
        (where the POIs' mismatch is ``first``) to which the POIs' match keeps improving from hop
        to hop, up to ALONG_WALK_HOPS hops; None where the second hop matches no better than the
        first (see ALONG_WALK_HOPS)."""
        def matched(hops: int) -> float:
            return self._with_fit_along(reference, current, u, v, self._hop(start, sign, hops))[2]
        hops, last = 1, first
        while hops < ALONG_WALK_HOPS:
            now = matched(hops + 1)
            if not now < last:
                break
            hops, last = hops + 1, now
        return None if hops == 1 else self._hop(start, sign, hops)

    def outline_sigma(self, fit: MemberFit, state: str | None, at_least: float = 0.0) -> _OutlineSigma:
        """An outline reading's own sigma (``fit``'s, see :meth:`MemberEdges.mean_sigma`) with what
        its last :meth:`motion` could not see along the member (see :class:`_OutlineSigma`), no
        less than ``at_least`` (px)."""
        return _OutlineSigma(self.member.mean_sigma(fit), max(self.along_ambiguity, at_least), state == "taken",
                             self.member.mean_sigma(fit, reported=True))

    def _mix(self, u: np.ndarray, v: np.ndarray, along: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The motion ``(u, v)`` across the member with ``along`` along it."""
        n_dir, t_dir = self.member.axes[:, 1], self.member.axes[:, 0]
        across = u * n_dir[0] + v * n_dir[1]
        return across * n_dir[0] + along * t_dir[0], across * n_dir[1] + along * t_dir[1]

    def _with_along(self, reference: np.ndarray, current: np.ndarray, u: np.ndarray, v: np.ndarray,
                    along: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """:meth:`_mix`, its mismatch, and ``along``."""
        mixed_u, mixed_v = self._mix(u, v, along)
        return mixed_u, mixed_v, _mismatch(reference, current, self.cols, self.rows, mixed_u, mixed_v), along

    def _with_fit_along(self, reference: np.ndarray, current: np.ndarray, u: np.ndarray, v: np.ndarray,
                        params: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
        """:meth:`_with_along` of the paint's along fit's along-member motion at ``params``."""
        return self._with_along(reference, current, u, v,
                                self.along(*self.along_fit.field(params, self.rows, self.cols)))

    def along(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """The along-member component of a motion at the POIs."""
        t_dir = self.member.axes[:, 0]
        return u * t_dir[0] + v * t_dir[1]

    def gain(self, current: np.ndarray) -> float | None:
        """The frame's brightness at the POIs relative to the reference's (lighting changes)."""
        gain = float(np.median(current[self.rows, self.cols])) / self.ref_level
        return gain if np.isfinite(gain) and gain > 0 else None

    def texture_fit(self, current: np.ndarray, start: np.ndarray) -> tuple[RegionMotion, bool]:
        """The region's texture fit into ``current`` from ``start``, and whether pixels were left
        out: on a lossy stream those the codec copied from the reference (see
        :func:`~flow.methods.deepflow.codecfloor.codec_copies`), where at least COPY_MIN_KEPT
        of the pixels stay (a region copied nearly whole shows no motion either way)."""
        keep = None
        if self.reference is not None:
            copied = codec_copies(self.reference, current, self.texture.rows, self.texture.cols)
            if copied.any() and np.count_nonzero(~copied) >= COPY_MIN_KEPT * copied.size:
                keep = ~copied
        return self.texture.fit(current, start, keep=keep), keep is not None

    def texture_reading(self, found: RegionMotion) -> tuple[np.ndarray, np.ndarray, tuple[float, float]]:
        u, v = self.texture.field(found.params, self.rows, self.cols)
        return u, v, _TextureSigma(found.sigma_px)

    def reported_sigma(self, sigma: tuple[float, float]) -> tuple[float, float]:
        """The sigma a reading reports: a texture reading's with the codec's error added in
        quadrature (the fit's own sigma does not see an error common to the region, which a
        lossy codec leaves; :func:`flow.methods.deepflow.codecfloor.codec_floor`), measured on
        this region the first time it is needed. Other readings' and lossless frames' as they are."""
        if isinstance(sigma, _OutlineSigma):
            # Along the member: the ambiguity, and the paint's codec floor where the paint's
            # own fit gave the motion there (a codec copies a faint paint's blocks whole:
            # x264 at CRF 18 left a paint of 2 grey levels sliding +-1.5 px along its bar read
            # in whole pixels, 0.3-1.5 px off, where the fit said 0.005 px).
            t = self.member.axes[:, 0]
            extra = sigma.ambiguity
            if sigma.texture and self.codec_crf is not None:
                fx, fy = self._codec_floor(along=True)
                extra = float(np.hypot(extra, np.hypot(t[0] * fx, t[1] * fy)))
            own = sigma.reported
            return (float(np.hypot(own[0], t[0] * extra)), float(np.hypot(own[1], t[1] * extra)))
        if not isinstance(sigma, _TextureSigma) or self.codec_crf is None:
            return tuple(sigma)
        return tuple(float(np.hypot(s, f)) for s, f in zip(sigma, self._codec_floor(), strict=True))

    def _codec_floor(self, *, along: bool = False) -> tuple[float, float]:
        """The region's codec floor (px, x and y) for its texture fit, or (``along``) for the
        paint's quick fit along the member, which is not pre-smoothed (see CODEC_PRESMOOTH_PX):
        each measured the first time it is needed."""
        found = self.along_floor_px if along else self.codec_floor_px
        if found is None:
            floor = codec_floor(self.reference, self.rows, self.cols, self.codec_crf,
                                presmooth_px=0.0 if along else _presmooth(self.codec_crf))
            found = tuple(f if np.isfinite(f) else 0.0 for f in floor)
            if along:
                self.along_floor_px = found
            else:
                self.codec_floor_px = found
        return found


def _clear_of(edges: MemberEdges | None, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Which of the pixels ``rows, cols`` lie more than OUTLINE_CLEAR_PX from every point of the
    member's outline in the reference (all of them where there is no outline)."""
    clear = np.ones(len(rows), bool)
    if edges is None or len(edges.px) == 0:
        return clear
    pad = int(np.ceil(OUTLINE_CLEAR_PX)) + 1
    r0, c0 = int(rows.min()) - pad, int(cols.min()) - pad
    shape = (int(rows.max()) + pad + 1 - r0, int(cols.max()) + pad + 1 - c0)
    at_r = np.rint(edges.py).astype(np.intp) - r0
    at_c = np.rint(edges.px).astype(np.intp) - c0
    near = (at_r >= 0) & (at_r < shape[0]) & (at_c >= 0) & (at_c < shape[1])
    if not near.any():
        return clear
    free = np.ones(shape, bool)
    free[at_r[near], at_c[near]] = False
    distance = ndimage.distance_transform_edt(free)
    return distance[rows - r0, cols - c0] > OUTLINE_CLEAR_PX


def _along_moves(along: np.ndarray | None, sigma: tuple[float, float]) -> bool:
    """Whether an outline's along-member motion, taken from the dense flow (``along``; None:
    the outline's own), is more than its own uncertainty (``sigma``, px on x and y).

    The next frames of its chain have no dense flow to take theirs from, and the key's would
    read the key's motion again (DIC Challenge Sample 14's L3 and L5 read L1's field so, RMSE
    0.09 px): on a strong texture, whose dense flow reads the along-member motion, they are
    measured in full. On a faint one (the bench's painted bars) the dense flow's along-member
    motion is no better read in one frame than in the next: measuring them in full there read
    the bench's bend 0.0390 px RMS instead of 0.0384 (compressed 0.1907 for 0.1901), and the
    key's is kept."""
    return along is not None and abs(float(np.mean(along))) > max(sigma)


def _deforms(region: _Region, dense_u: np.ndarray, dense_v: np.ndarray, *, lossless: bool) -> bool:
    """Whether the dense flow shows the region deforming beyond what an affine field (the
    texture fit's, and the outline's low-order one) can hold: its departure from its own affine
    fit, smoothed over :data:`flow.methods.deepflow.regionfit.DEFORM_SCALE_PX`, more than
    :data:`DEFORM_RATIO` times the departure's pixel-scale rest (see
    :func:`flow.methods.deepflow.regionfit.affine_departure`) plus the floor of ``lossless``
    frames or a codec's."""
    found = affine_departure(region.rows, region.cols, dense_u, dense_v)
    floor = DEFORM_FLOOR_PX if lossless else DEFORM_CODEC_FLOOR_PX
    return found is not None and found[0] > DEFORM_RATIO * found[1] + floor


def _sides_beyond(flow: np.ndarray, region: _Region) -> tuple | None:
    """What the dense ``flow`` shows beyond the region's outline: ``(motion, moved, out_x, out_y,
    sides)``, the member's median motion at its outline and its size, the points read beyond each
    profile, and for each side of the member with profiles enough to vote, which vote and the
    median motion beyond them; None where the member's motion is too small to tell (see
    :func:`_outline_motion`)."""
    member = region.member
    height, width = flow.shape[:2]
    at_profiles = flow[region.prior_rows, region.prior_cols].astype(np.float64)
    found = _outline_motion(at_profiles)
    if found is None:
        return None
    finite, motion, moved = found
    out_x, out_y, votes, hidden = _beyond(member, at_profiles, finite, moved, (height, width))
    outside = flow[np.clip(out_y, 0, height - 1).astype(np.intp),
                   np.clip(out_x, 0, width - 1).astype(np.intp)].astype(np.float64)
    votes &= np.all(np.isfinite(outside), axis=1)
    sides = [(voting, np.median(outside[voting], axis=0)) for voting in
             (_voting(votes, hidden, finite, member.side == side) for side in (-1, 1)) if voting is not None]
    return motion, moved, out_x, out_y, sides


def _background_static(flow: np.ndarray, region: _Region, reference: np.ndarray | None = None,
                       current: np.ndarray | None = None, *, beyond: tuple | None = None) -> bool | None:
    """Whether the dense ``flow`` shows the background beyond the region's outline, on each
    side of the member, either standing still or moving with the member while the member
    moves, or its pixels show it moving on its own (see OWN_ACROSS; True too: an outline
    between two layers either way) (None where the member's motion is too small to tell, or no side has profiles
    enough to vote); False where a side's background moves part of the way. Given the
    ``reference`` and ``current`` frames, a side whose flow says part of the way is still or
    moving with the member where its pixels clearly show it (see :func:`_background_seen`).
    ``beyond``: :func:`_sides_beyond`'s, where the caller has it already."""
    found = _sides_beyond(flow, region) if beyond is None else beyond
    if found is None:
        return None
    motion, moved, out_x, out_y, sides = found
    member = region.member
    height, width = flow.shape[:2]
    verdicts = []
    for voting, median in sides:
        verdict = _stands_still(median, moved) or _moves_with(median, motion, moved)
        if not verdict and reference is not None and current is not None:
            verdict = _background_seen(reference, current, out_x[voting], out_y[voting], motion,
                                       region.gain(current))
            if not verdict:
                band = np.arange(OWN_BAND_PX + 1)[None, :] * member.side[voting, None]
                band_x = out_x[voting, None] + np.where(member.vertical[voting, None], 0, band)
                band_y = out_y[voting, None] + np.where(member.vertical[voting, None], band, 0)
                inside = (band_x >= 1) & (band_x < width - 1) & (band_y >= 1) & (band_y < height - 1)
                verdict = _background_own(reference, current, band_x[inside], band_y[inside], motion,
                                          median, region.gain(current))
        verdicts.append(verdict)
    return all(verdicts) if verdicts else None


def _stands_still(beyond: np.ndarray, moved: float) -> bool:
    """Whether the dense flow's median motion ``beyond`` an outline stands still (within
    STATIC_RATIO of the member's motion ``moved``, px, plus the slack)."""
    return float(np.hypot(*beyond)) <= STATIC_RATIO * moved + STATIC_SLACK_PX


def _moves_with(beyond: np.ndarray, motion: np.ndarray, moved: float) -> bool:
    """Whether the dense flow's median motion ``beyond`` an outline moves with the member's
    ``motion`` (within WITH_RATIO of its size ``moved``, px, plus the slack)."""
    return float(np.hypot(*(beyond - motion))) <= WITH_RATIO * moved + STATIC_SLACK_PX


def _background_with(found: tuple | None, region: _Region, reference: np.ndarray, current: np.ndarray) -> bool:
    """Whether the dense flow (``found``: :func:`_sides_beyond`'s) shows the background beyond the
    region's outline moving with the member on every side that votes, none of them standing still,
    and the pixels beyond most of the voting profiles (WITH_SHOWN_SHARE) show it: over the
    profiles' reach from the outline located in the reference (WITH_BAND_PX, the nearer end moved
    out by the member's motion), the two predictions of them (standing still, moved with the
    member) differ by WITH_EVIDENCE and the moved one fits them WITH_SEEN_RATIO times better. The
    dense flow over a flat sky beside a member is dragged with it (and the codec drags the sky's
    blocks too): see WHOLE."""
    if found is None:
        return False
    motion, moved, _, _, sides = found
    member = region.member
    height, width = reference.shape
    # Clear of the outline's blur and of what the member's motion moved over (or uncovered).
    steps = np.arange(WITH_BAND_PX[0] + int(np.ceil(moved)), WITH_BAND_PX[1] + 1)[None, :]
    shown = total = 0
    for voting, beyond in sides:
        if _stands_still(beyond, moved) or not _moves_with(beyond, motion, moved):
            return False
        vertical, edge = member.vertical[voting, None], member.ref.edge[voting, None]
        band = steps * member.side[voting, None]
        xs = np.rint(np.where(vertical, member.px[voting, None], edge + band))
        ys = np.rint(np.where(vertical, edge + band, member.py[voting, None]))
        inside = np.isfinite(xs) & np.isfinite(ys) & (xs >= 1) & (xs < width - 1) & (ys >= 1) & (ys < height - 1)
        seen, still, moving = _predicted(reference, current, np.where(inside, xs, 1), np.where(inside, ys, 1),
                                         motion, region.gain(current))
        ok = inside & np.isfinite(moving)
        moving = np.where(ok, moving, still)
        differ = np.sum(np.where(ok, (still - moving) ** 2, 0.0), axis=1)
        shows = ((differ >= WITH_EVIDENCE * np.count_nonzero(ok, axis=1)) & (np.count_nonzero(ok, axis=1) >= 3)
                 & (np.sum(np.where(ok, (seen - moving) ** 2, 0.0), axis=1)
                    <= WITH_SEEN_RATIO * np.sum(np.where(ok, (seen - still) ** 2, 0.0), axis=1)))
        shown, total = shown + int(np.count_nonzero(shows)), total + shows.size
    return total > 0 and shown >= WITH_SHOWN_SHARE * total


def _outline_motion(at_profiles: np.ndarray) -> tuple[np.ndarray, np.ndarray, float] | None:
    """The member's motion at its outline profiles (``at_profiles``, (N, 2) px): which are
    known, their median motion and its size; None where fewer than 3 are known or the motion
    is below STATIC_MIN_MOTION_PX (too small to tell a background's motion by)."""
    finite = np.all(np.isfinite(at_profiles), axis=1)
    if finite.sum() < 3:
        return None
    motion = np.median(at_profiles[finite], axis=0)
    moved = float(np.hypot(*motion))
    return None if moved < STATIC_MIN_MOTION_PX else (finite, motion, moved)


def _voting(votes: np.ndarray, hidden: np.ndarray, finite: np.ndarray, on_side: np.ndarray) -> np.ndarray | None:
    """The profiles of one side (``on_side``) whose background samples vote; None where fewer
    than 3 do or more than HIDDEN_SHARE of the side's known profiles are hidden (see
    :func:`_beyond`): the side does not vote."""
    voting = votes & on_side
    if voting.sum() < 3 or hidden[on_side].sum() > HIDDEN_SHARE * finite[on_side].sum():
        return None
    return voting


def _beyond(member: MemberEdges, at_profiles: np.ndarray, finite: np.ndarray, moved: float,
            shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The background samples beyond a member's outline profiles whose motion is ``at_profiles``
    (``finite`` where known; ``moved`` px their median's size): their columns and rows (at
    BACKGROUND_OFFSET_PX plus BACKGROUND_DRAG times the motion), which may vote (in the frame,
    not hidden), and which are hidden by the member's advance.

    Where the member advanced over the background by about the sample's distance or more, the
    reference's background there is hidden in the frame and its flow is the member's or none
    (a bar swinging 35 px, at 25-31 px: its leading side read as background moving, and the
    dense flow, 0.5-0.7 px short, was taken instead of the outline): such profiles do not vote,
    and a side with more than HIDDEN_SHARE of them does not (its other profiles are those the
    dense flow read short: the workbench's beam moving 8-9 px, 0.6-0.8 of its motion)."""
    height, width = shape
    distance = BACKGROUND_OFFSET_PX + BACKGROUND_DRAG * moved
    offset = distance * member.side
    out_x = np.rint(np.where(member.vertical, member.px, member.px + offset))
    out_y = np.rint(np.where(member.vertical, member.py + offset, member.py))
    inside_frame = (out_x >= 0) & (out_x < width) & (out_y >= 0) & (out_y < height)
    advance = member.side * np.where(member.vertical, at_profiles[:, 1], at_profiles[:, 0])
    hidden = finite & (advance + HIDDEN_MARGIN_PX >= distance)
    return out_x, out_y, finite & ~hidden & inside_frame, hidden


def _background_clear(region: _Region, reference: np.ndarray, current: np.ndarray,
                      at_profiles: np.ndarray) -> bool:
    """Whether a tracked frame's pixels beyond the outline clearly show the background standing
    still or moving with the member (see :func:`_background_seen`) on every side that can vote,
    the member's motion at its profiles ``at_profiles`` being the outline fit's: a key too
    still to show it is then known to have such a background without the frame's dense flow.
    False where a side cannot tell (the frame is then measured in full, its dense flow asked)."""
    member = region.member
    found = _outline_motion(at_profiles)
    if found is None:
        return False  # too few profiles, or too little motion at the outline to tell, as in a full measurement
    finite, motion, moved = found
    out_x, out_y, votes, hidden = _beyond(member, at_profiles, finite, moved, reference.shape[:2])
    sides = 0
    # Each of the four sides on its own: the background beyond a bar's long sides may stand still
    # where beyond its ends (the mask's, not the member's) the bar goes on, moving with itself.
    for side in (-1, 1):
        for vertical in (False, True):
            voting = _voting(votes, hidden, finite, (member.side == side) & (member.vertical == vertical))
            if voting is None:
                continue
            if not _background_seen(reference, current, out_x[voting], out_y[voting], motion,
                                    region.gain(current)):
                return False
            sides += 1
    return sides > 0


def _background_seen(reference: np.ndarray, current: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                     motion: np.ndarray, gain: float | None) -> bool:
    """Whether the pixels ``xs``, ``ys`` beyond an outline, where the dense flow says the
    background moves part of the way, clearly show it standing still or moved with the member
    (by ``motion``): the one prediction of them from the reference (its pixels where they are,
    or where the member's motion brought them from) fits them within 1/CLEAR_RATIO of the
    difference between the two predictions, and within SEEN_RATIO of the other's misfit.

    The dense flow over a background of little texture beside a member is the smoothing's
    interpolation, not a measurement: the workbench's beam, whose logo plate behind it moves with
    it, read 0.75-0.95 of the way in a frame solved around a background mask, where the pixels
    matched the plate moving with the beam (misfit 0.02-0.07 of the predictions' difference,
    the misfit of standing still about that difference), and its outline was refused in 3 of 4
    frames. A shaded round column's limb is no such edge: its pixels fit neither (0.3-0.6),
    and its outline stays refused (it read 0.12 px RMS there, the dense flow 0.05)."""
    found = _predictions(reference, current, xs, ys, motion, gain)
    if found is None:
        return False
    seen, still, moving = found
    return _clearly(seen, still, moving) or _clearly(seen, moving, still)


def _predictions(reference: np.ndarray, current: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                 motion: np.ndarray, gain: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The pixels ``xs``, ``ys`` of ``current`` and their two predictions from the reference (see
    :func:`_background_seen`): ``(seen, still, moving)``; None where fewer than 3 have both."""
    seen, still, moving = _predicted(reference, current, xs, ys, motion, gain)
    ok = np.isfinite(moving)
    if ok.sum() < 3:
        return None
    return seen[ok], still[ok], moving[ok]


def _predicted(reference: np.ndarray, current: np.ndarray, xs: np.ndarray, ys: np.ndarray,
               motion: np.ndarray, gain: float | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels ``xs``, ``ys`` (any shape) of ``current``, the reference's there (standing still)
    and where the member's ``motion`` brought them from (NaN where that leaves the frame), both
    scaled by the frame's ``gain``."""
    scale = 1.0 if gain is None else gain
    cols, rows = xs.astype(np.intp), ys.astype(np.intp)
    still = scale * reference[rows, cols].astype(np.float64)
    moving = scale * sample(reference, np.ravel(xs - motion[0]), np.ravel(ys - motion[1])).astype(np.float64)
    return current[rows, cols].astype(np.float64), still, moving.reshape(np.shape(xs))


def _background_own(reference: np.ndarray, current: np.ndarray, xs: np.ndarray, ys: np.ndarray,
                    motion: np.ndarray, start: np.ndarray, gain: float | None) -> bool:
    """Whether the pixels ``xs``, ``ys`` beyond an outline clearly show the background moving
    on its own (see OWN_ACROSS): the reference moved by a translation fitted to them (Gauss-Newton
    from ``start``, the dense flow's motion there) fits them clearly better (see :func:`_clearly`)
    than it standing still or moved with the member (by ``motion``)."""
    if xs.size < 8:
        return False
    scale = 1.0 if gain is None else gain
    seen = current[ys.astype(np.intp), xs.astype(np.intp)].astype(np.float64)
    d = np.asarray(start, np.float64).copy()
    for _ in range(OWN_STEPS):
        moved = scale * sample(reference, xs - d[0], ys - d[1]).astype(np.float64)
        gx = 0.5 * scale * (sample(reference, xs - d[0] + 1, ys - d[1]) - sample(reference, xs - d[0] - 1, ys - d[1]))
        gy = 0.5 * scale * (sample(reference, xs - d[0], ys - d[1] + 1) - sample(reference, xs - d[0], ys - d[1] - 1))
        ok = np.isfinite(moved) & np.isfinite(gx) & np.isfinite(gy)
        if ok.sum() < 8:
            return False
        jac = -np.column_stack([gx[ok], gy[ok]]).astype(np.float64)  # d(moved)/d(d)
        hessian = jac.T @ jac
        if np.linalg.cond(hessian) > 1e6:
            return False  # a background without texture in both directions cannot show it
        d = d + np.linalg.solve(hessian, jac.T @ (seen[ok] - moved[ok]))
    if not _not_a_drag(d, motion):
        return False
    still = scale * reference[ys.astype(np.intp), xs.astype(np.intp)].astype(np.float64)
    with_member = scale * sample(reference, xs - motion[0], ys - motion[1]).astype(np.float64)
    own = scale * sample(reference, xs - d[0], ys - d[1]).astype(np.float64)
    ok = np.isfinite(with_member) & np.isfinite(own)
    return (ok.sum() >= 8 and _clearly(seen[ok], own[ok], still[ok])
            and _clearly(seen[ok], own[ok], with_member[ok]))


def _not_a_drag(beyond: np.ndarray, motion: np.ndarray) -> bool:
    """Whether a background motion ``beyond`` (u, v) is no fraction of the member's ``motion``
    the dense flow's smoothing could have dragged it (see OWN_ACROSS)."""
    size = float(np.hypot(*motion))
    if size <= 0:
        return False
    unit = np.asarray(motion, np.float64) / size
    along = float(beyond @ unit)
    across = abs(float(beyond[0] * unit[1] - beyond[1] * unit[0]))
    return (across > OWN_ACROSS * size + STATIC_SLACK_PX or along < -STATIC_SLACK_PX
            or along > size + STATIC_SLACK_PX)


def _clearly(seen: np.ndarray, this: np.ndarray, other: np.ndarray) -> bool:
    """Whether the pixels ``seen`` clearly show the prediction ``this`` rather than ``other``:
    its misfit within 1/CLEAR_RATIO of the two predictions' difference and within SEEN_RATIO of
    the other's misfit."""
    misfit = float(np.sum((seen - this) ** 2))
    return (CLEAR_RATIO * misfit <= float(np.sum((this - other) ** 2))
            and misfit <= SEEN_RATIO * float(np.sum((seen - other) ** 2)))


def _presmooth(codec_crf: float | None) -> float:
    """The texture fits' pre-smoothing (px): CODEC_PRESMOOTH_PX on a lossy stream (``codec_crf``
    given), none on lossless frames."""
    return 0.0 if codec_crf is None else CODEC_PRESMOOTH_PX


def _background_texture(reference: np.ndarray, read: np.ndarray | None, *,
                        bias_correction: bool, codec_crf: float | None = None) -> RegionFit | None:
    """The texture fit of the background points the driver reads (camera-motion compensation),
    where they have a texture strong enough to be taken (see MIN_TEXTURE_GRADIENT); else None
    (their dense flow is read).

    A wall's or the ground's texture moves rigidly with the camera: one affine correlation
    subset over it reads that motion to hundredths of a pixel, where the dense flow's smoothness
    and its coarse-to-fine steps leave a few percent (the workbench's tripod shake: 8 % short)."""
    if read is None or np.shape(read) != reference.shape:
        return None
    rows, cols = np.nonzero(read)
    if rows.size < 8:
        return None
    # (The sub-pixel bias correction, on lossless frames, resamples the points' bounding box
    # once: for points spread around a member, most of the frame.)
    fit = RegionFit(reference, rows, cols, bias_correction=bias_correction, presmooth_px=_presmooth(codec_crf),
                    rounding_floor=codec_crf is None)
    if not fit.textured or min(fit.gradient_rms) < MIN_TEXTURE_GRADIENT:
        return None
    return fit


def _poi_motion(flow: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> float:
    """The POIs' median motion (px; NaN where none is finite)."""
    motion = np.hypot(flow[rows, cols, 0], flow[rows, cols, 1])
    motion = motion[np.isfinite(motion)]
    return float(np.median(motion)) if motion.size else float("nan")


def _in_band(value: float, key: float) -> bool:
    """A tracked frame's mismatch (or residual) within its chain key's band."""
    return key / WARM_RATIO - MATCH_SLACK <= value <= key * WARM_RATIO + MATCH_SLACK


@register("deepflow")
class DeepFlow(DenseMethod):
    """DeepFlow: DeepMatching matches blended into a variational energy, then each region's
    motion refined from what its images support: its texture, or its outline.

    The dense flow (DeepMatching + DeepFlow) covers the POIs' window (see ``crop``) and starts
    two refinements of every region of the mask, each with its own assumptions:

    * *texture* (:mod:`flow.methods.deepflow.regionfit`): the region as one image-correlation subset, an
      affine warp (translation, rotation, stretch, shear) with gain and offset fitted to all
      of its pixels; it needs texture inside the mask and nothing else;
    * *outline* (:mod:`flow.methods.deepflow.member`): the member's edges against a background that stands
      still; it needs a straight-edged member in front of a static background and nothing
      inside the mask.

    Each region takes (:func:`_choose`) its texture where the texture is strong
    (:data:`MIN_TEXTURE_GRADIENT`) and fixes the motion (:data:`TEXTURE_ENOUGH_PX`); else
    its outline, where the dense flow shows the background beyond it standing still or moving
    with the member (not dragged part of the way) while the member moves
    (:func:`_background_static`; seen so, not only not seen dragged, where the texture is
    strong and the outline no more precise than it) and the outline matches the POIs no worse
    than the dense flow; else a strong texture however imprecise; else, where the outline was
    refused as too imprecise, a fainter texture's fit that resolves the motion on both axes and
    matches the POIs no worse than the dense flow (:data:`FAINT_TEXTURE_MAX_SIGMA_PX`); else the
    dense flow. A strong texture's region whose dense flow deforms beyond any affine field
    (:func:`_deforms`: a sine, a wave) takes the dense flow whatever the models say.
    Through a video the driver hands the frames over in chains (see ``warm``): a chain's
    first frame is measured so, and the rest track each region with the model its key chose,
    from the previous frames' motion, while their photometric mismatch stays in the chain's
    band (on a strong texture, an outline whose along-member motion came from the dense flow
    and is more than its uncertainty is not tracked: its frames are measured in full, see
    :func:`_along_moves`; nor is a fainter texture's reading). The sidecar counts the readings of each model
    (``<model>_readings``) and why each was taken (``why_<reason>``, :data:`REASONS`).

    On a lossy stream (``codec_crf``) a texture reading's sigma also holds the error the codec
    leaves in the region's fit, which the fit's own sigma cannot see (common to the region):
    measured once per region on the reference shifted by known amounts and passed through
    libx264 (:mod:`flow.methods.deepflow.codecfloor`); the sidecar's timings say it
    (``codec_floor_x_px``, ``codec_floor_y_px``) and what it cost (``codec_floor_s``).

    Parameters (keyword-only; defaults follow the papers, see
    :class:`flow.methods.deepflow.deepmatching.MatchParams` and
    :class:`flow.methods.deepflow.variational.VariationalParams`)
    ----------
    preset : {"default", "fast", "large-displacement"}
    member : bool
        Refine the POIs from the member's edges (default True).
    texture : bool
        Refine each region as one affine correlation subset (default True).
    bias_correction : bool or None
        Take the texture fit's own sub-pixel bias, measured on the reference shifted exactly,
        off its readings (:meth:`flow.methods.deepflow.regionfit.RegionFit.bias_curve`). None (default): on for
        frames given as arrays; ``refflow track`` makes it on for lossless input (image folders
        of TIFF/PNG/BMP/PGM, camera files, FFV1 and other lossless video) and off for a lossy
        codec's, whose own interpolation the correction does not know.
    codec_crf : float or None
        The H.264 quality (crf, 0..51) of a lossy stream: a texture reading's sigma gets the
        codec's error measured at it (see above). None (default): none added; ``refflow track``
        takes it from a lossy stream's x264 settings (``DEFAULT_CRF`` of
        :mod:`flow.pipeline` where the encoder did not write them) and leaves it None for
        lossless input.
    warm : bool
        Track each region from frame to frame within a chain of :data:`CHAIN_LENGTH` frames,
        verified by the photometric mismatch (default True; False: every frame measured in
        full). With background points to read, every frame is measured in full.
    crop : bool
        Solve the dense flow only around the pixels that are read (default True): the POIs'
        and background points' bounding box plus a margin that holds the matching's reach
        (which follows the member's motion, :data:`BASE_REACH_PX`; or ``ngh_rad``), the
        pyramid's settling (:data:`flow.methods.base.CROP_MARGIN_PX`) and the member's
        reference analysis; the flow elsewhere is NaN. Without :meth:`bind` the whole frame is
        solved, with the frame's reach (:func:`flow.methods.deepflow.deepmatching.search_radius`).
    downscale, ngh_rad, max_patch, ... : matching parameters
    alpha, beta, delta, gamma, kappa, sigma, eta, n_outer, n_sor, omega, ... :
        variational parameters; ``beta = 0`` switches the matching term (and
        the matching itself) off.
    """

    summary = ("DeepMatching + DeepFlow (clean-room, numba), each region refined from its texture "
               "(affine correlation) or its outline, whichever the images support (default)")
    member_default = True
    texture_default = True
    parameters = (
        Param("preset", "choice", "default", "settings the other parameters start from", choices=tuple(PRESETS)),
        Param("member", "bool", True, "refine the POIs from the member's edges", optional=True,
              none_means="the method's default"),
        Param("texture", "bool", True, "refine each region as one affine correlation subset",
              optional=True, none_means="the method's default"),
        Param("warm", "bool", True, "track each region frame to frame within a chain"),
        Param("bias_correction", "bool", None, "take the texture fit's own sub-pixel bias, measured on the "
              "reference, off its readings", optional=True,
              none_means="on where the frames are lossless (images, camera files, FFV1), off for a lossy codec"),
        Param("codec_crf", "float", None, "the lossy stream's H.264 quality: the texture readings' sigma "
              "gets the error libx264 at this crf leaves in the region's fit", low=0.0, high=51.0,
              optional=True, none_means="no codec floor (frames taken as lossless)"),
        CROP, *declared(MatchParams), *declared(VariationalParams))

    def __init__(self, *, preset: str = "default", member: bool | None = None,
                 texture: bool | None = None, crop: bool = True, warm: bool = True,
                 bias_correction: bool | None = None, codec_crf: float | None = None, **params: Any) -> None:
        merged = _resolve(preset, params)
        self._match, self._var = _split(merged)
        for label, value, optional in (("member", member, True), ("texture", texture, True),
                                       ("warm", warm, False), ("bias_correction", bias_correction, True)):
            if not (isinstance(value, bool) or (optional and value is None)):
                raise ValueError(f"{label} must be true or false, got {value!r}")
        self._member_on = self.member_default if member is None else member
        self._texture_on = self.texture_default if texture is None else texture
        # Frames handed over as arrays are taken as they are (`refflow track` resolves None from
        # the input: lossless or not, see flow.pipeline).
        self._bias_on = True if bias_correction is None else bias_correction
        # Frames the driver hands one instance in order (0: each frame on its own); set by bind.
        self._warm_on = warm
        self.chain_length = 0
        self._chaining = False
        self._warm_flow: np.ndarray | None = None
        # The pixels whose flow a frame's calc gave, not read (see calc): None where none may be.
        self.last_filled: np.ndarray | None = None
        # Frames measured in full and tracked from their predecessor (see CHAIN_LENGTH), the
        # regions' readings by model and why each full measurement chose its model: the driver
        # sums every instance's counts into the sidecar's timings.
        # (``reach_widened``: dense solves done again with a longer reach, see WIDEN_SHARE.)
        self.counts = dict.fromkeys(("full_frames", "warm_frames", "hidden_frames", "outline_readings", "affine_readings",
                                     "dense_readings", "background_texture_readings", "along_texture", "reach_widened",
                                     "outline_every_model", "outline_models_left_out", "codec_copies_left_out", "outline_whole_with",
                                     "texture_light_blocks", "codec_floor_s", "mask_past_outline_px", "rim_filled_frames",
                                     "codec_floor_x_px", "codec_floor_y_px",
                                     *(f"field_window_{w:g}px" for w in (WINDOW_PX, *WIDER_WINDOWS_PX)),
                                     *(f"why_{reason}" for reason in REASONS)), 0)
        # The matching's reach (see BASE_REACH_PX): the chain's POIs' latest motion (px, None:
        # none seen yet), the reach of the latest dense solve (the window it took is
        # ``window_with(_margin(reach))``) and the POIs whose motion decides it (see bind).
        self._motion_px: float | None = None
        self.last_reach_px: float | None = None
        self._poi_rows = self._poi_cols = np.zeros(0, np.intp)
        # Scratch reused from frame to frame: an instance serves one thread at a time.
        self._workspace = Workspace()
        self._regions: list[_Region] = []  # one per region of the mask (see bind)
        self._background: RegionFit | None = None  # the background points' texture (see bind)
        self._read_rows = self._read_cols = np.zeros(0, np.intp)  # and all those points
        self._scene: SceneCheck | None = None  # tells the frames that show nothing (see bind)
        # The last frame showed nothing of the scene (the driver flags it); None: not checked.
        self.last_hidden: bool | None = None
        super().__init__(
            preset=preset, member=self._member_on, texture=self._texture_on, crop=crop, warm=warm,
            bias_correction=bias_correction, codec_crf=codec_crf,
            **dataclasses.asdict(self._match),
            **dataclasses.asdict(self._var)
        )
        self._codec_crf = None if codec_crf is None else float(codec_crf)  # checked against its Param above

    def bind(self, reference: np.ndarray, mask: np.ndarray, *, read: np.ndarray | None = None) -> None:
        super().bind(reference, mask, read=read)
        self._regions = []
        self._chaining = False
        self._warm_flow = None
        # The driver reads chain_length after bind: without a region to track (or with
        # background points, whose flow only the dense solve gives) frames stand alone.
        self.chain_length = 0
        self._motion_px = None
        self._scene = None
        self.last_filled = None
        mask = np.asarray(mask)
        self._poi_rows, self._poi_cols = (np.nonzero(mask) if self._crop_on and mask.shape == reference.shape
                                          else (np.zeros(0, np.intp),) * 2)
        self._background = (_background_texture(reference, read, bias_correction=self._bias_on,
                                                codec_crf=self._codec_crf)
                            if self._texture_on else None)
        self._read_rows, self._read_cols = (np.nonzero(read) if self._background is not None
                                            else (np.zeros(0, np.intp),) * 2)
        if not (self._member_on or self._texture_on) or mask.shape != reference.shape:
            return
        # One member per region of a labelled mask (a bool mask: one region, label 1).
        for label in np.unique(mask[mask != 0]):
            region = mask == label
            if region.sum() < 3:
                self._regions = []
                return
            self._regions.append(_Region.of(reference, region, int(label), member=self._member_on,
                                            texture=self._texture_on, bias_correction=self._bias_on,
                                            codec_crf=self._codec_crf))
        self.counts["mask_past_outline_px"] = max([0] + [r.rim_px for r in self._regions])
        if any(r.rim_rows.size for r in self._regions):
            self.last_filled = np.zeros(reference.shape, bool)
        self._scene = SceneCheck(reference, self._window)
        if self._warm_on and read is None:
            self.chain_length = CHAIN_LENGTH

    def window_margin(self, shape: tuple[int, ...]) -> int | None:
        return _matching_margin(self._match, shape)

    def max_window_margin(self, shape: tuple[int, ...]) -> int | None:
        # The reach may widen up to MAX_REACH_PX; the member's reference analysis reads
        # MEMBER_CONTEXT_PX beyond the mask (a frame cut closer would change its numbers).
        widest = super().max_window_margin(shape)
        if self._crop_on and self._match.ngh_rad is None and self._var.beta > 0:
            widest = _margin(MAX_REACH_PX)
        return None if widest is None else max(widest, MEMBER_CONTEXT_PX)

    def warm_up(self) -> None:
        """Compile the kernels before the first frame (see :func:`compile_kernels`)."""
        compile_kernels()

    def restart(self) -> None:
        """Begin a chain: the next frame gets the full measurement, the following ones (until
        the next restart or bind) may be tracked from their predecessor. Before the first
        restart after a bind every call of :meth:`calc` stands alone."""
        self._chaining = self.chain_length > 1 and bool(self._regions)
        self._motion_px = None
        for region in self._regions:
            region.restart()
            region.last_mean, region.last_step_px = None, 0.0

    def _dense_reaching(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        """The dense flow in the window of a reach that holds the POIs' motion (see
        :data:`BASE_REACH_PX`): from the chain's motion so far, doubled while the motion found
        comes past :data:`WIDEN_SHARE` of it. Unbound, ``crop=false`` or with an explicit
        ``ngh_rad``: one solve, in the bound window (the whole frame's reach where there are
        no POIs to follow)."""
        adaptive = self._match.ngh_rad is None and self._var.beta > 0 and self._poi_rows.size > 0
        if not adaptive or current.shape != self._bound_shape:
            self.last_reach_px = None
            return self._dense(reference, current)
        reach = _reach_for(self._motion_px if self._chaining else None)
        window = self.window_with(_margin(reach))
        cut = window if window is not None else (slice(None), slice(None))
        if np.array_equal(reference[cut], current[cut]):
            # The reference itself (a clip's first frame): its flow is nought, not solved (the
            # solver reads at most 6e-6 px there, at the cost of any full frame's).
            self.last_reach_px = reach
            flow = np.full(current.shape + (2,), np.nan, np.float32)
            flow[cut] = 0.0
            return flow
        while True:
            self.last_reach_px = reach
            flow = self._dense_in(reference, current, self.window_with(_margin(reach)))
            found = _poi_motion(flow, self._poi_rows, self._poi_cols)
            if not (found > WIDEN_SHARE * reach) or reach >= MAX_REACH_PX:
                return flow
            self.counts["reach_widened"] += 1
            reach = min(2.0 * reach, MAX_REACH_PX)

    def _solve(self, reference: np.ndarray, current: np.ndarray, *,
               whole_shape: tuple[int, ...]) -> np.ndarray:
        if self._var.beta > 0:
            match = _match_at(self._match, self.last_reach_px, reference.shape, whole_shape)
            grid = deep_matching(reference, current, match, checkpoint=self.check_stop)
            match_flow, match_weight = densify(grid, reference.shape, nearest=True)
            flow = refine(
                reference,
                current,
                self._var,
                match_flow=match_flow,
                match_weight=match_weight,
                workspace=self._workspace,
                checkpoint=self.check_stop,
            )
        else:
            flow = refine(reference, current, self._var, workspace=self._workspace, checkpoint=self.check_stop)
        if self._workspace.nbytes() > WORKSPACE_KEEP_BYTES:
            # A window this large (a whole 4K frame: 2 GB) keeps no scratch between solves: the
            # regions' fits that follow (a deforming region's windowed step: 1.7 GB) would add
            # to it, and faulting it in again costs a few per cent of such a solve.
            self._workspace = Workspace()
        return flow

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        check_pair(reference, current)
        regions = self._regions if current.shape == self._bound_shape else []
        self.last_sigmas_px = {}
        self.last_sigmas_hold_reference = set()
        self.last_field_sigma = None  # set where a region is read pixel by pixel (see _full)
        if self.last_filled is not None:
            self.last_filled[...] = False
        # None where the frame is not checked (no region refined: deepflow-dense).
        self.last_hidden = None if not regions or self._scene is None else False
        if self.last_hidden is not None and self._scene.hidden(current):
            # Nothing of the scene in view (see flow.methods.deepflow.hidden): the dense flow
            # at a quarter of the resolution, kept (and flagged downstream) like any reading;
            # the chains go on from the frames before it.
            self.counts["hidden_frames"] += 1
            self.last_hidden = True
            return self._glimpse(reference, current)
        # Each region on its own: tracked from its previous frames where it may be, measured
        # in full otherwise; the dense flow is solved when any region needs it.
        tracked = [self._track(reference, current, r) if self._chaining and r.model is not None else None
                   for r in regions]
        if regions and all(t is not None for t in tracked):
            self.counts["warm_frames"] += 1
            if self._warm_flow is None or self._warm_flow.shape[:2] != current.shape:
                self._warm_flow = np.full(current.shape + (2,), np.nan, np.float32)
            flow = self._warm_flow
        else:
            self.counts["full_frames"] += 1
            flow = self._dense_reaching(reference, current)
        # The camera's motion first (from the background points, where given): the outline
        # model takes the reference's background where the camera brought it from.
        camera = None
        if self._background is not None and current.shape == self._bound_shape:
            camera = self._read_background(current, flow)
        rims = []  # written once every region is read (a region's background check reads the flow beyond it)
        for region, warm in zip(regions, tracked, strict=True):
            self.check_stop()
            found = warm if warm is not None else self._full(reference, current, flow, region,
                                                             camera=self._camera_at(camera, region))
            if found is not None:
                u, v, sigma = found
                self.last_sigmas_px[region.label] = self._reported_sigma(region, sigma)
                if isinstance(sigma, _TextureSigma):
                    # Its fit's residuals compare the frame with the reference, and its codec
                    # floor is measured against the decoded reference: the reference's own
                    # error is in it already (see with_reference_term).
                    self.last_sigmas_hold_reference.add(region.label)
                elif isinstance(sigma, _OutlineSigma) and len(region.member.models) <= len(BLURS):
                    # Read without the blur models that cannot draw the reference's outlines
                    # (a soft reference: the lens out of focus; see MemberEdges._plausible_models).
                    self.counts["outline_models_left_out"] += 1
                flow[region.rows, region.cols, 0] = u
                flow[region.rows, region.cols, 1] = v
            if region.rim_rows.size and found is not None and region.read_by == "outline":
                # The mask's pixels beyond the member's outline: the member's mean motion (the
                # dense flow there is the still background's, dragged near the outline). Where
                # the outline did not read the frame, their own flow: what lies beyond was not
                # seen standing still, and eq. (10)-(12) judge those pixels as any others.
                rims.append((region, float(np.mean(u)), float(np.mean(v))))
        for region, mean_u, mean_v in rims:
            flow[region.rim_rows, region.rim_cols, 0] = mean_u
            flow[region.rim_rows, region.rim_cols, 1] = mean_v
            # (Given, not read: the driver leaves them out of the frame's photometric residual,
            # where the still wall moved by the member's motion would look like an occluder.)
            self.last_filled[region.rim_rows, region.rim_cols] = True
        self.counts["rim_filled_frames"] += bool(rims)
        if self._chaining:
            self._motion_px = _poi_motion(flow, self._poi_rows, self._poi_cols)
            for region in regions:
                block = flow[region.rows, region.cols]
                read = np.isfinite(block).all(axis=1)
                if not read.any():
                    continue
                mean = (float(block[read, 0].mean()), float(block[read, 1].mean()))
                if region.last_mean is not None:
                    region.last_step_px = float(np.hypot(mean[0] - region.last_mean[0], mean[1] - region.last_mean[1]))
                region.last_mean = mean
        return flow

    def _glimpse(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        """The dense flow of a frame that shows nothing of the scene (an occluder's, see
        :mod:`flow.methods.deepflow.hidden`), solved in the base window at 1/:data:`GLIMPSE_SCALE`
        of the resolution (a sixteenth of the cost) and without the regions' refinements: a
        reading of what is in view all the same, kept and flagged by the driver (see
        :attr:`last_hidden`). A frame misjudged hidden would read its
        window's coarse motion: on the bench's painted bar (visible frames glimpsed on purpose)
        0.03-1.5 px off the full measurement, the wall's texture outweighing the bar's at that
        scale (at 1/8, 1.5 ms a frame instead of 13 ms, up to 5.5 px off)."""
        window = self._window if self._window is not None else (slice(None), slice(None))
        ref, cur = reference[window], current[window]
        height, width = ref.shape
        scale = GLIMPSE_SCALE
        # A narrow window (or a coarse matching): a finer glimpse; the matching needs its atoms.
        shortest = max(GLIMPSE_MIN_PX, 2 * ATOMIC * self._match.downscale if self._var.beta > 0 else 0)
        while scale > 1 and min(height, width) < shortest * scale:
            scale //= 2
        if scale == 1:
            self.last_reach_px = BASE_REACH_PX
            return self._dense_in(reference, current, self._window)
        size = (width // scale, height // scale)
        small_ref = cv2.resize(ref, size, interpolation=cv2.INTER_AREA)
        small_cur = cv2.resize(cur, size, interpolation=cv2.INTER_AREA)
        self.last_reach_px = BASE_REACH_PX / scale
        small = self._solve(small_ref, small_cur, whole_shape=small_ref.shape)
        flow = np.full(reference.shape + (2,), np.nan, np.float32)
        flow[window] = cv2.resize(small, (width, height), interpolation=cv2.INTER_LINEAR) * np.float32(
            [width / size[0], height / size[1]])
        return flow

    def _read_background(self, current: np.ndarray, flow: np.ndarray) -> np.ndarray | None:
        """The background points' motion from their texture: one affine correlation subset over
        all of them, started from the dense flow there, written over the dense flow at those
        points (the driver fits the camera's motion to them); its affine parameters returned.
        Where the fit fails the dense flow stays (None)."""
        fit = self._background
        u, v = flow[fit.rows, fit.cols, 0], flow[fit.rows, fit.cols, 1]
        start = fit.params_from_flow(u, v, fit.rows, fit.cols)
        found = None if start is None else fit.fit(current, start)
        if found is None or not (found.converged and all(np.isfinite(found.sigma_px))):
            return None
        u, v = fit.field(found.params, self._read_rows, self._read_cols)
        flow[self._read_rows, self._read_cols, 0] = u
        flow[self._read_rows, self._read_cols, 1] = v
        self.counts["background_texture_readings"] += 1
        return found.params

    def _camera_at(self, camera: np.ndarray | None, region: _Region) -> np.ndarray | None:
        """The camera's image motion (u, v) px at a region's centroid from the background's
        affine parameters ``camera`` (None: not known)."""
        if camera is None:
            return None
        u, v = self._background.field(camera, np.array([region.rows.mean()]), np.array([region.cols.mean()]))
        return np.array([u[0], v[0]])

    def _reported_sigma(self, region: _Region, sigma: tuple[float, float], *,
                        reading: bool = True) -> tuple[float, float]:
        """A region's reported sigma (see :meth:`_Region.reported_sigma`); the time measuring
        its codec floor took goes to the counts (the sidecar's timings), and the floor itself
        where the sigma is that of a texture ``reading`` reported (not only compared, see
        :meth:`_outline_sharper`)."""
        measured = (region.codec_floor_px, region.along_floor_px)
        started = time.perf_counter()
        reported = region.reported_sigma(sigma)
        if measured != (region.codec_floor_px, region.along_floor_px):
            self.counts["codec_floor_s"] += time.perf_counter() - started
        if reading and isinstance(sigma, _TextureSigma) and region.codec_floor_px is not None:
            for axis, floor in zip("xy", region.codec_floor_px, strict=True):
                self.counts[f"codec_floor_{axis}_px"] = max(self.counts[f"codec_floor_{axis}_px"], floor)
        return reported

    def _texture_fit(self, region: _Region, current: np.ndarray, start: np.ndarray) -> RegionMotion:
        """:meth:`_Region.texture_fit`, counting the fits that left a codec's copies out and those
        read block by block under a light that changed across the region."""
        found, left_out = region.texture_fit(current, start)
        if left_out:
            self.counts["codec_copies_left_out"] += 1
        # The light changed across the region: fitted with each block's own gain (see regionfit).
        self.counts["texture_light_blocks"] += found.light_varies
        return found

    def _copied_profiles(self, region: _Region, reference: np.ndarray, current: np.ndarray, *,
                         count: bool = True) -> tuple[np.ndarray | None, bool]:
        """Which of the member's outline profiles a codec copied from the reference (see
        :func:`~flow.methods.deepflow.codecfloor.codec_copies`: their outline pixel) on a lossy
        stream, to be left out of the fit where enough for one stay (None: none left out), and
        whether more than COPY_OUTLINE_MAX of them were copied (the frame is not the reference
        itself): the codec froze the member's edges, or the member moved along them only, which
        shows the same; the outline is then not read where a strong texture's fit (the copies
        left out) reads the motion instead."""
        member = region.member
        if self._bias_on or member is None or member.n_profiles == 0:
            return None, False
        height, width = reference.shape
        rows = np.clip(np.rint(member.py).astype(np.intp), 0, height - 1)
        cols = np.clip(np.rint(member.px).astype(np.intp), 0, width - 1)
        copied = codec_copies(reference, current, rows, cols)
        if not copied.any() or copied.all():
            return None, False
        share = float(np.mean(copied))
        frozen = share > (FROZEN_TEXTURE_COPIED if self._texture_reads_frozen(region) else COPY_OUTLINE_MAX)
        if share > COPY_OUTLINE_MAX or np.count_nonzero(~copied) < member.params.min_profiles:
            return None, frozen
        self.counts["codec_copies_left_out"] += count
        return copied, frozen

    def _band_texture(self, region: _Region) -> bool:
        """Whether the region's texture, just short of strong (at least FROZEN_TEXTURE_GRADIENT) on
        a lossy stream, is read where the codec froze the outline (see _texture_reads_frozen)."""
        return not region.strong_texture and self._texture_reads_frozen(region)

    def _texture_reads_frozen(self, region: _Region) -> bool:
        """Whether the region's texture, at least FROZEN_TEXTURE_GRADIENT on a lossy stream, reads
        the motion where the codec froze the outline: where the codec leaves its reading precise
        (its codec floor, measured the first time it is needed, within FROZEN_TEXTURE_FLOOR_PX on
        both axes). Beside it an outline is frozen from FROZEN_TEXTURE_COPIED of its profiles
        copied on, a strong texture's as a band texture's."""
        if (region.texture is None or region.codec_crf is None
                or min(region.texture_strength) < FROZEN_TEXTURE_GRADIENT):
            return False
        return max(self._reported_sigma(region, _TextureSigma((0.0, 0.0)), reading=False)) <= FROZEN_TEXTURE_FLOOR_PX

    def _outline_state(self, flow: np.ndarray, region: _Region, reference: np.ndarray,
                       current: np.ndarray) -> tuple[bool | None, np.ndarray | None, bool]:
        """Whether the region's background stands still (see :func:`_background_static`; None: no
        member, no outline fitted (see SHADED_ACROSS_GRADIENT), or not known) and its outline's profiles a codec copied (see
        :meth:`_copied_profiles`; not looked for where the outline is refused anyway, nor counted
        as left out): ``(static, skip, frozen)``."""
        if region.member is None or region.shaded_across:
            return None, None, False  # (no outline is fitted)
        found = _sides_beyond(flow, region)
        static = _background_static(flow, region, reference, current, beyond=found)
        region.static_known = static is not None
        region.key_with = static is True and _background_with(found, region, reference, current)
        self.counts["outline_whole_with"] += region.key_with
        skip, frozen = (None, False) if static is False else self._copied_profiles(region, reference, current)
        return static, skip, frozen

    def _count(self, model: str | None, reason: str | None = None) -> None:
        if model is not None:
            self.counts[f"{model}_readings"] += 1
        if reason is not None:
            self.counts[f"why_{reason}"] += 1

    def _full(self, reference: np.ndarray, current: np.ndarray, flow: np.ndarray, region: _Region, *,
              camera: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, tuple[float, float]] | None:
        """A region's POI motion from its texture or its edges, starting from the dense
        ``flow``; None where the dense flow stays (neither fits). ``camera``: the camera's image
        motion (u, v) px at the region, where a background gives it."""
        region.restart()
        dense_u, dense_v = flow[region.rows, region.cols, 0], flow[region.rows, region.cols, 1]
        affine, texture, deforms, outline, fit, along, refined = None, None, False, None, None, None, None
        imprecise = False  # an outline fitted and refused as too imprecise (OUTLINE_MAX_SIGMA_PX)
        static, skip, frozen = self._outline_state(flow, region, reference, current)
        # A texture too weak to be trusted is never taken (see _choose): not fitted at all; one just
        # short of it is, as a strong one, where the codec froze the outline (FROZEN_TEXTURE_GRADIENT).
        strong = region.strong_texture
        beside_frozen = frozen and self._band_texture(region)
        if strong or beside_frozen:
            texture = self._fit_from_dense(region, current, dense_u, dense_v)
            affine = None if texture is None else region.texture_reading(texture)
            # (Frames are lossless where the bias correction is on: see bias_correction.)
            deforms = _deforms(region, dense_u, dense_v, lossless=self._bias_on)
        strong = strong or (beside_frozen and affine is not None)  # (its fit failed: the outline)
        if static is False:
            self._count(None, "outline_background_moves")
        elif frozen and affine is not None:
            self._count(None, "outline_codec_copied")
        elif region.shaded_across:
            self._count(None, "outline_shaded_across")
        elif region.member is not None:
            fit = region.member.fit(current, flow[region.prior_rows, region.prior_cols].astype(np.float64),
                                    gain=region.gain(current), camera=camera, skip=skip, first=WHOLE if region.key_with else None)
            if fit.ok:
                u, v, edges, along, state = region.motion(
                    reference, current, fit, region.along(dense_u, dense_v), texture=True)
                region.along_tried, region.along_texture = state is not None, state == "taken"
                # The edges must not make the POIs' own match worse than the dense flow's.
                sigma = region.outline_sigma(fit, state)
                if min(sigma) > OUTLINE_MAX_SIGMA_PX:
                    self._count(None, "outline_imprecise")
                    imprecise = True
                elif _matches(edges, _mismatch(reference, current, region.cols, region.rows, dense_u, dense_v)):
                    outline = (u, v, sigma)
                    region.key_mismatch = edges
        if (outline is not None and strong and static is not True
                and not self._outline_sharper(region, outline, affine)):
            # A strong texture lets the dense flow see the region's own motion: an outline is
            # not taken over it on the word of a background never seen standing still, unless
            # it is the more precise of the two across the member (the workbench's beam before
            # its release: an 8 px strip's texture fit, 0.22 px sigma with the codec's error,
            # read 0.05 px off where the outline, 0.002-0.03 px, read the rest).
            self._count(None, "outline_background_unseen")
            outline = None
        elif outline is not None and strong and self._texture_sharper(region, outline, affine):
            # Nor where the texture's fit is at least as precise on both axes (its sigma with the
            # codec's error): an outline found right, with a background seen still, reads a
            # strongly textured member under heavy noise 0.35 px off (its sigma 0.11 px) where
            # the texture read 0.13 (its sigma 0.015).
            self._count(None, "outline_texture_sharper")
            outline = None
        chosen, model, reason = _choose(affine, outline, strong, deforms)
        if reason == "dense_only" and imprecise and not (region.strong_texture or beside_frozen) and (
                faint := self._faint_texture(reference, current, region, dense_u, dense_v)) is not None:
            (texture, chosen), model, reason = faint, "affine", "faint_texture"
        if reason == "dense_only":
            self._dense_along(reference, current, flow, region)
        if reason == "dense_deforms":
            # The dense field read, its small deformations' shortfall taken off (see localfit),
            # and each POI's own uncertainty for the field file ...
            refined = refine_locally(reference, current, region.rows, region.cols, dense_u, dense_v,
                                     with_sigma=self.want_field_sigma)
            # ... unless the texture's affine fit matches the region's pixels clearly better than
            # that field: the dense flow, not the region, departed from an affine field (see
            # DEFORM_MATCH_RATIO), and the region is read as one that does not deform.
            field_mismatch = _mismatch(reference, current, region.cols, region.rows, refined[0], refined[1])
            if affine is not None and (_mismatch(reference, current, region.cols, region.rows, affine[0], affine[1])
                                       < DEFORM_MATCH_RATIO * field_mismatch):
                chosen, model, reason = _choose(affine, outline, strong)
                reason, refined = "texture_matches_better" if model == "affine" else reason, None
            elif outline is not None and region.key_mismatch < DEFORM_MATCH_RATIO * field_mismatch:
                # The same for the outline where the texture's fit failed (started from that torn
                # field: a facade of windows in low light, one key 2.4 px off).
                chosen, model, reason, refined = outline, "outline", "outline_matches_better", None
        self._count(model, reason)
        if refined is not None:
            # The widest window the field's own deformation allows (see refine_adaptively).
            refined, window = refine_adaptively(reference, current, region.rows, region.cols, refined,
                                                with_sigma=self.want_field_sigma)
            self.counts[f"field_window_{window:g}px"] += 1
            flow[region.rows, region.cols, 0] = refined[0]
            flow[region.rows, region.cols, 1] = refined[1]
            if self.want_field_sigma:
                self.last_field_sigma = (self.last_field_sigma or []) + [
                    (region.rows, region.cols, refined[2].astype(np.float32), refined[3].astype(np.float32))]
        self.counts["along_texture"] += model == "outline" and region.along_texture
        region.read_by = model
        if self._chaining:
            self._key(region, model, chosen, fit, along, texture, strong)
        return chosen

    @staticmethod
    def _key(region: _Region, model: str, chosen: tuple | None, fit: MemberFit | None, along: np.ndarray | None,
             texture: RegionMotion | None, strong: bool) -> None:
        """Make a full measurement that took the outline or the texture's affine fit (``model``,
        its reading ``chosen``, the ``fit`` or ``texture`` it came from) the key of a chain its next
        frames are tracked from (see :meth:`_track`): not an outline whose along-member motion
        moved where the texture is ``strong``, nor a texture fit of a region with a rim, nor one of
        a texture that is not ``strong`` (strong, or just short of it beside a frozen outline: the
        textures a tracked frame reads; a fainter one read in place of the dense flow, see
        FAINT_TEXTURE_MAX_SIGMA_PX, has its next frame measured in full)."""
        if model == "outline" and not (strong and _along_moves(along, chosen[2])):
            region.model, region.theta, region.key_along = "outline", fit.params, along
            region.key_outline = (fit.model, fit.systematic, fit.spread, fit.reported_systematic)
            region.key_ambiguity = region.along_ambiguity
        elif model == "affine" and strong and not region.rim_rows.size:  # (see _Region.rim_rows)
            region.model, region.affine, region.key_residual = "affine", texture.params, texture.residual
            region.key_rms = texture.rms

    def _fit_from_dense(self, region: _Region, current: np.ndarray, dense_u: np.ndarray,
                        dense_v: np.ndarray) -> RegionMotion | None:
        """The region's texture fit (:meth:`_texture_fit`) started from the affine field of the dense
        flow at its POIs (``dense_u``, ``dense_v``); None where that has too few finite values or
        the fit does not converge to a finite sigma."""
        start = region.texture.params_from_flow(dense_u, dense_v, region.rows, region.cols)
        found = None if start is None else self._texture_fit(region, current, start)
        return found if found is not None and found.converged and all(np.isfinite(found.sigma_px)) else None

    def _faint_texture(self, reference: np.ndarray, current: np.ndarray, region: _Region,
                       dense_u: np.ndarray, dense_v: np.ndarray) -> tuple[RegionMotion, tuple] | None:
        """The fit of a region's texture too faint to be trusted over an outline, and its reading,
        where it replaces the dense flow's (``dense_u``, ``dense_v`` at the POIs) after the outline
        was refused as too imprecise (see FAINT_TEXTURE_MAX_SIGMA_PX); None where the region has no
        texture to fit, the fit fails, or it is not precise enough or matches worse."""
        found = None if region.texture is None else self._fit_from_dense(region, current, dense_u, dense_v)
        if found is None:
            return None
        reading = region.texture_reading(found)
        if max(self._reported_sigma(region, reading[2], reading=False)) > FAINT_TEXTURE_MAX_SIGMA_PX:
            return None
        matched = _mismatch(reference, current, region.cols, region.rows, reading[0], reading[1])
        if matched > _mismatch(reference, current, region.cols, region.rows, dense_u, dense_v):
            return None
        return found, reading

    def _dense_along(self, reference: np.ndarray, current: np.ndarray, flow: np.ndarray,
                     region: _Region) -> None:
        """The dense ``flow`` at the POIs of a region shaded across its member (no outline fitted,
        see :attr:`_Region.shaded_across`) given its own texture's along-member motion where the
        POIs match that clearly better (see :meth:`_Region.texture_along`).

        Over a faint texture the dense flow's smoothing holds a member sliding along itself
        back towards the still background either side of it: the tests' narrow shaded column
        moving 3 px along its axis read 0.19-0.40 px."""
        if not region.shaded_across or region.along_fit is None:
            return
        dense_u, dense_v = flow[region.rows, region.cols, 0], flow[region.rows, region.cols, 1]
        dense = (dense_u, dense_v, _mismatch(reference, current, region.cols, region.rows, dense_u, dense_v), None)
        found, state = region.texture_along(reference, current, dense_u, dense_v, dense, [],
                                            texture=True, texture_first=False, tracked=False)
        if state == "taken":
            flow[region.rows, region.cols, 0], flow[region.rows, region.cols, 1] = found[0], found[1]
            self.counts["along_texture"] += 1

    def _outline_sharper(self, region: _Region, outline: tuple, affine: tuple | None) -> bool:
        """Whether an outline reading is more precise than the texture's (``affine``; None: no
        texture reading) on the axis the outline fixes best, the texture's sigma with the
        codec's error (see :meth:`_Region.reported_sigma`)."""
        if affine is None:
            return False
        axis = int(np.argmin(outline[2]))
        return outline[2][axis] < self._reported_sigma(region, affine[2], reading=False)[axis]

    def _texture_sharper(self, region: _Region, outline: tuple, affine: tuple | None) -> bool:
        """Whether a texture reading (``affine``; None: none) is at least as precise as an
        outline reading on both axes, the texture's sigma with the codec's error (an outline
        sigma that is not finite never is)."""
        if affine is None or not all(np.isfinite(outline[2])):
            return False
        texture = self._reported_sigma(region, affine[2], reading=False)
        return all(t <= o for t, o in zip(texture, outline[2], strict=True))

    def _track(self, reference: np.ndarray, current: np.ndarray,
               region: _Region) -> tuple[np.ndarray, np.ndarray, tuple[float, float]] | None:
        """A region's POI motion with its chain key's model, from its previous frames' motion;
        None where the fit fails or its mismatch leaves the chain's band (the region is then
        measured in full)."""
        if region.model == "affine":
            if not region.strong_texture and not self._copied_profiles(region, reference, current, count=False)[1]:
                # A texture just short of strong is read only where the codec froze the outline
                # (see FROZEN_TEXTURE_GRADIENT): a frame whose outline it did not freeze is measured
                # in full (a faint bar moving +-1.5 px, its first frames frozen: their texture's
                # chain read 30 frames 0.092 px RMS where the outline read 0.062).
                return None
            previous = region.affine
            start = previous if region.affine_before is None else 2.0 * previous - region.affine_before
            found = self._texture_fit(region, current, start)
            # The residual is that of the pixels the robust weights keep: a fit caught a pixel
            # or two off the motion keeps few and can show a residual as small as the key's (a
            # photo texture moving 1.5 px between frames: 0.095 grey levels on 41 % of the
            # pixels, the key 0.062); over all the pixels it is 5.8 against the key's 0.93.
            if not (found.converged and all(np.isfinite(found.sigma_px))
                    and _in_band(found.residual, region.key_residual)
                    and found.rms <= WARM_RMS_RATIO * region.key_rms + MATCH_SLACK):
                return None
            region.affine_before, region.affine = previous, found.params
            self._count("affine")
            region.read_by = "affine"
            return region.texture_reading(found)
        member = region.member
        if region.last_step_px > MAX_WARM_STEP_PX:
            # The member moved further than a tracked outline may step since the frame before: the
            # fit, started from that frame's outline, finds an edge within its search instead (a
            # bar swung +-35 px: 8.4 px between two frames, read 5.7 px short).
            return None
        skip, frozen = self._copied_profiles(region, reference, current)
        if frozen and (region.strong_texture or self._band_texture(region)):
            return None  # measured in full, where the outline is refused for the texture's fit
        prior = np.column_stack(member.field.uv(region.theta))
        model, systematic, spread, reported = region.key_outline
        fit = member.fit(current, prior, gain=region.gain(current),
                         first=WHOLE if region.key_with else _first_models(model),
                         enough_spread=np.inf if region.key_with else TRACKED_SPREAD_RATIO * spread + 1e-3,
                         systematic=systematic, skip=skip,
                         reported_systematic=reported)
        if not fit.ok:
            return None
        u, v, edges, _, state = region.motion(reference, current, fit, region.key_along,
                                              texture=region.along_tried, texture_first=region.along_texture,
                                              tracked=True)
        if region.along_seen is not None and state is None:
            return None  # the texture that read the chain's along-member motion lost it: measured in full
        now_u, now_v = member.poi_field.uv(fit.params)
        before_u, before_v = member.poi_field.uv(region.theta)
        step = float(np.hypot(np.mean(now_u - before_u), np.mean(now_v - before_v)))
        # Along the member a tracked frame has the key's motion unless the paint reads its own:
        # what the key could not tell apart there, it cannot either.
        sigma = region.outline_sigma(fit, state,
                                     at_least=0.0 if state == "taken" else region.key_ambiguity)
        if not (_in_band(edges, region.key_mismatch) and step <= MAX_WARM_STEP_PX
                and min(sigma) <= OUTLINE_MAX_SIGMA_PX):
            return None
        # A key too still to show its background standing still: measured in full (and checked)
        # once the member has moved far enough to tell, unless the frame's own pixels beyond the
        # outline clearly show it.
        if not region.static_known and float(np.hypot(np.mean(now_u), np.mean(now_v))) >= STATIC_MIN_MOTION_PX:
            if not _background_clear(region, reference, current, np.column_stack(member.field.uv(fit.params))):
                return None
            region.static_known = True
        region.theta = fit.params
        self._count("outline")
        region.read_by = "outline"
        self.counts["outline_every_model"] += fit.every_model
        if state == "taken":
            self.counts["along_texture"] += 1
        return u, v, sigma


def _warm_up_pair() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A small scene every kernel of the default runs on: a faintly textured bar over a
    textured wall (so the outline and the dense flow are fitted; the texture fit, too faint to
    be tried here, is scipy's and has nothing to compile), its frame with the bar moved by
    0.6 px, and the bar's mask."""
    rng = np.random.default_rng(0)
    height, width = 96, 128
    wall = cv2.GaussianBlur(rng.uniform(60, 160, (height, 4 * width)).astype(np.float32), (0, 0), 3.0)
    paint = 150 + 4 * cv2.GaussianBlur(rng.standard_normal((height, 4 * width)).astype(np.float32), (0, 0), 2.0)
    x = np.arange(4 * width) / 4.0
    frames = []
    for shift in (0.0, 0.6):
        cover = np.clip(np.minimum(x + 0.125 - 48 - shift, 80 + shift - (x - 0.125)) * 4, 0, 1)[None, :]
        moved = np.roll(paint, int(round(4 * shift)), axis=1)
        fine = cover * moved + (1 - cover) * wall
        frames.append(np.clip(fine.reshape(height, width, 4).mean(axis=2), 0, 255).astype(np.uint8))
    mask = np.zeros((height, width), bool)
    mask[24:88, 54:74] = True
    return frames[0], frames[1], mask


def compile_kernels() -> None:
    """Compile (or load from numba's cache) every kernel the default method runs, on a small
    scene: a chain's full measurement and a tracked frame. The first run on a machine
    compiles them (about 30 s on 2 cores); ``make`` runs this once at install, and
    ``refflow track`` before its first frame (a fraction of a second once they are cached)."""
    reference, moved, mask = _warm_up_pair()
    method = DeepFlow()
    method.bind(reference, mask)
    method.restart()
    # (Not the reference itself first: its flow is nought, not solved, and the solver's kernels
    # would be left to the first frame of a clip.)
    for current in (moved, moved, moved):
        method.calc(reference, current)


@register("deepflow-dense")
class DeepFlowDense(DeepFlow):
    """``deepflow`` without the edge refinement: the dense DeepMatching + DeepFlow field at the
    POIs (the paper's method as published, solved on the POIs' window; an ablation of the
    default). Every frame is measured on its own."""

    summary = "DeepMatching + DeepFlow dense field at the POIs, no edge refinement (the paper's method)"
    member_default = False
    texture_default = False
    parameters = with_defaults(DeepFlow.parameters, member=False, texture=False)


@register("deepmatching")
class DeepMatchingDense(DenseMethod):
    """DeepMatching alone, interpolated densely (ablation of the variational part).

    Parameters
    ----------
    interpolation : {"linear", "nearest"}
        Interpolation between atomic-patch centres.
    crop : bool
        Solve only around the pixels read (see :class:`DeepFlow`).
    downscale, ngh_rad, max_patch, ... : see :class:`flow.methods.deepflow.deepmatching.MatchParams`.
    """

    summary = "DeepMatching quasi-dense matches interpolated to a dense field"
    parameters = (Param("interpolation", "choice", "linear", "between atomic-patch centres",
                        choices=("linear", "nearest")), CROP, *declared(MatchParams))

    def __init__(self, *, interpolation: str = "linear", crop: bool = True, **params: Any) -> None:
        if interpolation not in ("linear", "nearest"):
            raise ValueError(f"interpolation must be 'linear' or 'nearest', got {interpolation!r}")
        unknown = set(params) - _MATCH_FIELDS
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {sorted(unknown)}; valid: {sorted(_MATCH_FIELDS)}"
            )
        self._match = MatchParams(**params)
        self._nearest = interpolation == "nearest"
        super().__init__(crop=crop, interpolation=interpolation, **dataclasses.asdict(self._match))

    def window_margin(self, shape: tuple[int, ...]) -> int | None:
        return _matching_margin(self._match, shape)

    def _solve(self, reference: np.ndarray, current: np.ndarray, *,
               whole_shape: tuple[int, ...]) -> np.ndarray:
        # Bound and cropping: the base reach (no chain to follow the motion from); else the frame's.
        reach = BASE_REACH_PX if self._crop_on and self._bound_shape is not None else None
        grid = deep_matching(reference, current, _match_at(self._match, reach, reference.shape, whole_shape),
                             checkpoint=self.check_stop)
        flow, _ = densify(grid, reference.shape, nearest=self._nearest)
        return flow
