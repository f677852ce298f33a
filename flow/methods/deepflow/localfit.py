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
at wavelengths well beyond the window is taken off (Sample 14's gain 0.975 / 0.896 / 0.800 ->
0.993 / 0.995 / 0.973 on L1 / L3 / L5),
while at wavelengths within the window the dense field stays nearly as it was (one step, not
iterated to the windowed estimate's own fixed point, which would add its noise there).

* The frame is interpolated with a cubic B-spline (bicubic convolution biases sub-pixel
  shifts of fine speckle by a few hundredths of a pixel: the gain of this step with OpenCV's
  cubic remap was 0.78-0.81).
* Both frames are smoothed by :data:`PRESMOOTH_PX` first: the noise's variance under an
  interpolant depends on the sub-pixel position and pulls a least-squares estimate towards
  half-pixel shifts (gain 1.01-1.02 without it on Sample 14).
* The reference's gradient is that of its own B-spline interpolant (a central difference of the
  samples reads fine speckle's slope short, and the step long).
* Each window fits a brightness offset and gain with the motion (auto-exposure, flicker).
* A window whose texture does not fix both directions (stripes, a flat patch's noise), one
  with too few POIs, and a step longer than :data:`MAX_STEP_PX` keep the dense field.

The window's width is then chosen by the data (:func:`refine_adaptively`): a wider window
(12-32 px) averages more noise out of each POI's motion and reads short deformations shorter;
the widest whose field reads the region's deformation within 2 % of the base window's is kept
(Sample 14 L1 / L3 / L5, column means: 0.0035 / 0.0037 / 0.0049 px at 8 px -> 0.0026 / 0.0029
/ 0.0044 at 32 / 16 / 12 px; the Stars, whose cosines reach 10 px periods, keep 8 px).

Each corrected POI's standard uncertainty (``with_sigma``) is its window's least-squares
covariance: the window's residual variance after the step times the inverse of its normal
matrix, times the ratio of the window's squared weights to its weights (the effective number of
pixels a Gaussian window holds), times the presmoothing's correlation of neighbouring residuals
(the inverse of its kernel's squared weights: the smoothed noise's sum over a window varies as
the raw noise's). A POI whose dense field stays has none (NaN).

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

from flow.measure.robust import MAD_TO_SIGMA
from flow.methods.deepflow.regionfit import departure_from_affine

# The Gaussian window's standard deviation, px (Sample 14, the default through the CLI: L1 / L3 /
# L5 column-mean RMSE 0.0035 / 0.0037 / 0.0049 px, gain 0.993 / 0.995 / 0.973; a first version
# without offset and gain, in a script: 16 px 0.0034 / 0.0036 / 0.0067, L5 gain 0.971, a wider
# window leaving more of the shorter periods to the dense field; 12 px 0.0035 / 0.0036 / 0.0052).
WINDOW_PX = 8.0
PRESMOOTH_PX = 0.7
SPLINE_ORDER = 3
SPLINE_MODE = "mirror"  # the same at the spline's prefilter and its evaluation
# Windows holding less than this share of a full window's weight in POIs (a POI at a thin
# mask's edge) keep the dense field.
MIN_COVER = 0.2
# A window's texture must fix both directions: the structure tensor's smaller eigenvalue at least
# MIN_GRADIENT grey levels per px squared (per unit of the window's weight) and MIN_ISOTROPY of
# the larger one (stripes read 0.09 px RMS across themselves without it, a flat patch's noise
# 0.085 px).
MIN_GRADIENT = 1.0
MIN_ISOTROPY = 0.01
# A step longer than this (px, either axis) is not the correction of a converged dense field:
# the dense field stays.
MAX_STEP_PX = 0.5
SOLVE_CHUNK = 65536  # POIs whose 4x4 systems are solved at once
# Rows of the POIs' bounding box whose POIs are corrected at once (see refine_locally).
BAND_ROWS = 512


def refine_locally(reference: np.ndarray, current: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                   u: np.ndarray, v: np.ndarray, *, window_px: float = WINDOW_PX, with_sigma: bool = False
                   ) -> tuple[np.ndarray, ...]:
    """The POIs' motion ``(u, v)`` (px, at ``rows``, ``cols`` of the reference) after one
    windowed least-squares step from the dense field ``u``, ``v`` (see the module's notes).
    Where a POI's window holds too little texture in either direction or too few POIs, where
    its step would be longer than :data:`MAX_STEP_PX`, or where the frame is sampled outside
    its bounds, the dense field stays. ``with_sigma``: also each POI's standard uncertainty
    ``(sigma_u, sigma_v)`` (px; NaN where the dense field stays)."""
    u = np.asarray(u, np.float64)
    v = np.asarray(v, np.float64)
    finite = np.isfinite(u) & np.isfinite(v)
    if finite.sum() < 3:
        return (u, v, np.full(u.shape, np.nan), np.full(v.shape, np.nan)) if with_sigma else (u, v)
    height, width = reference.shape
    pad = int(np.ceil(3 * window_px)) + 2
    reach = int(np.ceil(np.nanmax(np.abs(np.concatenate([u[finite], v[finite]]))))) + 4
    top, left = max(int(rows.min()) - pad, 0), max(int(cols.min()) - pad, 0)
    bottom, right = min(int(rows.max()) + pad + 1, height), min(int(cols.max()) + pad + 1, width)
    ref = _smoothed(reference[top:bottom, left:right]).astype(np.float64)
    # The frame over the box plus the motion's reach (where the POIs' pixels come from).
    c_top, c_left = max(top - reach, 0), max(left - reach, 0)
    c_bottom, c_right = min(bottom + reach, height), min(right + reach, width)
    coef = ndimage.spline_filter(_smoothed(current[c_top:c_bottom, c_left:c_right]).astype(np.float64),
                                 order=SPLINE_ORDER, mode=SPLINE_MODE)
    r, c = rows - top, cols - left
    # The reference's gradient is its own interpolant's (a central difference of the samples
    # reads fine speckle's slope short and the step long: 7 % on Sample 14, 20 % on 1 px speckle).
    gy, gx = np.gradient(ndimage.spline_filter(ref, order=SPLINE_ORDER, mode=SPLINE_MODE))
    box = _Box(ref, gx, gy, coef, (c_top - top, c_left - left), float(np.mean(ref[r, c])), window_px)
    out_u, out_v = u.copy(), v.copy()
    sigma = np.full((len(r), 2), np.nan) if with_sigma else None
    # The POIs in bands of BAND_ROWS rows of the box, each with the POIs within the windows'
    # reach of it (their sums are the whole box's, to the bit): a whole 4K frame's 8 M POIs held
    # their dozens of per-POI arrays at once (2.8 GB).
    halo = int(np.ceil(4.0 * window_px)) + 2  # OpenCV's Gaussian kernel reaches 4 sigma
    order = np.argsort(r, kind="stable")
    sorted_rows = r[order]
    for b0 in range(0, ref.shape[0], BAND_ROWS):
        b1 = min(b0 + BAND_ROWS, ref.shape[0])
        g0, g1 = max(b0 - halo, 0), min(b1 + halo, ref.shape[0])
        if b0 == 0 and b1 == ref.shape[0]:
            near = np.arange(len(r))
        else:
            near = order[np.searchsorted(sorted_rows, g0):np.searchsorted(sorted_rows, g1)]
        own = (r[near] >= b0) & (r[near] < b1)
        if not own.any():
            continue
        found = box.step(r[near], c[near], u[near], v[near], finite[near], (g0, g1), own, with_sigma)
        kept = near[own]
        out_u[kept], out_v[kept] = found[0], found[1]
        if with_sigma:
            sigma[kept] = found[2]
    if not with_sigma:
        return out_u, out_v
    return out_u, out_v, sigma[:, 0], sigma[:, 1]


class _Box:
    """The reference (smoothed), its interpolant's gradient and the frame's B-spline coefficients
    over the POIs' bounding box (see :func:`refine_locally`), and the step of any of its POIs."""

    def __init__(self, ref: np.ndarray, gx: np.ndarray, gy: np.ndarray, coef: np.ndarray,
                 coef_offset: tuple[int, int], ref_mean: float, window_px: float) -> None:
        self.ref, self.gx, self.gy, self.coef = ref, gx, gy, coef
        self.coef_offset, self.ref_mean, self.window_px = coef_offset, ref_mean, window_px

    def step(self, r: np.ndarray, c: np.ndarray, u: np.ndarray, v: np.ndarray, finite: np.ndarray,
             rows: tuple[int, int], own: np.ndarray, with_sigma: bool) -> tuple[np.ndarray, ...]:
        """The corrected ``(u, v)`` (and ``(N, 2)`` sigmas) of the POIs ``own`` of these (at box
        rows ``r``, columns ``c``), whose windows hold no POI beyond these; the windowed sums are
        taken on the box's ``rows`` (first, stop) alone."""
        ref, coef, window_px = self.ref, self.coef, self.window_px
        level = ref[r, c] - self.ref_mean
        basis = (self.gx[r, c], self.gy[r, c], np.ones(len(r)), level)
        ys = r + np.where(finite, v, 0.0) - self.coef_offset[0]
        xs = c + np.where(finite, u, 0.0) - self.coef_offset[1]
        inside = finite & (xs >= 0) & (ys >= 0) & (xs <= coef.shape[1] - 1) & (ys <= coef.shape[0] - 1)
        warped = ndimage.map_coordinates(coef, [ys, xs], order=SPLINE_ORDER, prefilter=False, mode=SPLINE_MODE)
        error = np.where(inside, warped - ref[r, c], 0.0)
        used = inside.astype(np.float64)
        g0, g1 = rows
        grid_r = r - g0
        every = bool(own.all())
        picked = slice(None) if every else np.flatnonzero(own)
        at = (grid_r, c) if every else (grid_r[picked], c[picked])

        def window(values: np.ndarray, sigma_px: float = window_px) -> np.ndarray:
            grid = np.zeros((g1 - g0, ref.shape[1]), np.float32)
            grid[grid_r, c] = values
            return cv2.GaussianBlur(grid, (0, 0), sigma_px)[at]

        # Each window's least squares of the error on the motion and a brightness offset and gain
        # (auto-exposure, flicker: a 5 % gain left 0.036 px RMS on a 0.3 px shift without them).
        # The windowed sums are kept in float32, one array per entry, and the systems solved in
        # chunks: a 3000x400 member's 1.2 M POIs cost tens of MB, not a (N, 4, 4) float64 stack.
        n = len(basis)
        pairs = [(i, j) for i in range(n) for j in range(i, n)]
        sums = {pair: window(used * basis[pair[0]] * basis[pair[1]]) for pair in pairs}
        rhs = [window(used * b * error) for b in basis]
        a11, a12, a22, cover = sums[0, 0], sums[0, 1], sums[1, 1], sums[2, 2]
        # Texture in both directions: the structure tensor's smaller eigenvalue at least
        # MIN_GRADIENT^2 per unit of the window's weight and MIN_ISOTROPY of the larger (stripes,
        # a flat patch's noise: the dense field stays).
        trace, det = a11.astype(np.float64) + a22, a11.astype(np.float64) * a22 - a12.astype(np.float64) * a12
        smaller = 0.5 * (trace - np.sqrt(np.maximum(trace * trace - 4 * det, 0.0)))
        good = (inside[picked] & (cover >= MIN_COVER) & (smaller >= MIN_GRADIENT ** 2 * np.maximum(cover, 1e-12))
                & (smaller >= MIN_ISOTROPY * (trace - smaller)))
        count = len(at[0])
        step = np.zeros((count, 2))
        if with_sigma:
            variance = np.full((count, 2), np.nan)
            squares = window(used * error * error).astype(np.float64)
            # The window's squared weights (a Gaussian's square is the Gaussian of sigma / sqrt 2).
            weight2 = window(used, window_px / np.sqrt(2.0)) / (4.0 * np.pi * window_px ** 2)
        chosen = np.flatnonzero(good)
        for start in range(0, chosen.size, SOLVE_CHUNK):
            part = chosen[start:start + SOLVE_CHUNK]
            system = np.empty((part.size, n, n))
            for i, j in pairs:
                system[:, i, j] = system[:, j, i] = sums[i, j][part]
            right = np.stack([b[part] for b in rhs], axis=1).astype(np.float64)
            if with_sigma:
                # With the step, the inverse's first two columns (one factorization for all
                # three right-hand sides: a separate inverse cost a third of the step's time).
                unit = np.zeros((part.size, n, 2))
                unit[:, 0, 0] = unit[:, 1, 1] = 1.0
                solved = np.linalg.solve(system, np.concatenate([right[..., None], unit], axis=2))
                solution = solved[..., 0]
            else:
                solution = np.linalg.solve(system, right[..., None])[..., 0]
            step[part] = solution[:, :2]
            if with_sigma:
                # The residual's weighted variance after the step, and the step's covariance.
                rss = np.maximum(squares[part] - np.sum(solution * right, axis=1), 0.0)
                cover_part = cover[part].astype(np.float64)
                scale = rss / cover_part * (weight2[part] / cover_part) / _KERNEL_SQUARES
                variance[part, 0] = scale * solved[:, 0, 1]
                variance[part, 1] = scale * solved[:, 1, 2]
        good &= (np.abs(step[:, 0]) <= MAX_STEP_PX) & (np.abs(step[:, 1]) <= MAX_STEP_PX)
        mine_u, mine_v = u[picked], v[picked]
        out = (np.where(good, mine_u - step[:, 0], mine_u), np.where(good, mine_v - step[:, 1], mine_v))
        return out + (np.where(good[:, None], np.sqrt(variance), np.nan),) if with_sigma else out


# The wider windows a deforming region's field is tried at, px, in order (see
# refine_adaptively), and the most a wider window may read the field's departure from its affine
# fit short of the base window's (least squares gain of the base on the wider one, minus 1).
WIDER_WINDOWS_PX = (12.0, 16.0, 24.0, 32.0)
MAX_ATTENUATION = 0.02
# A local feature the wider window smoothed away (see _keep_local_features): the two fields'
# difference more than FEATURE_MADS robust deviations above its median over the region (Sample 14:
# 6.9 at most by the noise alone; a 0.3 px bump of 12 px on a 0.3 px sine: 16), the base field
# kept where the standing-out POIs fill FEATURE_SHARE of a 16 px Gaussian neighbourhood and more.
FEATURE_MADS = 8.0
FEATURE_SHARE = 0.1


def refine_adaptively(reference: np.ndarray, current: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                      base: tuple[np.ndarray, ...], *, with_sigma: bool = False
                      ) -> tuple[tuple[np.ndarray, ...], float]:
    """The widest window the field's own deformation allows, and the POIs' motion read there.

    ``base`` is :func:`refine_locally`'s result at :data:`WINDOW_PX` (``with_sigma`` alike). A
    wider window averages more of the frames' noise into each POI's motion (Sample 14's 0.1 px
    sine of periods near 700 px, L1: 0.014 px per pixel at 8 px, 0.005 at 32 px), and reads a
    deformation whose wavelength is near the window's short (its L5, periods down to 50 px: gain
    0.98 at 12 px, 0.96 at 16 px, 0.83 at 24 px). The data choose: a window of
    :data:`WIDER_WINDOWS_PX` reads the field from the base field smoothed over that window (a
    normalized Gaussian over the POIs: its wavelengths within the window are the noise's) and
    one step of that window's least squares (see :func:`refine_locally`), the base field kept
    near the region's edge (see :func:`_inset`); it is acceptable where the base field's
    departure from its own affine fit, regressed on the wider field's, has a gain of at most
    1 + :data:`MAX_ATTENUATION` (a wider field that reads the deformation short has a gain above
    1; the noise it takes off adds to it too, so that a field whose deformation hardly shows
    above its noise keeps the base window). The widest is tried first (a smooth field: one
    try), then the others by bisection, a wider window taken to read a deformation no better
    than a narrower one. Returns the kept result and its window (px)."""
    rows = np.asarray(rows, np.intp)
    cols = np.asarray(cols, np.intp)
    depth = _depth(rows, cols)
    # (Only windows some POI lies deep enough to be read through alone: see _inset.)
    windows = [w for w in WIDER_WINDOWS_PX if float(depth.max()) >= 2.0 * w]
    kept, window = base, WINDOW_PX
    low, high = -1, len(windows)  # windows[low] acceptable (-1: the base), windows[high] not
    trial = high - 1
    while low + 1 < high:
        wider = windows[trial]
        start = [_smoothed_over(rows, cols, base[k], wider) for k in (0, 1)]
        # (Its sigma tells where its step was taken: see _inset.)
        read = refine_locally(reference, current, rows, cols, *start, window_px=wider, with_sigma=True)
        found = _inset(depth, base, read if with_sigma else read[:2], np.isfinite(read[2]), wider)
        if attenuation(rows, cols, base[:2], found[:2]) <= 1.0 + MAX_ATTENUATION:
            low, kept, window = trial, found, wider
        else:
            high = trial
        trial = (low + high) // 2
    if window > WINDOW_PX:
        kept = _keep_local_features(rows, cols, base, kept)
    return kept, window


def _keep_local_features(rows: np.ndarray, cols: np.ndarray, base: tuple[np.ndarray, ...],
                         wider: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """``wider`` with ``base`` kept about a local feature it smoothed away: where the two
    fields' difference (smoothed over the base window) stands out of its own spread over the
    region by more than FEATURE_MADS robust deviations (a strain concentration, a bump, a
    crack: the region-wide gain test does not see a feature that is a small share of the
    region's deformation), and over the wider window's reach about it (see FEATURE_SHARE)."""
    difference = np.hypot(*(_smoothed_over(rows, cols, base[k] - wider[k], WINDOW_PX) for k in (0, 1)))
    ok = np.isfinite(difference)
    if ok.sum() < 16:
        return wider
    middle = float(np.median(difference[ok]))
    spread = MAD_TO_SIGMA * float(np.median(np.abs(difference[ok] - middle)))
    standing_out = ok & (difference > middle + FEATURE_MADS * max(spread, 1e-6))
    if not standing_out.any():
        return wider
    reach = _smoothed_over(rows, cols, standing_out.astype(np.float64), 2.0 * WINDOW_PX)
    base_share = np.clip(reach / FEATURE_SHARE, 0.0, 1.0)
    return _blend(base, wider, 1.0 - base_share)


def _depth(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Each POI's distance (px) to the nearest pixel outside the region (a hole's included)."""
    r0, c0 = int(rows.min()), int(cols.min())
    inside = np.zeros((int(rows.max()) - r0 + 3, int(cols.max()) - c0 + 3), bool)
    inside[rows - r0 + 1, cols - c0 + 1] = True
    return ndimage.distance_transform_edt(inside)[rows - r0 + 1, cols - c0 + 1]


def _inset(depth: np.ndarray, base: tuple[np.ndarray, ...], wider: tuple[np.ndarray, ...],
           stepped: np.ndarray, window_px: float) -> tuple[np.ndarray, ...]:
    """``wider`` (read through windows of ``window_px``) where a POI lies (``depth``, px) at
    least twice that inside the region, ``base`` within twice the base window of its edge, and
    between the two in proportion: a window cut by the edge averages the field on one side of
    its POI, and reads a slope there short by the slope times the distance it reaches in (a
    0.3 px sine of 400 px period at 24 px: 0.09 px at the edge; its column means' RMSE 0.0072 px
    against 0.0054 so inset, the base window's 0.0066). ``base`` wherever the wider window took
    no step (``stepped`` False: too few POIs or too little texture in it, a step too long):
    there ``wider`` holds its start, the base field smoothed over the window, no reading. Where
    both are blended, their sigmas (if given) are blended alike (NaN where either has none)."""
    near, far = 2.0 * WINDOW_PX, 2.0 * window_px
    share = np.where(stepped, np.clip((depth - near) / (far - near), 0.0, 1.0), 0.0)
    return _blend(base, wider, share)


def _blend(base: tuple[np.ndarray, ...], wider: tuple[np.ndarray, ...], share: np.ndarray) -> tuple[np.ndarray, ...]:
    """``wider`` in ``share`` (0-1 per POI) and ``base`` in the rest, entry by entry (either
    alone where its share is whole: the other's NaN does not leak in)."""
    return tuple(np.where(share >= 1.0, w, np.where(share <= 0.0, b, share * w + (1.0 - share) * b))
                 for b, w in zip(base, wider, strict=True))


def attenuation(rows: np.ndarray, cols: np.ndarray, field: tuple[np.ndarray, np.ndarray],
                smoother: tuple[np.ndarray, np.ndarray]) -> float:
    """The least-squares gain of ``field``'s departure from its own affine fit (u and v
    together) on ``smoother``'s: 1 where ``smoother`` reads every deformation ``field`` shows
    (its noise aside), above 1 where it reads them short. NaN where either has no departure."""
    ok = np.ones(len(rows), bool)
    for values in (*field, *smoother):
        ok &= np.isfinite(values)
    if ok.sum() < 4:
        return float("nan")
    product = square = 0.0
    for a, b in zip(field, smoother, strict=True):
        a, b = (departure_from_affine(rows[ok], cols[ok], np.asarray(x, np.float64)[ok]) for x in (a, b))
        product += float(a @ b)
        square += float(b @ b)
    return product / square if square > 0 else float("nan")


def _smoothed_over(rows: np.ndarray, cols: np.ndarray, values: np.ndarray, sigma_px: float) -> np.ndarray:
    """``values`` at the POIs smoothed by a Gaussian of ``sigma_px`` normalized over the POIs
    whose value is finite (the mask's edge and a hole take no weight)."""
    values = np.asarray(values, np.float64)
    ok = np.isfinite(values)
    out = values.copy()
    if not ok.any():
        return out
    r0, c0 = int(rows.min()), int(cols.min())
    shape = (int(rows.max()) - r0 + 1, int(cols.max()) - c0 + 1)
    total = np.zeros(shape, np.float32)
    weight = np.zeros(shape, np.float32)
    total[rows[ok] - r0, cols[ok] - c0] = values[ok]
    weight[rows[ok] - r0, cols[ok] - c0] = 1.0
    total = cv2.GaussianBlur(total, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    weight = cv2.GaussianBlur(weight, (0, 0), sigma_px, borderType=cv2.BORDER_CONSTANT)
    at = (rows[ok] - r0, cols[ok] - c0)
    out[ok] = total[at] / np.maximum(weight[at], 1e-12)
    return out


def _smoothed(image: np.ndarray) -> np.ndarray:
    return cv2.GaussianBlur(np.asarray(image, np.float32), (0, 0), PRESMOOTH_PX)


def _kernel_squares() -> float:
    """The sum of the squared weights of the presmoothing's 2-D kernel (its impulse response)."""
    impulse = np.zeros((33, 33), np.float32)
    impulse[16, 16] = 1.0
    return float(np.sum(_smoothed(impulse).astype(np.float64) ** 2))


_KERNEL_SQUARES = _kernel_squares()
