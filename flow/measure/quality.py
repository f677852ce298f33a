"""Quality flags and the measurement of a run's tracks.

A frame is flagged invalid when its photometric residual is far above its baseline (the
view blocked), when no POI was measured, or when the POIs that survive the eq. 10-12
filters scatter far more than usual; :func:`measure` alternates the flags and the
filtering until they settle, then reports the averaged displacement, each frame's
consistent fraction of POIs and the uncertainty of the mean. A clip whose typical frame the
images cannot resolve to a fraction of a pixel (:func:`typical_sigma`), nor to a small
fraction of its motion (:func:`motion_resolution`), has every frame flagged.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np

from flow.measure.filtering import (
    MCR_THRESHOLD,
    THRESHOLD_RATIO,
    FilterResult,
    filter_and_average,
    row_blocks,
)
from flow.measure.robust import MAD_TO_SIGMA
from flow.measure.tracks import Measurement, Resolution, Tracks

# Quality thresholds of :func:`measure`, the defaults of the flags it calls.
# A frame's photometric residual (mean |grey difference| at the POIs) counts as a blocked
# view only far out in the tail of the clip's own residuals: RESIDUAL_K_MAD robust sigmas
# above their median (noise and codec flicker stay well inside), RESIDUAL_RATIO times the
# median (a steady clip's tiny MAD alone would flag ordinary variation) and RESIDUAL_FLOOR
# grey levels (below that it is sensor noise whatever the baseline).
RESIDUAL_K_MAD = 8.0
RESIDUAL_RATIO = 2.5
RESIDUAL_FLOOR = 3.0
# The kept POIs scatter as if the flow failed (an occluder as bright as the structure):
# SPREAD_RATIO times their median spread, and at least SPREAD_FLOOR_PX px, so that POIs
# agreeing to hundredths of a pixel are not flagged for a tenth.
SPREAD_RATIO = 4.0
SPREAD_FLOOR_PX = 1.5
# The band within which a POI agrees with its frame's median (poi_kept_frac): BAND_RATIO
# times the median spread of the valid frames, at least BAND_FLOOR_PX px, widened to
# BAND_RELATIVE of the median displacement so that a member that rotates or bends within
# the mask keeps its POIs at large amplitude.
BAND_RATIO = 3.0
BAND_FLOOR_PX = 0.5
BAND_RELATIVE = 0.25
# A clip whose typical frame has a standard uncertainty above MAX_TYPICAL_SIGMA_PX px on both
# axes (the images' own uncertainty, :func:`typical_sigma`) holds no sub-pixel reading: a
# video compressed until the outlines are smeared into blocks. Measured (deepflow / dis,
# defaults): every other clip we have reads 0.002-0.25 px (the bench's CRF 30 clip: 0.25 /
# 0.53, where dis's RMSE is 1.26 px); the workbench's 0.01 bit-per-pixel clip 0.47 / 0.54,
# with errors of about 1 px.
MAX_TYPICAL_SIGMA_PX = 0.35
# ... unless the motion is large against it: 0.5 px of uncertainty is hopeless for a 0.3 px
# vibration and excellent for a 20 px swing. A clip still resolves its motion when, on one
# axis, the typical uncertainty is at most MAX_SIGMA_TO_RANGE of the robust range (5-95 %)
# of the readings on that axis (:func:`motion_resolution`): a sinusoid's amplitude 16 sigmas.
# Noise alone spans 3.3 sigma (0.30), and the dense methods' own sigma under-states their
# error by up to 3-4x (the bench's 2-sigma coverage 0.13-0.3): at 0.03 their true error is
# still about a tenth of the motion's range. Measured (defaults): the Tacoma deck (the deck
# polygon of scripts/tacoma.sh) with dis 0.015-0.017 (0.30-0.34 px of a 20 px swing; 0.004
# with --grid-step 4), deepflow-opencv 0.02-0.03 (0.07 in the tight ROI, where it reads half
# dis's swing: flagged); flagged as before: the bench's CRF 30 clip with every dense baseline
# 0.08-0.11 (farneback 0.51; their readings 0.65-3.3 px RMS off a 4.2 px swing), farneback on
# the bench's bend and occlusion clips 0.17 / 0.26, the workbench's 0.01 bit-per-pixel clip
# about 0.08 (estimated: 0.47 px of a swing of about 5 px), and scripts/tacoma.sh's near-curb
# pieces with deepflow's outline fit 0.033-0.083 (1-2 px; on one piece the reading jumps by
# 20-30 px; since issue 30 the default refuses that outline and reads 0.12-0.19 px, unflagged).
MAX_SIGMA_TO_RANGE = 0.03
# The robust range of the motion: the spread between these percentiles of the readings.
MOTION_PERCENTILES = (5.0, 95.0)
# The frames averaged into the reference (--reference-average) are at rest by the user's word:
# their readings scatter only by the measurement's own error. Where they scatter more than their
# sigmas say (:func:`rest_excess`, from REST_MIN_FRAMES valid frames), the excess is an error no
# frame's fit shows, added to every frame's sigma. Measured: the workbench's 0.01 bit-per-pixel
# clip (x264 at about 5 Mbit/s at 4K60, a key frame every second), deepflow: its 30 frames at
# rest read 0.74 to -0.54 px (the codec rebuilds the paint's texture differently from frame to
# frame), their sigma 0.11-0.43 px (median 0.15); every frame valid at 1.19 px RMS error.
REST_MIN_FRAMES = 5


def flag_invalid(residual: np.ndarray, *, k_mad: float = RESIDUAL_K_MAD, ratio: float = RESIDUAL_RATIO,
                 floor: float = RESIDUAL_FLOOR) -> tuple[np.ndarray, float]:
    """Frames whose photometric residual is far above its robust baseline (view blocked).

    A frame is invalid when its residual exceeds ``max(median + k_mad * sigma,
    ratio * median, floor)`` with ``sigma = 1.4826 * MAD`` over all frames, or is NaN.
    Returns ``(valid, threshold)``.
    """
    residual = np.asarray(residual, float)
    finite = residual[np.isfinite(residual)]
    if finite.size == 0:
        return np.zeros(residual.shape, bool), float("nan")
    median = float(np.median(finite))
    sigma = MAD_TO_SIGMA * float(np.median(np.abs(finite - median)))
    threshold = max(median + k_mad * sigma, ratio * median, floor)
    return np.isfinite(residual) & (residual <= threshold), threshold


class _NanQuiet:
    """Frames where every POI is NaN give NaN statistics, without RuntimeWarnings."""

    def __enter__(self) -> None:
        self._errstate = np.errstate(all="ignore")
        self._errstate.__enter__()
        self._warnings = warnings.catch_warnings()
        self._warnings.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc: object) -> None:
        self._warnings.__exit__(*exc)
        self._errstate.__exit__(*exc)


def poi_spread(dx: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Per frame, the robust spread (px) of the POI displacements: 1.4826 x MAD, x and y combined.

    POIs on one structural member move almost alike; an occluder, a lost view
    or a failed flow scatters them.
    """
    spread = np.full(dx.shape[0], np.nan)
    if dx.shape[1] == 0:
        return spread
    with _NanQuiet():
        mad_x = np.nanmedian(np.abs(dx - np.nanmedian(dx, axis=1, keepdims=True)), axis=1)
        mad_y = np.nanmedian(np.abs(dy - np.nanmedian(dy, axis=1, keepdims=True)), axis=1)
    return MAD_TO_SIGMA * np.hypot(mad_x, mad_y)


