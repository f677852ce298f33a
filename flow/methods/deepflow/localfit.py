"""A deforming region's dense flow corrected by a windowed least-squares step at every POI.

Where a region's texture is strong and the dense flow shows it deforming beyond any affine
field (a speckled specimen under a non-uniform strain, see ``_deforms`` in
:mod:`flow.methods.deepflow.method`), the default reads the dense DeepMatching + DeepFlow field
itself. Its smoothness term is balanced against a data term whose strength grows with the
motion's contrast: a small deformation (a tenth of a pixel) is pulled towards the smoothest
field and read short, however long its wavelength (the DIC Challenge's Sample 14, a 0.1 px
sine with periods from 870 px down to 100 px: gain 0.975 on its longest periods, 0.80 on its
shortest; a 0.5 px cosine of the Star images is read within 10 % down to periods of 26-31 px).

The correction here is linear in the motion: a Gauss-Newton step of the brightness-constancy
criterion in a Gaussian window of :data:`WINDOW_PX` around every POI (an inverse-compositional
Lucas-Kanade step over the POIs only, so that no background pixel enters a window at the
mask's edge), from the dense field. Its frequency response is the window's: the field's error
at wavelengths well beyond the window is taken off (Sample 14's gain 0.80-0.975 -> 0.999-1.015),
while at wavelengths within the window the dense field stays nearly as it was (one step, not
iterated to the windowed estimate's own fixed point, which would add its noise there).

* The frame is interpolated with a cubic B-spline (bicubic convolution biases sub-pixel
  shifts of fine speckle by a few hundredths of a pixel: the gain of this step with OpenCV's
  cubic remap was 0.78-0.81).
* Both frames are smoothed by :data:`PRESMOOTH_PX` first: the noise's variance under an
  interpolant depends on the sub-pixel position and pulls a least-squares estimate towards
  half-pixel shifts (gain 1.01-1.02 without it on Sample 14).

References
----------
.. [1] B. D. Lucas, T. Kanade, "An iterative image registration technique with an application to
   stereo vision", IJCAI 1981.
.. [2] S. Baker, I. Matthews, "Lucas-Kanade 20 years on: a unifying framework", IJCV 56, 2004.
.. [3] P. L. Reu et al., "DIC Challenge: developing images and guidelines for evaluating
   accuracy and resolution of 2D analyses", Exp. Mech. 58, 2018 (Sample 14).
"""

from __future__ import annotations

import cv2
import numpy as np
from scipy import ndimage

# The Gaussian window's standard deviation, px (Sample 14 with one step from the dense field:
# 8 px: L1 / L3 / L5 column-mean RMSE 0.0037 / 0.0040 / 0.0047 px, gain 1.007 / 1.015 / 0.999;
# 16 px: 0.0034 / 0.0036 / 0.0067, gain 1.022 / 1.018 / 0.971, a wider window leaving more of
# the shorter periods to the dense field).
WINDOW_PX = 8.0
PRESMOOTH_PX = 0.7
SPLINE_ORDER = 3
# Windows holding less than this share of a full window's weight in POIs (a POI at a thin
# mask's edge) keep the dense field.
MIN_COVER = 0.2


def refine_locally(reference: np.ndarray, current: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                   u: np.ndarray, v: np.ndarray, *, window_px: float = WINDOW_PX
                   ) -> tuple[np.ndarray, np.ndarray]:
    """The POIs' motion ``(u, v)`` (px, at ``rows``, ``cols`` of the reference) after one
    windowed least-squares step from the dense field ``u``, ``v`` (see the module's notes).
    Where a POI's window holds too little texture or too few POIs, or the frame is sampled
    outside its bounds, the dense field stays."""
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    finite = np.isfinite(u) & np.isfinite(v)
    if finite.sum() < 3:
        return u, v
    height, width = reference.shape
    pad = int(np.ceil(3 * window_px)) + 2
    reach = int(np.ceil(np.nanmax(np.abs(np.concatenate([u[finite], v[finite]]))))) + 4
    top, left = max(int(rows.min()) - pad, 0), max(int(cols.min()) - pad, 0)
    bottom, right = min(int(rows.max()) + pad + 1, height), min(int(cols.max()) + pad + 1, width)
    ref = _smoothed(reference[top:bottom, left:right])
    # The frame over the box plus the motion's reach (where the POIs' pixels come from).
    c_top, c_left = max(top - reach, 0), max(left - reach, 0)
    c_bottom, c_right = min(bottom + reach, height), min(right + reach, width)
    coef = ndimage.spline_filter(_smoothed(current[c_top:c_bottom, c_left:c_right]).astype(np.float64),
                                 order=SPLINE_ORDER)
    r, c = rows - top, cols - left
    gy, gx = np.gradient(ref)
    gx_p, gy_p = gx[r, c].astype(np.float64), gy[r, c].astype(np.float64)
    ys = rows + np.where(finite, v, 0.0) - c_top
    xs = cols + np.where(finite, u, 0.0) - c_left
    inside = finite & (xs >= 0) & (ys >= 0) & (xs <= coef.shape[1] - 1) & (ys <= coef.shape[0] - 1)
    warped = ndimage.map_coordinates(coef, [ys, xs], order=SPLINE_ORDER, prefilter=False, mode="nearest")
    error = np.where(inside, warped - ref[r, c], 0.0)
    used = inside.astype(np.float64)

    def window(values: np.ndarray) -> np.ndarray:
        grid = np.zeros(ref.shape, np.float64)
        grid[r, c] = values
        return cv2.GaussianBlur(grid, (0, 0), window_px)[r, c]

    a11, a12, a22 = window(used * gx_p * gx_p), window(used * gx_p * gy_p), window(used * gy_p * gy_p)
    b1, b2 = window(gx_p * error), window(gy_p * error)
    cover = window(used)
    det = a11 * a22 - a12 * a12
    # A window whose texture fixes both directions (the smaller eigenvalue of its structure
    # tensor not vanishing against the larger) and that holds enough POIs.
    trace = a11 + a22
    good = inside & (cover >= MIN_COVER) & (det > 1e-6 * trace * trace) & (trace > 0)
    safe = np.where(good, det, 1.0)
    du = (a22 * b1 - a12 * b2) / safe
    dv = (a11 * b2 - a12 * b1) / safe
    return np.where(good, u - du, u), np.where(good, v - dv, v)


def _smoothed(image: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), PRESMOOTH_PX)
