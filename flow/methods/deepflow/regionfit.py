"""A region's motion as one correlation subset: an affine warp fitted to all of its pixels.

Image correlation (DIC) measures a patch of a textured surface by warping the current frame
back onto the reference patch with a low-order shape function and minimising the grey-level
difference. Here the patch is a whole region of the user's mask (a member's face, a panel, a
slab): its motion field is affine (translation, rotation, stretch and shear over the region,
enough for a rigid part turning about a pivot outside the mask or a member bending linearly
across it), and the frame may be brighter or darker than the reference (a zero-normalised
criterion: gain and offset fall out).

* Criterion: zero-normalised sum of squared differences (ZNSSD), robust to a linear change of
  lighting. Where the light changed across the region (a shadow's edge sweeping over a panel, a
  passing cloud's: see :meth:`RegionFit.light_changed`), the frame is fitted again with a gain
  and offset of its own in every block of :data:`GAIN_BLOCK_PX` (``RegionMotion.light_varies``).
  One gain for the region read a textured panel under a moving soft shadow 0.09-0.20 px RMS
  (DIS 0.045); block by block 0.042. Not everywhere: what a block's mean tells of the motion is
  then lost, which on a faint, coarse texture (blobs of 4-20 px, 6-10 grey levels) read a shift
  1.3-3 times worse.
* Solver: inverse-compositional Gauss-Newton (IC-GN): the steepest-descent images come from the
  reference once; every iteration warps the frame with a cubic B-spline interpolant (bicubic
  convolution biases sub-pixel shifts by up to a few hundredths of a pixel on fine speckle, a
  B-spline by far less) and composes the inverse of the increment into the warp.
* Robustness: iteratively re-weighted (Tukey's biweight on the residual, scaled by its median
  absolute deviation), so that pixels near the mask's edge that see the background, a glint
  or a passing object drop out. On frames as a camera recorded them (lossless:
  ``rounding_floor``) the scale is never below the spread the frames' own rounding
  to whole grey levels leaves in the residual (:func:`rounding_spread`): on a clean, faint
  texture most pixels of a frame moved a few tenths of a pixel round to the reference's
  values, their residuals' median deviation is nearly 0, and without that floor the pixels
  that did change (the ones that carry the motion) were cut as outliers: a noise-free texture
  of 0.6-1.7 grey levels per pixel shifted 0.3 px read 0.000 px. Not on a lossy stream: there
  the residual is the codec's, not the rounding's (the codec's copies are left out by
  :func:`~flow.methods.deepflow.codecfloor.codec_copies`), and the floor moved the readings of
  a paint's fit along its member enough to change which model a hazard-taped girder's chains
  took (0.055 -> 0.092 px RMS).
* Pre-smoothing (``presmooth_px``, on a lossy stream): both frames are smoothed by a small
  Gaussian before the fit. A codec rings about a sharp edge and rebuilds each transform block's
  finest detail its own way; the fit, whose weight lies where the gradient is steepest, reads
  that as motion common to the region (a panel of sharp-edged windows at CRF 18: 0.069 px RMS
  with the fit started at the truth, 0.037 after 0.7 px of smoothing; DIS 0.037).
* Bias: the fit's own systematic error against a sub-pixel shift (interpolation and gradient
  error, periodic in the shift) is measured on the reference shifted exactly and taken off
  each reading (:meth:`RegionFit.bias_curve`), where the frames are lossless.
* Uncertainty: the clustered (sandwich) covariance over blocks of a codec's macroblock size,
  and no less than the scatter of the translations of strips of the region; neither sees an
  error common to the whole region (a codec's quantised motion): on a lossy stream the default
  adds that, measured on the region (:mod:`flow.methods.deepflow.codecfloor`).

The fit needs a starting warp within the basin of the criterion (a pixel or two for fine
texture, more for coarse): the dense flow's affine least-squares fit over the region, or the
previous frame's warp within a chain of frames.

References
----------
.. [1] B. Pan, K. Li, W. Tong, "Fast, robust and accurate digital image correlation
   calculation without redundant computations", Exp. Mech. 53, 2013 (IC-GN with ZNSSD).
.. [2] S. Baker, I. Matthews, "Lucas-Kanade 20 years on: a unifying framework", IJCV 56,
   2004 (the inverse-compositional algorithm).
.. [3] H. W. Schreier, J. R. Braasch, M. A. Sutton, "Systematic errors in digital image
   correlation caused by intensity interpolation", Opt. Eng. 39(11), 2000.
.. [4] P. J. Huber, *Robust Statistics*, Wiley 1981 (M-estimation, IRLS).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from flow.measure.robust import MAD_TO_SIGMA

# At most this many of a region's pixels enter the fit (a regular subsample of a larger
# region): a whole 4K frame's worth of POIs costs what a 170x170 region costs, and the
# mean motion of so many pixels is far below a video's noise floor either way (the codec's
# error is common to the whole region: 0.03-0.04 px on phone-quality H.264 whatever the
# region's size).
MAX_POINTS = 30_000
# The cubic B-spline interpolant (order 3).
SPLINE_ORDER = 3
# Iterations stop when no pixel of the region moves more than this (px) in one update.
TOLERANCE_PX = 5e-4
MAX_ITERATIONS = 40
# Tukey's biweight constant (95 % efficiency at the Gaussian).
TUKEY_C = 4.685
# Levenberg-Marquardt damping of every Gauss-Newton step, relative to the Hessian's mean
# diagonal: directions the texture does not constrain (along a shading that varies in one
# direction only, the stretch of a thin strip) stay where they started instead of following
# the noise; the solution where the texture does constrain is unchanged (the iteration stops
# where the gradient of the criterion vanishes, whatever the damping).
DAMPING = 1e-3
# A fit that ends farther than this (px) from its start, at the region's centroid, has left the
# basin it started in (no texture to hold it): failed.
MAX_TRAVEL_PX = 4.0
# The share of the region's pixels a step must keep within the frame (the others, warped out
# of it, are left out of that step): fewer, and the fit has failed. Before 2026-12-05 one pixel
# out failed it: a background marked up to the frame's edge lost its texture reading as soon
# as the camera drifted (the workbench's long-drift scenario, 2.4 px: 1 frame of 61 read).
MIN_INSIDE = 0.5
# A fit with a budget of iterations (see _out_of_budget) stops once its steps, shrinking as the
# last ones did, would need more than this factor of it to converge.
OUT_OF_BUDGET = 1.5
# ... judged from this step on where the budget is the fit's own (MAX_ITERATIONS; a caller's
# budget is judged from the fourth). Since 2026-12-07 every fit is judged, not only those given
# a budget: a region deforming beyond any affine field (the Tacoma deck) or a texture too faint
# for its noise ran all 40 steps without converging, in every frame. Over 160 synthetic fits on
# faint textures (102 converging after 8-40 steps; tests/unit/test_regionfit.py), judged from
# the fourth step on 7 were cut that would have converged, from the 12th none.
UNBUDGETED_FIRST = 12
# Pixels the warped region may leave the cut-out window before it is cut again.
WINDOW_MARGIN_PX = 6

# The fit's own bias against a sub-pixel shift (interpolation and gradient error: periodic in
# the shift, zero at whole pixels) is measured on the reference itself, shifted exactly (in
# Fourier space) by these fractions of a pixel along x and along y, and taken off every reading
# (see RegionFit.bias).
BIAS_SHIFTS = np.arange(1, 8) / 8.0
# Harmonics of the periodic bias curve fitted to those shifts.
BIAS_HARMONICS = 2
# Margin (px) of reference around the region's bounding box that is shifted with it (mirrored
# beyond, so that the shift's ringing at the cut stays outside what the fit samples).
BIAS_MARGIN_PX = 24

# The region's strips whose translations must agree (see RegionFit._sigma).
STRIPS = 4
# The side of the blocks whose residuals are taken as correlated (a codec's macroblock).
CLUSTER_PX = 16
# The side of the blocks with a gain and offset of their own where the light changed across the
# region (see the module's docstring): wider by the square root of the subsampling step where a
# large region is subsampled (MAX_POINTS), so that a block holds about as many of its pixels.
GAIN_BLOCK_PX = 16
# The light changed across the region where blocks holding at least LIGHT_AREA of its pixels are
# off by an offset (the mean of a block's residual under one gain for the region) of at least
# LIGHT_STEP of the region's mean grey and at least LIGHT_OFFSET of the block's rms residual.
# Under a moving shadow 35 % dark or a soft cloud's, such blocks hold a third to all of the
# region's pixels, their offsets 5-27 grey levels (the 90th percentile over the blocks); on
# the bench's textured clips and the tests' scene kinds, none: offsets within 1.2 grey levels,
# 2.0 under a flicker of the whole frame's light by +-8 %.
LIGHT_STEP = 0.025
LIGHT_OFFSET = 0.5
LIGHT_AREA = 0.1

# A dense flow's departure from every affine field (see affine_departure): smoothed over this
# many px (a Gaussian's sigma: above the dense flow's own pixel-scale noise, and short enough
# to keep most of a wave of 20 px period: the DIC Challenge Stars' waves run from 10 px; at
# 6 px their short periods went to the rest and Star 1 read 2.7 times it, at 3 px 15 times),
# on the region's pixels at least DEFORM_INSET_PX inside its outline (where the dense flow's
# smoothing drags the background's motion in: a departure of the flow, not of the region).
DEFORM_SCALE_PX = 3.0
DEFORM_INSET_PX = 12
# Fewer interior pixels than this: too few to tell.
DEFORM_MIN_PIXELS = 400

# The parameters a fit frees: all six, or the translation alone.
_AFFINE = np.arange(6)
_TRANSLATION = np.array([0, 3])

# A derivative of fourth-order accuracy: small bias on fine texture.
_DERIVATIVE = np.array([1.0, -8.0, 0.0, 8.0, -1.0]) / 12.0


@dataclass(frozen=True)
class RegionMotion:
    """One frame's affine motion of a region.

    ``params`` are ``(u, u_x, u_y, v, v_x, v_y)``: the displacement at the region's centroid
    (px) and its derivatives per unit of the region's scale length, so that the displacement
    at a pixel ``(x, y)`` is ``u + u_x (x - x0) / L + u_y (y - y0) / L`` (and ``v`` alike).
    """

    params: np.ndarray
    converged: bool
    sigma_px: tuple[float, float]  # standard uncertainty of the region's mean displacement
    residual: float  # robust rms of the grey-level residual, in the reference's grey levels
    iterations: int
    inliers: float  # share of the pixels the robust weights keep (weight > 0)
    rms: float = float("nan")  # plain rms of the grey-level residual over the region's pixels (those in the frame)
    light_varies: bool = False  # the light changed across the region: read with each block's own gain (see fit)


def _warp_matrix(params: np.ndarray, scale: float) -> np.ndarray:
    """The warp as a matrix on pixel offsets from the centroid (the derivatives are per
    ``scale`` px)."""
    u, ux, uy, v, vx, vy = params
    return np.array([[1.0 + ux / scale, uy / scale, u], [vx / scale, 1.0 + vy / scale, v], [0.0, 0.0, 1.0]])


def _params_of(matrix: np.ndarray, scale: float) -> np.ndarray:
    return np.array([matrix[0, 2], (matrix[0, 0] - 1.0) * scale, matrix[0, 1] * scale,
                     matrix[1, 2], matrix[1, 0] * scale, (matrix[1, 1] - 1.0) * scale])


class RegionFit:
    """The affine IC-GN fit of one region of a reference frame.

    Parameters
    ----------
    reference : ndarray (H, W)
        The reference frame (grey, any real dtype).
    rows, cols : ndarray (N,) int
        The region's pixels.
    max_points, tolerance_px
        The most pixels the fit takes (a regular subsample of them) and the step (px) below
        which it has converged: :data:`MAX_POINTS` and :data:`TOLERANCE_PX` unless a quicker,
        rougher fit is wanted.
    bias_correction : bool
        Take the fit's own sub-pixel bias, measured on the reference (see :meth:`bias_curve`),
        off every reading. Right where the frames are what a camera records (raw, lossless);
        wrong where a lossy codec rebuilt them with its own interpolation (on an H.264 girder
        moving 0.3 px the correction read 3 % shorter): off there.
    rounding_floor : bool
        Keep the robust scale of the fit's residual at least :func:`rounding_spread` (frames
        as a camera recorded them); off for a lossy codec's (see the module's docstring).
    local_light : bool
        Where the light changed across the region, fit the frame again with each block's own
        gain and offset (see the module's docstring); False: one gain and offset for the
        region in every frame.
    presmooth_px : float
        The standard deviation (px) of the Gaussian both frames are smoothed with before the
        fit (0: none; see the module's docstring). The texture's strength
        (:attr:`gradient_rms`) is that of the frame as it is, whatever this is.
    """

    def __init__(self, reference: np.ndarray, rows: np.ndarray, cols: np.ndarray, *,
                 bias_correction: bool = True, max_points: int = MAX_POINTS,
                 tolerance_px: float = TOLERANCE_PX, presmooth_px: float = 0.0,
                 rounding_floor: bool = True, local_light: bool = True) -> None:
        if not (np.isfinite(presmooth_px) and presmooth_px >= 0):
            raise ValueError(f"presmooth_px must be a number >= 0, got {presmooth_px!r}")
        rows = np.asarray(rows, np.intp)
        cols = np.asarray(cols, np.intp)
        if rows.shape != cols.shape or rows.ndim != 1 or rows.size < 8:
            raise ValueError(f"a region fit needs at least 8 pixels, got {rows.size}")
        self.shape = reference.shape
        self.x0, self.y0 = float(cols.mean()), float(rows.mean())
        self.scale = max(float(np.ptp(cols)), float(np.ptp(rows)), 1.0) / 2.0
        step = int(np.ceil(rows.size / max_points))
        self.tolerance_px = tolerance_px
        self.presmooth_px = float(presmooth_px)
        rows, cols = rows[::step], cols[::step]
        self.rows, self.cols = rows, cols
        # Filters run on the region's bounding box plus their reach, not on the whole frame.
        height, width = reference.shape
        pad = 8 + int(np.ceil(4 * self.presmooth_px))  # the filters' reach, the smoothing's too
        r0, c0 = max(int(rows.min()) - pad, 0), max(int(cols.min()) - pad, 0)
        r1, c1 = min(int(rows.max()) + pad + 1, height), min(int(cols.max()) + pad + 1, width)
        ref = reference[r0:r1, c0:c1].astype(np.float64)
        local_rows, local_cols = rows - r0, cols - c0
        fitted = self._smoothed(ref)
        self.rounding_spread = rounding_spread(reference[r0:r1, c0:c1], self.presmooth_px) if rounding_floor else 0.0
        fx = ndimage.correlate1d(fitted, _DERIVATIVE, axis=1, mode="nearest")[local_rows, local_cols]
        fy = ndimage.correlate1d(fitted, _DERIVATIVE, axis=0, mode="nearest")[local_rows, local_cols]
        self._dx = (cols - self.x0) / self.scale
        self._dy = (rows - self.y0) / self.scale
        f = fitted[local_rows, local_cols]
        self._f = f - f.mean()
        self._f_norm = float(np.sqrt(np.sum(self._f ** 2)))
        self._jacobian = np.column_stack([fx, fx * self._dx, fx * self._dy, fy, fy * self._dx, fy * self._dy])
        # Blocks of CLUSTER_PX pixels: the clusters of the uncertainty (see _sigma).
        self._cluster = _blocks(rows, cols, CLUSTER_PX)
        # The blocks of a light that changed across the region (see fit): the reference and the
        # steepest-descent images less each block's mean (the criterion's zero-mean reference
        # and its derivative).
        self._grey = abs(float(f.mean()))
        self._gain_block = _blocks(rows, cols, int(np.ceil(GAIN_BLOCK_PX * np.sqrt(step)))) if local_light else None
        if self._gain_block is not None:
            self._f_local = _centred(f, self._gain_block)
            self._jacobian_local = _centred(self._jacobian, self._gain_block)
        # STRIPS strips across the region's longer extent: the reproducibility check (see _sigma).
        along = self._dx if np.ptp(cols) >= np.ptp(rows) else self._dy
        self._strip = np.minimum(((along - along.min()) / max(np.ptp(along), 1e-9) * STRIPS).astype(np.intp),
                                 STRIPS - 1)
        self.textured = self._f_norm > 0 and bool(np.all(np.isfinite(self._jacobian)))
        self.bias_correction = bias_correction
        self._reference = reference if bias_correction else None  # for the bias curve (see bias)
        self._bias_coefficients: np.ndarray | None = None
        # The texture's strength: the rms grey-level gradient over the region (the reference
        # smoothed over a pixel, so that sensor noise does not count), along x and y.
        smooth = ndimage.gaussian_filter(ref, 1.0)
        self._smooth_gradient = np.column_stack([
            ndimage.correlate1d(smooth, _DERIVATIVE, axis=axis, mode="nearest")[local_rows, local_cols]
            for axis in (1, 0)])
        self.gradient_rms = self.gradient_rms_of(np.ones(rows.size, bool))

    def _smoothed(self, image: np.ndarray) -> np.ndarray:
        """``image`` (float64, a part of a frame) smoothed by :attr:`presmooth_px` (as it is at 0)."""
        if self.presmooth_px <= 0:
            return image
        return ndimage.gaussian_filter(image, self.presmooth_px, mode="nearest")

    def gradient_rms_of(self, keep: np.ndarray) -> tuple[float, float]:
        """The texture's strength (see :attr:`gradient_rms`) over the fit's pixels ``keep``
        (bool over :attr:`rows`, :attr:`cols`); 0 where none is kept."""
        kept = self._smooth_gradient[np.asarray(keep, bool)]
        if kept.size == 0:
            return 0.0, 0.0
        return tuple(float(x) for x in np.sqrt(np.mean(kept ** 2, axis=0)))

    def gradient_rms_along(self, keep: np.ndarray, direction: np.ndarray) -> float:
        """The texture's strength in one ``direction`` (a unit (x, y) vector): the rms of its
        smoothed gradient's component along it over the fit's pixels ``keep``; 0 where none is kept."""
        kept = self._smooth_gradient[np.asarray(keep, bool)]
        if kept.size == 0:
            return 0.0
        return float(np.sqrt(np.mean((kept @ np.asarray(direction, np.float64)) ** 2)))

    def field(self, params: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The displacement ``(u, v)`` the affine ``params`` give at the pixels (float64)."""
        dx = (np.asarray(cols, np.float64) - self.x0) / self.scale
        dy = (np.asarray(rows, np.float64) - self.y0) / self.scale
        u, ux, uy, v, vx, vy = params
        return u + ux * dx + uy * dy, v + vx * dx + vy * dy

    def params_from_flow(self, u: np.ndarray, v: np.ndarray, rows: np.ndarray,
                         cols: np.ndarray) -> np.ndarray | None:
        """The affine least-squares fit of a flow's ``(u, v)`` at the pixels (a starting warp);
        None where the flow has too few finite values."""
        ok = np.isfinite(u) & np.isfinite(v)
        if ok.sum() < 8:
            return None
        dx = (np.asarray(cols, np.float64)[ok] - self.x0) / self.scale
        dy = (np.asarray(rows, np.float64)[ok] - self.y0) / self.scale
        design = np.column_stack([np.ones_like(dx), dx, dy])
        cu = np.linalg.lstsq(design, u[ok].astype(np.float64), rcond=None)[0]
        cv = np.linalg.lstsq(design, v[ok].astype(np.float64), rcond=None)[0]
        return np.array([cu[0], cu[1], cu[2], cv[0], cv[1], cv[2]])

    def _window(self, xs: np.ndarray, ys: np.ndarray) -> tuple[int, int, int, int]:
        """The part of the frame the positions ``xs``, ``ys`` sample, with its margins."""
        height, width = self.shape
        pad = WINDOW_MARGIN_PX + 2 * SPLINE_ORDER
        r0 = int(np.clip(np.floor(ys.min()) - pad, 0, height - 1))
        r1 = int(np.clip(np.ceil(ys.max()) + pad + 1, r0 + 1, height))
        c0 = int(np.clip(np.floor(xs.min()) - pad, 0, width - 1))
        c1 = int(np.clip(np.ceil(xs.max()) + pad + 1, c0 + 1, width))
        return r0, r1, c0, c1

    def _positions(self, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        u, v = self.field(params, self.rows, self.cols)
        return self.cols + u, self.rows + v

    def fit(self, current: np.ndarray, start: np.ndarray, *, keep: np.ndarray | None = None) -> RegionMotion:
        """The region's affine motion into ``current`` (same shape as the reference), from the
        starting warp ``start`` (6 params, see :class:`RegionMotion`); ``keep`` (bool over
        :attr:`rows`, :attr:`cols`; None: all) the pixels the fit may use (those a codec copied
        from the reference carry no motion: see :func:`~flow.methods.deepflow.codecfloor.codec_copies`).

        Where the affine fit does not converge (a texture that constrains the stretch no more
        than a change of contrast does: a smoothly shaded round member), the translation alone
        is fitted, the deformation kept at the start's. Where the light changed across the
        region (:meth:`light_changed`), the frame is fitted again with each block's own gain and
        offset (``light_varies`` in the result), unless that fit fails where the first did not."""
        found = self._affine_or_translation(current, start, keep, local=False)
        if found.light_varies:
            found = self._by_blocks(found, self._affine_or_translation(current, start, keep, local=True))
        return self._unbiased(found)

    @staticmethod
    def _by_blocks(whole: RegionMotion, blocks: RegionMotion) -> RegionMotion:
        """The fit block by block where it converged or the fit with one gain did not either;
        else the latter, which then says it was read with one gain (``light_varies`` False)."""
        return blocks if blocks.converged or not whole.converged else dataclasses.replace(whole, light_varies=False)

    def _affine_or_translation(self, current: np.ndarray, start: np.ndarray, keep: np.ndarray | None, *,
                               local: bool) -> RegionMotion:
        found = self._solve(current, start, _AFFINE, keep=keep, local=local)
        if not (found.converged or found.iterations == 0):
            found = self._solve(current, start, _TRANSLATION, keep=keep, local=local)
        return found

    def fit_translation(self, current: np.ndarray, start: np.ndarray, *,
                        max_iterations: int | None = None) -> RegionMotion:
        """:meth:`fit` with the translation alone free, the deformation kept at the start's, in
        at most ``max_iterations`` steps (None: the fit's own budget)."""
        if max_iterations is not None and max_iterations < 1:
            raise ValueError(f"max_iterations={max_iterations}: a fit needs at least one iteration")
        found = self._solve(current, start, _TRANSLATION, max_iterations)
        if found.light_varies:
            found = self._by_blocks(found, self._solve(current, start, _TRANSLATION, max_iterations, local=True))
        return self._unbiased(found)

    def _unbiased(self, found: RegionMotion) -> RegionMotion:
        """``found`` with the fit's own bias (see :meth:`bias`) taken off, where it is on."""
        if not (found.converged and self.bias_correction):
            return found
        bias_u, bias_v = self.bias(found.params)
        params = found.params.copy()
        params[0] -= bias_u
        params[3] -= bias_v
        return dataclasses.replace(found, params=params)

    def bias(self, params: np.ndarray) -> tuple[float, float]:
        """The fit's own systematic error (px) in the mean ``(u, v)`` for the motion ``params``:
        the bias curve measured on the reference (see :meth:`bias_curve`) at the fractional
        part of each pixel's displacement, averaged over the region."""
        coefficients = self.bias_curve()
        u, v = self.field(params, self.rows, self.cols)
        return tuple(float(np.mean(_periodic(np.mod(d, 1.0)) @ c)) for d, c in zip((u, v), coefficients, strict=True))

    def bias_curve(self, noise_grey: float = 0.0) -> np.ndarray:
        """The Fourier coefficients ``(2, 2 * BIAS_HARMONICS)`` of the fit's bias in u (against a
        shift along x) and in v (along y) as periodic functions of the shift's fractional part.

        The reference around the region, shifted exactly by each of BIAS_SHIFTS (a phase ramp:
        the band-limited image a camera would record after the motion), is fitted as any frame
        is; whatever the fit reads beyond the shift is its own error, which a cubic interpolant
        and a finite-difference gradient leave on fine texture (Schreier et al. 2000: periodic
        in the shift, zero at whole pixels; on DIC Challenge Sample 3 0.002-0.003 px at a
        quarter pixel). Measured once, on the first call."""
        if self._bias_coefficients is not None:
            return self._bias_coefficients
        coefficients = np.zeros((2, 2 * BIAS_HARMONICS))
        base = np.asarray(self._reference, np.float64)
        height, width = base.shape
        r0, c0 = max(int(self.rows.min()) - BIAS_MARGIN_PX, 0), max(int(self.cols.min()) - BIAS_MARGIN_PX, 0)
        r1 = min(int(self.rows.max()) + BIAS_MARGIN_PX + 1, height)
        c1 = min(int(self.cols.max()) + BIAS_MARGIN_PX + 1, width)
        crop = base[r0:r1, c0:c1]
        mirrored = np.pad(crop, ((0, crop.shape[0]), (0, crop.shape[1])), mode="symmetric")
        spectrum = np.fft.fft2(mirrored)
        if noise_grey > 0:  # the texture without the reference's own noise (see the docstring)
            power = np.abs(spectrum) ** 2
            spectrum = spectrum * np.maximum(0.0, 1.0 - mirrored.size * noise_grey ** 2 / np.maximum(power, 1e-30))
        fy = np.fft.fftfreq(mirrored.shape[0])[:, None]
        fx = np.fft.fftfreq(mirrored.shape[1])[None, :]
        design = _periodic(BIAS_SHIFTS)
        current = base.copy()  # the reference, its region replaced by each shifted copy
        for axis in (0, 1):  # u against shifts along x, v along y
            errors = []
            for shift in BIAS_SHIFTS:
                ramp = np.exp(-2j * np.pi * shift * (fx if axis == 0 else fy))
                moved = np.real(np.fft.ifft2(spectrum * ramp))[: crop.shape[0], : crop.shape[1]]
                current[r0:r1, c0:c1] = moved
                start = np.zeros(6)
                start[3 * axis] = shift
                found = self._solve(current, start, _AFFINE)
                if not found.converged:
                    errors = None
                    break
                errors.append(found.params[3 * axis] - shift)
            if errors is not None:
                coefficients[axis] = np.linalg.lstsq(design, np.asarray(errors), rcond=None)[0]
        self._bias_coefficients = coefficients
        return coefficients

    def _solve(self, current: np.ndarray, start: np.ndarray, free: np.ndarray,
               max_iterations: int | None = None, keep: np.ndarray | None = None, *,
               local: bool = False) -> RegionMotion:
        """The IC-GN fit (see the module's docstring) with the parameters ``free``: one gain and
        offset for the region, or (``local``) each block's own."""
        start = np.asarray(start, np.float64)
        params = start.copy()
        failed = RegionMotion(params, False, (float("nan"), float("nan")), float("nan"), 0, 0.0)
        if not self.textured or current.shape != self.shape or not np.all(np.isfinite(params)):
            return failed
        window, coeffs = None, None
        full = self._jacobian_local if local else self._jacobian
        jacobian = full[:, free]
        weights = np.ones(self.rows.size)
        error = np.zeros(self.rows.size)
        converged, iteration = False, 0
        moves: list[float] = []
        height, width = self.shape
        inside = np.ones(self.rows.size, bool)
        for iteration in range(1, (max_iterations or MAX_ITERATIONS) + 1):  # noqa: B007 (read after the loop)
            xs, ys = self._positions(params)
            if not (np.all(np.isfinite(xs)) and np.all(np.isfinite(ys))):
                return failed
            # (A pixel between the frame's edge and one beyond it would be read from the
            # spline's mirror image of the frame, not from the scene: it is out too.)
            inside = (xs >= 0) & (ys >= 0) & (xs <= width - 1) & (ys <= height - 1)
            if keep is not None:
                inside &= keep
            everywhere = bool(inside.all())
            if not everywhere:
                # Pixels the warp took out of the frame (a wall's edge as the camera drifts, a
                # member leaving the view) are left out of this step; the fit fails where fewer
                # than MIN_INSIDE of them stay (a lost or wild start).
                if inside.sum() < MIN_INSIDE * (inside.size if keep is None else int(keep.sum())):
                    return failed
                xs, ys = xs[inside], ys[inside]
            if window is None or not _inside(window, xs, ys, self.shape):
                window = self._window(xs, ys)
                r0, r1, c0, c1 = window
                coeffs = ndimage.spline_filter(self._smoothed(current[r0:r1, c0:c1].astype(np.float64)),
                                               order=SPLINE_ORDER, mode="mirror")
            r0, _, c0, _ = window
            g = ndimage.map_coordinates(coeffs, [ys - r0, xs - c0], order=SPLINE_ORDER,
                                        prefilter=False, mode="mirror")
            # The reference over the pixels in the frame (error and weight 0 elsewhere).
            part = self._residual(g, inside, everywhere, local)
            if part is None:
                return failed
            previous = weights[inside] if iteration > 1 else None
            error, weights = np.zeros(inside.size), np.zeros(inside.size)
            error[inside] = part
            weights[inside] = _tukey(part, previous, self.rounding_spread)
            weighted = jacobian * weights[:, None]
            hessian = weighted.T @ jacobian
            damped = hessian + DAMPING * np.trace(hessian) / free.size * np.eye(free.size)
            step = np.zeros(6)
            try:
                step[free] = -np.linalg.solve(damped, weighted.T @ error)
            except np.linalg.LinAlgError:
                return failed
            params = _params_of(_warp_matrix(params, self.scale) @ np.linalg.inv(_warp_matrix(step, self.scale)),
                                self.scale)
            moved = np.abs(step[0]) + np.abs(step[3]) + np.abs(step[[1, 2, 4, 5]]).sum()
            if not np.isfinite(moved):
                return failed
            if moved < self.tolerance_px:
                converged = True
                break
            moves.append(moved)
            if _out_of_budget(moves, iteration, max_iterations or MAX_ITERATIONS, self.tolerance_px,
                              first=4 if max_iterations is not None else UNBUDGETED_FIRST):
                break
        if np.hypot(params[0] - start[0], params[3] - start[3]) > MAX_TRAVEL_PX:
            return dataclasses.replace(failed, iterations=iteration)
        return RegionMotion(params, converged, self._sigma(error, weights, hessian, jacobian, full[:, [0, 3]]),
                            _robust_rms(error, weights), iteration, float(np.mean(weights > 0)),
                            float(np.sqrt(np.mean(error[inside] ** 2))),
                            local or self.light_changed(error, inside))

    def _residual(self, g: np.ndarray, inside: np.ndarray, everywhere: bool, local: bool) -> np.ndarray | None:
        """The ZNSSD residual of the region's pixels in the frame (``inside``) against the frame's
        grey levels ``g`` there: ``f - (|f| / |g|) g``, both less their mean, over the region or
        (``local``) block by block (0 in a block the frame shows flat); None where it is flat."""
        if local:
            blocks = self._gain_block if everywhere else self._gain_block[inside]
            f = self._f_local if everywhere else _centred(self._f_local[inside], blocks)
            g = _centred(g, blocks)
            g_norm = np.sqrt(_block_sums(g ** 2, blocks))
            f_norm = np.sqrt(_block_sums(f ** 2, blocks))
            # (A block the frame shows flat, a clipped one: its spline's values differ by rounding.)
            seen = g_norm > 1e-6 * f_norm
            if not seen.any():
                return None
            return np.where(seen, f - f_norm / np.where(seen, g_norm, 1.0) * g, 0.0)
        g = g - g.mean()
        g_norm = float(np.sqrt(np.sum(g ** 2)))
        if g_norm <= 0:
            return None
        if everywhere:
            f, f_norm = self._f, self._f_norm
        else:
            f = self._f[inside] - self._f[inside].mean()
            f_norm = float(np.sqrt(np.sum(f ** 2)))
        return f - (f_norm / g_norm) * g

    def light_changed(self, error: np.ndarray, inside: np.ndarray) -> bool:
        """Whether a fit with one gain for the region left the light's change across it in its
        residual ``error`` (over the region's pixels; those ``inside`` the frame count): blocks
        holding at least LIGHT_AREA of them off by an offset of at least LIGHT_STEP of the
        region's grey, most of their residual (see the constants). Never without blocks
        (``local_light=False``)."""
        if self._gain_block is None or not inside.any():
            return False
        blocks, part = self._gain_block[inside], error[inside]
        n = int(self._gain_block.max()) + 1
        count = np.bincount(blocks, minlength=n)
        mean = np.bincount(blocks, weights=part, minlength=n) / np.maximum(count, 1)
        rms = np.sqrt(np.bincount(blocks, weights=part ** 2, minlength=n) / np.maximum(count, 1))
        offset = (np.abs(mean) >= LIGHT_STEP * self._grey) & (np.abs(mean) >= LIGHT_OFFSET * rms) & (count > 0)
        return bool(count[offset].sum() >= LIGHT_AREA * part.size)

    def _sigma(self, error: np.ndarray, weights: np.ndarray, hessian: np.ndarray,
               jacobian: np.ndarray, translation: np.ndarray) -> tuple[float, float]:
        """The clustered (sandwich) covariance of the mean displacement: ``H^-1 (sum_c s_c
        s_c^T) H^-1`` with ``s_c`` the score of the pixels of block ``c``. A codec moves whole
        blocks by slightly wrong amounts, which leaves correlated residuals inside each block
        that a per-pixel variance cannot see; the blocks' scores do. ``translation``: the
        steepest-descent images of the translation (see :meth:`_strip_spread`)."""
        score = jacobian * (weights * error)[:, None]
        n_clusters = int(self._cluster.max()) + 1
        sums = np.stack([np.bincount(self._cluster, weights=score[:, k], minlength=n_clusters)
                         for k in range(score.shape[1])], axis=1)
        used = np.bincount(self._cluster, weights=weights, minlength=n_clusters) > 0
        if used.sum() < 4:
            return float("nan"), float("nan")
        meat = sums[used].T @ sums[used] * (used.sum() / (used.sum() - 1.0))
        try:
            inverse = np.linalg.inv(hessian)
        except np.linalg.LinAlgError:
            return float("nan"), float("nan")
        cov = inverse @ meat @ inverse
        v_index = 1 if jacobian.shape[1] == 2 else 3  # u, v: the first two of a translation
        sigma = np.sqrt(np.maximum([cov[0, 0], cov[v_index, v_index]], 0.0))
        return tuple(float(x) for x in np.maximum(sigma, self._strip_spread(error, weights, translation)))

    def _strip_spread(self, error: np.ndarray, weights: np.ndarray, translation: np.ndarray) -> np.ndarray:
        """The standard uncertainty of the mean translation from the scatter of the STRIPS
        strips' own translations about the fit (one Gauss-Newton step each from the fit's
        residual): a texture that a codec rebuilt differently in every frame leaves the strips
        disagreeing by far more than their pixels' residuals imply (a painted bar's faint
        texture: strips 0.2-0.4 px apart where the clustered covariance said 0.015 px)."""
        steps = []
        for strip in range(STRIPS):
            inside = (self._strip == strip) & (weights > 0)
            if inside.sum() < 8:
                continue
            part = translation[inside] * weights[inside, None]
            try:
                steps.append(-np.linalg.solve(part.T @ translation[inside], part.T @ error[inside]))
            except np.linalg.LinAlgError:
                return np.array([np.inf, np.inf])
        if len(steps) < 2:
            return np.zeros(2)
        steps = np.asarray(steps)
        return steps.std(axis=0, ddof=1) / np.sqrt(len(steps))


def affine_departure(rows: np.ndarray, cols: np.ndarray, u: np.ndarray, v: np.ndarray) -> tuple[float, float] | None:
    """How far a dense flow ``(u, v)`` at a region's pixels departs from every affine field,
    against its own noise: ``(smooth_px, fine_px)``, the rms over the region's interior of
    its departure from its own affine least-squares fit smoothed over DEFORM_SCALE_PX (a
    deformation the affine model does not hold: a sine, a bend of higher order), and the
    robust scale of the rest of the departure (the flow's pixel-scale noise). None where the
    region has too few interior pixels with a finite flow to tell.

    The departure is taken from the flow's own affine fit, not from the texture fit's: a
    difference of the two means (the dense flow's own bias) is no deformation."""
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    ok = np.isfinite(u) & np.isfinite(v)
    if ok.sum() < DEFORM_MIN_PIXELS:
        return None
    rows, cols = rows[ok], cols[ok]
    r0, c0 = int(rows.min()), int(cols.min())
    shape = (int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1)
    inside = np.zeros(shape, np.float64)
    inside[rows - r0, cols - c0] = 1.0
    interior = ndimage.distance_transform_edt(np.pad(inside, 1))[1:-1, 1:-1] > DEFORM_INSET_PX
    if interior.sum() < DEFORM_MIN_PIXELS:
        return None
    weight = ndimage.gaussian_filter(inside, DEFORM_SCALE_PX, mode="constant")
    smooth_sq = fine_sq = 0.0
    for component in (u, v):
        departure = departure_from_affine(rows, cols, np.asarray(component, np.float64)[ok])
        image = np.zeros(shape)
        image[rows - r0, cols - c0] = departure
        smooth = ndimage.gaussian_filter(image, DEFORM_SCALE_PX, mode="constant") / np.maximum(weight, 1e-12)
        smooth_sq += float(np.mean(smooth[interior] ** 2))
        # The rest's robust scale (its median absolute value, as a normal's sigma): a part of
        # the region deforming faster than the smoothing follows (a wave's shortest periods)
        # leaves its rest large there, and is no noise of the rest of the region.
        fine_sq += (MAD_TO_SIGMA * float(np.median(np.abs((image - smooth)[interior])))) ** 2
    return float(np.sqrt(smooth_sq)), float(np.sqrt(fine_sq))


def departure_from_affine(rows: np.ndarray, cols: np.ndarray, values: np.ndarray) -> np.ndarray:
    """``values`` at the pixels ``rows``, ``cols`` less their own affine least-squares fit (a
    plane in x and y: what no affine field holds)."""
    dx = (cols - cols.mean()) / max(float(np.ptp(cols)), 1.0)
    dy = (rows - rows.mean()) / max(float(np.ptp(rows)), 1.0)
    design = np.column_stack([np.ones_like(dx), dx, dy])
    return values - design @ np.linalg.lstsq(design, values, rcond=None)[0]


def _periodic(fraction: np.ndarray) -> np.ndarray:
    """The bias curve's basis at the fractional shifts: ``sin(2 pi k d)`` and ``cos(2 pi k d) - 1``
    for k = 1 .. BIAS_HARMONICS (zero at whole pixels)."""
    phase = 2.0 * np.pi * np.asarray(fraction, np.float64)[..., None] * np.arange(1, BIAS_HARMONICS + 1)
    return np.concatenate([np.sin(phase), np.cos(phase) - 1.0], axis=-1)


def _out_of_budget(moves: list[float], iteration: int, budget: int, tolerance: float, *, first: int = 4) -> bool:
    """Whether a fit whose steps shrink no faster than its last ones did (``moves``: each
    iteration's step, px) cannot reach ``tolerance`` within OUT_OF_BUDGET times its ``budget``
    of iterations. A fit on a faint texture shrinks its steps by a near-constant ratio (the
    reference's gradients mostly noise: 0.9 an iteration on the bench's painted bars), and one
    that would end unconverged at its budget is stopped once it shows it: from the fourth step
    on, the first with three ratios to judge by (before 2026-12-05 never before half the
    budget: on the bench's painted bars 65 of 90 such fits of lowtex-wide ran 10 steps where 4
    tell; the 16 bench clips' outputs byte-identical, 48 synthetic fits converging after 7-20
    steps none cut, see tests/unit/test_regionfit.py). Judged from step ``first`` on (at least
    the fourth: three ratios; see UNBUDGETED_FIRST)."""
    if iteration < max(first, 4):
        return False  # three ratios of steps, at least
    ratio = min(moves[-k] / max(moves[-k - 1], 1e-300) for k in (1, 2, 3))
    if not 0.0 < ratio < 1.0:
        return False  # not shrinking: as the budget decides
    return iteration + np.log(tolerance / moves[-1]) / np.log(ratio) > OUT_OF_BUDGET * budget


def _inside(window: tuple[int, int, int, int], xs: np.ndarray, ys: np.ndarray,
            shape: tuple[int, ...]) -> bool:
    """Whether the cut-out ``window`` still holds the positions with the spline's margin; a side
    where the window already reaches the frame's edge needs none (cutting it again would give the
    same window there: a region marked up to the edge was filtered again every step)."""
    r0, r1, c0, c1 = window
    height, width = shape[:2]
    pad = SPLINE_ORDER
    return bool((c0 == 0 or xs.min() >= c0 + pad) and (c1 == width or xs.max() <= c1 - 1 - pad)
                and (r0 == 0 or ys.min() >= r0 + pad) and (r1 == height or ys.max() <= r1 - 1 - pad))


# At most this many of a frame's values are looked at for their grid (see rounding_spread).
GRID_SAMPLE = 200_000


def rounding_spread(image: np.ndarray, presmooth_px: float = 0.0) -> float:
    """The standard deviation (grey levels) that rounding ``image`` and a frame like it to
    their grey-level step leaves in their difference, after both are smoothed by a Gaussian of
    ``presmooth_px``: ``step / sqrt(6)`` (two independent uniform rounding errors) times the
    smoothing's noise gain. The step: 1 for frames of whole grey levels (8-bit video), else the
    smallest spacing of ``image``'s distinct values (a 10-16-bit camera's brought to the 8-bit
    scale by a gain: that gain, found on a regular sample of GRID_SAMPLE of them), never more
    than 1 (a frame of few levels is no coarser camera); 0 where the values are not on a grid
    (float frames made by a program)."""
    image = np.asarray(image)
    if np.issubdtype(image.dtype, np.integer) or np.array_equal(image, np.rint(image)):
        step = 1.0
    else:
        values = np.unique(image.ravel()[:: max(1, image.size // GRID_SAMPLE)].astype(np.float64))
        gaps = np.diff(values)
        step = float(gaps.min()) if gaps.size else 0.0
        # On a grid only where every gap is a whole number of the smallest one (to float32's
        # rounding of the gain's multiples).
        if not (step > 0 and np.allclose(gaps / step, np.rint(gaps / step), atol=0.05)):
            return 0.0
        step = min(step, 1.0)
    gain = 1.0
    if presmooth_px > 0:  # the kernel of RegionFit._smoothed, from its response to one pixel
        impulse = np.zeros(2 * int(4.0 * presmooth_px + 0.5) + 1)
        impulse[impulse.size // 2] = 1.0
        kernel = ndimage.gaussian_filter1d(impulse, presmooth_px, mode="constant")
        gain = float(np.sum(kernel ** 2))  # per axis sqrt(sum k^2); the 2-D filter their product
    return step / np.sqrt(6.0) * gain


def _blocks(rows: np.ndarray, cols: np.ndarray, side: int) -> np.ndarray:
    """Each pixel's block of ``side`` px (numbered 0.. over the blocks that hold a pixel)."""
    block_rows = (rows - rows.min()) // side
    block_cols = (cols - cols.min()) // side
    return np.unique(block_rows * (int(block_cols.max()) + 1) + block_cols, return_inverse=True)[1].ravel()


def _block_sums(values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """Sums of ``values`` ((N,) or (N, K)) over each block, indexed back to its pixels."""
    n = int(blocks.max()) + 1
    if values.ndim == 1:
        return np.bincount(blocks, weights=values, minlength=n)[blocks]
    return np.stack([np.bincount(blocks, weights=values[:, k], minlength=n) for k in range(values.shape[1])],
                    axis=1)[blocks]


def _centred(values: np.ndarray, blocks: np.ndarray) -> np.ndarray:
    """``values`` ((N,) or (N, K)) less their block's mean."""
    counts = np.bincount(blocks)[blocks].astype(np.float64)
    return values - _block_sums(values, blocks) / (counts if values.ndim == 1 else counts[:, None])


def _tukey(error: np.ndarray, previous: np.ndarray | None, floor: float = 0.0) -> np.ndarray:
    """Tukey's biweights of the residuals, scaled by their median absolute deviation (of the
    pixels kept so far), no less than ``floor`` (grey levels: see :func:`rounding_spread`)."""
    base = error if previous is None else error[previous > 0]
    scale = MAD_TO_SIGMA * float(np.median(np.abs(base - np.median(base)))) if base.size else 0.0
    scale = max(scale, floor)
    if not scale > 0:
        return np.ones_like(error)
    z = error / (TUKEY_C * scale)
    return np.where(np.abs(z) < 1.0, (1.0 - z ** 2) ** 2, 0.0)


def _robust_rms(error: np.ndarray, weights: np.ndarray) -> float:
    total = float(weights.sum())
    return float(np.sqrt(np.sum(weights * error ** 2) / total)) if total > 0 else float("nan")