def consistent_fraction(dx: np.ndarray, dy: np.ndarray, *, band_px: float,
                        relative: float = BAND_RELATIVE) -> np.ndarray:
    """Per frame, the fraction of POIs whose displacement is finite and agrees with the frame's median.

    A POI agrees when its 2-D distance from the frame's median displacement is
    at most ``max(band_px, relative * |median|)``: the relative term lets a
    structure that rotates or bends within the mask keep its POIs at large
    amplitude, while a blocked view or a failed flow scatters them out.
    """
    if dx.shape[1] == 0:
        return np.zeros(dx.shape[0])
    with _NanQuiet():
        median_x = np.nanmedian(dx, axis=1, keepdims=True)
        median_y = np.nanmedian(dy, axis=1, keepdims=True)
        distance = np.hypot(dx - median_x, dy - median_y)
        band = np.maximum(band_px, relative * np.hypot(median_x, median_y))
        agree = np.isfinite(distance) & (distance <= band)
    return agree.sum(axis=1) / dx.shape[1]


def flag_incoherent(spread: np.ndarray, *, ratio: float = SPREAD_RATIO,
                    floor_px: float = SPREAD_FLOOR_PX) -> np.ndarray:
    """Frames whose POIs disagree far more than usual: ``spread > max(ratio * median, floor_px)``.

    Catches an occluder whose brightness happens to match the structure's
    (the photometric residual then stays low while the flow is garbage).
    NaN spread (no POI measured) counts as coherent here; ``all_nan`` handles it.
    """
    finite = spread[np.isfinite(spread)]
    if finite.size == 0:
        return np.zeros(spread.shape, bool)
    threshold = max(ratio * float(np.median(finite)), floor_px)
    return np.isfinite(spread) & (spread > threshold)


def _per_frame(tracks: Tracks, columns: np.ndarray | None,
               statistic: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """``statistic(dx_block, dy_block)`` of every frame, offsets removed, read in blocks."""
    out = np.full(len(tracks.frame), np.nan)
    for rows, bx, by in row_blocks(tracks.dx, tracks.dy, tracks.offset_dx, tracks.offset_dy, columns):
        out[rows] = statistic(bx, by)
    return out


def measure(tracks: Tracks, *, filter_enabled: bool = True, average: str = "mean",
            threshold_ratio: float = THRESHOLD_RATIO, threshold_px: float | None = None,
            mcr_threshold: float = MCR_THRESHOLD, residual_ratio: float = RESIDUAL_RATIO,
            residual_k_mad: float = RESIDUAL_K_MAD, residual_floor: float = RESIDUAL_FLOOR,
            spread_ratio: float = SPREAD_RATIO, spread_floor_px: float = SPREAD_FLOOR_PX,
            check_coherence: bool = True, max_rounds: int = 3, band_ratio: float = BAND_RATIO,
            band_floor_px: float = BAND_FLOOR_PX, band_relative: float = BAND_RELATIVE,
            max_typical_sigma_px: float = MAX_TYPICAL_SIGMA_PX,
            max_sigma_to_range: float = MAX_SIGMA_TO_RANGE) -> Measurement:
    """Quality flags, eq. (10)-(12) filtering and averaging of a run's tracks.

    A frame is invalid when its photometric residual is far above its baseline
    (:func:`flag_invalid`), when no POI was measured, when the method saw nothing of the
    scene in it (``tracks.hidden``), or, with
    ``check_coherence``, when the POIs that survive the filters scatter far more
    than usual (:func:`flag_incoherent`). The coherence check must only look at
    the surviving POIs (background POIs in the mask stay put while the
    structure moves, which is no sign of a blocked view), and the filters must
    only use valid frames, so the two alternate until the flags settle (at most
    ``max_rounds`` rounds).

    ``poi_kept_frac`` is, per frame, the :func:`consistent_fraction` of the
    surviving POIs with a band of ``max(band_ratio * median spread,
    band_floor_px)``.

    Where the method reports the images' own uncertainty (``tracks.sigma_dx``), a clip whose
    :func:`typical_sigma` exceeds ``max_typical_sigma_px`` (0: never) and, on its better axis,
    ``max_sigma_to_range`` of the motion's robust range (:func:`motion_resolution`) has every
    frame flagged (``Measurement.unresolved``): it resolves neither a sub-pixel reading nor
    its motion. The readings stay in ``filtered``: a flag qualifies a number, never deletes it.
    """
    # (Frames the method saw nothing in still count towards the residual's threshold, as they
    # do for every method that does not tell them: kept out, they flagged the workbench's
    # frames after the A4 sheet longer, valid share 0.769 -> 0.752, recovery 0.37 -> 0.48 s.)
    photometric, threshold = flag_invalid(tracks.residual, k_mad=residual_k_mad, ratio=residual_ratio,
                                          floor=residual_floor)
    measured = _per_frame(tracks, None, lambda bx, by: np.isfinite(bx).any(axis=1)) > 0
    base = photometric & measured
    if tracks.hidden is not None:
        base &= ~np.asarray(tracks.hidden, bool)
    offset = (tracks.offset_dx, tracks.offset_dy)

    def run_filters(valid: np.ndarray) -> FilterResult:
        return filter_and_average(tracks.dx, tracks.dy, valid=valid, offset=offset,
                                  threshold_ratio=threshold_ratio, threshold_px=threshold_px,
                                  mcr_threshold=mcr_threshold, average=average, enabled=filter_enabled)

    valid = base.copy()
    filtered = run_filters(valid)
    spread = _per_frame(tracks, filtered.kept, poi_spread)
    for _ in range(max_rounds if check_coherence else 0):
        flagged = base & ~flag_incoherent(spread, ratio=spread_ratio, floor_px=spread_floor_px)
        if np.array_equal(flagged, valid):
            break
        valid = flagged
        filtered = run_filters(valid)
        spread = _per_frame(tracks, filtered.kept, poi_spread)
    typical = spread[valid & np.isfinite(spread)]
    band = max(band_ratio * float(np.median(typical)) if typical.size else 0.0, band_floor_px)
    kept_frac = _per_frame(tracks, filtered.kept, lambda bx, by: consistent_fraction(
        bx, by, band_px=band, relative=band_relative))
    precision_px, unresolved = float("nan"), False
    if tracks.sigma_dx is not None and tracks.sigma_dy is not None:
        held = tracks.sigma_holds_reference
        sigma_dx = with_reference_term(np.asarray(tracks.sigma_dx, float), valid, held)
        sigma_dy = with_reference_term(np.asarray(tracks.sigma_dy, float), valid, held)
        rest = rest_excess(tracks, filtered, tracks.sigma_dx, tracks.sigma_dy, valid)
        sigma_dx, sigma_dy = np.hypot(sigma_dx, rest[0]), np.hypot(sigma_dy, rest[1])
        precision_px = typical_sigma(sigma_dx, sigma_dy, valid)
        motion = motion_resolution(filtered.dx, filtered.dy, sigma_dx, sigma_dy, valid)
        unresolved = bool(max_typical_sigma_px > 0 and precision_px > max_typical_sigma_px
                          and not motion.ratio <= max_sigma_to_range)
        if unresolved:
            valid = np.zeros_like(valid)
    else:
        # Features followed on their own (KLT): the standard error of their mean.
        sigma_dx = _per_frame(tracks, filtered.kept, lambda bx, by: _standard_error(bx))
        sigma_dy = _per_frame(tracks, filtered.kept, lambda bx, by: _standard_error(by))
        rest = rest_excess(tracks, filtered, sigma_dx, sigma_dy, valid)
        sigma_dx, sigma_dy = np.hypot(sigma_dx, rest[0]), np.hypot(sigma_dy, rest[1])
        motion = Resolution()
    return Measurement(tracks, filtered, valid, kept_frac, spread, threshold, band, sigma_dx, sigma_dy,
                       typical_sigma_px=precision_px, unresolved=unresolved, resolution=motion,
                       rest_excess_px=rest)


def rest_excess(tracks: Tracks, filtered: FilterResult, sigma_dx: np.ndarray, sigma_dy: np.ndarray,
                valid: np.ndarray, *, min_frames: int = REST_MIN_FRAMES) -> tuple[float, float]:
    """How much more the readings of the frames averaged into the reference scatter than their
    sigmas say, ``(x, y)`` px (0 where they do not, or with fewer than ``min_frames`` of them
    valid: a reference of one frame, a range of frames without them).

    The frames ``reference_frame .. reference_frame + reference_average - 1`` are at rest by the
    user's word (``--reference-average``): each reads the same motion, none. Their scatter
    about their mean (ddof 1: each is in the mean it is compared with) holds every error that
    changes from frame to frame; what of it their median sigma (``sigma_dx``, ``sigma_dy``:
    the method's own, without the reference's error, which is common to them all) does not
    cover is an error the fits cannot see (a codec that rebuilds a texture differently in each
    frame), taken as the same in the frames that move. Only a scatter beyond what chance gives
    n frames whose sigma is right counts, and only what lies beyond that bound (their variance
    more than 2 of its standard errors, ``sqrt(2 / (n - 1))``, above the sigma's square): an
    estimate on the low side by design. A sigma that holds the reference's error already (a
    texture fit's, ``Tracks.sigma_holds_reference``) counts it as the frames' own, which makes
    the excess smaller still. A structure not quite at rest makes it larger: an uncertainty
    stated too wide. The frames are those of ``tracks``: a run of a ``--frames`` range that holds
    none or only some of them gets none or a rougher one; parts merged get the whole run's.
    """
    frame = np.asarray(tracks.frame)
    start = tracks.reference_frame
    rest = (frame >= start) & (frame < start + max(int(tracks.reference_average), 1)) & np.asarray(valid, bool)
    excess = []
    for values, sigma in ((filtered.dx, sigma_dx), (filtered.dy, sigma_dy)):
        values, sigma = np.asarray(values, float), np.asarray(sigma, float)
        use = rest & np.isfinite(values) & np.isfinite(sigma)
        if use.sum() < min_frames:
            excess.append(0.0)
            continue
        scatter = float(np.var(values[use], ddof=1))
        own = float(np.median(np.square(sigma[use]))) * (1.0 + 2.0 * np.sqrt(2.0 / (use.sum() - 1)))
        excess.append(float(np.sqrt(max(scatter - own, 0.0))))
    return excess[0], excess[1]


def motion_resolution(dx: np.ndarray, dy: np.ndarray, sigma_dx: np.ndarray, sigma_dy: np.ndarray,
                      valid: np.ndarray, *, percentiles: tuple[float, float] = MOTION_PERCENTILES) -> Resolution:
    """How well a clip resolves its own motion: per axis, the median standard uncertainty of the
    valid frames against the robust range (5-95 %) of their readings; the axis whose ratio is
    smaller (NaN fields without two valid frames).

    The robust range, because a few wild frames (a twist the flow cannot follow) must not
    make a clip look resolved; per axis, because a member's outline fixes only the motion
    across it, and the uncertainty of one axis says nothing of the other's motion.
    """
    valid = np.asarray(valid, bool)
    best = Resolution()
    for axis, values, sigma in (("dx", dx, sigma_dx), ("dy", dy, sigma_dy)):
        values, sigma = np.asarray(values, float), np.asarray(sigma, float)
        readings = values[valid & np.isfinite(values)]
        sigmas = sigma[valid & np.isfinite(sigma)]
        if readings.size < 2 or sigmas.size == 0:
            continue
        low, high = np.percentile(readings, percentiles)
        found = Resolution(axis=axis, sigma_px=float(np.median(sigmas)), range_px=float(high - low))
        if not best.ratio <= found.ratio:  # NaN (none yet) loses to any number
            best = found
    return best


def typical_sigma(sigma_dx: np.ndarray, sigma_dy: np.ndarray, valid: np.ndarray) -> float:
    """The images' precision over a clip: the median standard uncertainty of the valid frames
    on the better-measured axis (px; NaN without any).

    The better axis, because a member's outline fixes only the motion across it (along a
    vertical member dy is poorly determined on every clip). The median, because a single
    frame's uncertainty also grows where the structure deforms within the mask (on Tacoma
    up to 7 px in the largest twists, 0.10 px typical): what the codec or the light took
    from the images shows in every frame.
    """
    valid = np.asarray(valid, bool)
    medians = [float(np.median(s[valid & np.isfinite(s)])) for s in (sigma_dx, sigma_dy)
               if (valid & np.isfinite(s)).any()]
    return min(medians) if medians else float("nan")


def with_reference_term(sigma: np.ndarray, valid: np.ndarray, held: np.ndarray | None = None) -> np.ndarray:
    """A method's per-frame uncertainty with the reference frame's own added in quadrature,
    except in the frames whose sigma already ``held`` it.

    Every frame is measured against one reference, which is itself an image measured the
    same way (its outlines fitted under the same models, its noise and codec pattern): its
    error is one draw, common to every frame, that no frame's own fit can show (on an
    independent clip it was an offset of -0.04 px in every frame, 1.2 of the frames' own
    sigmas). Its standard uncertainty is taken as a typical frame's, the median of the valid
    frames' that do not hold it (not reduced for an averaged reference: the models' phase
    error does not average away).

    A sigma that holds it already (``held``, per frame; see ``Tracks.sigma_holds_reference``)
    is left as it is: a fit that compares the frame with the reference has both images' noise
    in its residuals, and a codec floor measured against the decoded reference has the
    reference's codec error in it. Counted twice, it made the bench's textured clips' sigma
    1.4 times too large (2-sigma coverage 1.00 on g2, g5, g7, g8).
    """
    sigma = np.asarray(sigma, np.float64)
    held = np.zeros(sigma.shape, bool) if held is None else np.asarray(held, bool)
    typical = sigma[np.asarray(valid, bool) & np.isfinite(sigma) & ~held]
    if typical.size == 0:
        return sigma
    return np.where(held, sigma, np.hypot(sigma, float(np.median(typical))))


def _standard_error(block: np.ndarray) -> np.ndarray:
    """Per row, 1.4826 MAD / sqrt(n) of the finite values (NaN with fewer than 2)."""
    with _NanQuiet():
        n = np.isfinite(block).sum(axis=1)
        mad = np.nanmedian(np.abs(block - np.nanmedian(block, axis=1, keepdims=True)), axis=1)
        return np.where(n >= 2, MAD_TO_SIGMA * mad / np.sqrt(np.maximum(n, 1)), np.nan)
