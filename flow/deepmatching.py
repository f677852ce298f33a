"""DeepMatching: hierarchical deformable dense matching (clean-room).

Written from the description in Revaud et al. (IJCV 2016) and the summary in
the refflow paper (section 3.4); no code of the original was used.

Pipeline
--------
1. Pixel descriptors: the image is pre-smoothed, its gradient projected on 8
   orientations and rectified (``max(0, .)``), each orientation map smoothed
   again and passed through a power non-linearity.
2. Atomic patches of 4x4 pixels (128 values) on a non-overlapping grid are
   correlated (normalised dot product) with every 4x4 patch of the other image
   within ``ngh_rad`` pixels. The response maps are kept in *displacement*
   space, ``C(p, d)``: patch ``p`` matched to ``p + d``.
3. Bottom-up aggregation: each response map is max-pooled (3x3), subsampled by
   two and the four children of a patch twice as large averaged at the parent's
   displacement, followed by the power rectification ``x -> x**1.4``
   (patch sizes 8, 16, 32, ... up to ``max_patch``).
4. Top-down backtracking from the best response of each top-level patch: every
   child follows the maximum that max-pooling selected, down to the atomic
   patches; an atomic patch keeps the path with the best accumulated score.
5. Reciprocal verification: matches are kept only when the backward matching
   (current to reference) maps them back to where they started.

Work is done on an image downscaled by ``downscale`` (2 by default, as in the
original), with numba kernels parallel over the patch grid.

References
----------
.. [1] J. Revaud, P. Weinzaepfel, Z. Harchaoui, C. Schmid, "DeepMatching:
   Hierarchical Deformable Dense Matching", IJCV 120(3), 2016.
.. [2] P. Weinzaepfel et al., "DeepFlow: Large displacement optical flow with
   deep matching", ICCV 2013.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit, prange

ATOMIC = 4  # atomic patch side in (downscaled) pixels
N_ORIENT = 8


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`deep_matching`.

    downscale : int
        Integer factor the images are reduced by before matching (1 = none).
    ngh_rad : float
        Search radius in full-resolution pixels (``<= 0``: whole image, slow).
    max_patch : int
        Largest patch side in downscaled pixels (4 * 2**levels).
    presmooth_sigma, desc_sigma : float
        Gaussian smoothing before the gradient and of each orientation map.
    desc_power : float
        Power non-linearity of the orientation maps.
    aggregation_power : float
        Rectification exponent applied after each aggregation (1.4).
    reciprocal : bool
        Keep only forward-backward consistent matches.
    reciprocal_tol : float
        Allowed forward-backward mismatch in downscaled pixels.
    min_score : float
        Drop atomic matches whose normalised correlation is below this.
    """

    downscale: int = 2
    ngh_rad: float = 32.0
    max_patch: int = 32
    presmooth_sigma: float = 1.0
    desc_sigma: float = 1.0
    desc_power: float = 0.5
    aggregation_power: float = 1.4
    reciprocal: bool = True
    reciprocal_tol: float = 3.0
    min_score: float = 0.0


@dataclass
class MatchGrid:
    """Quasi-dense matches on the atomic-patch grid, in full-resolution pixels.

    ``x``, ``y``: patch centres in the reference; ``dx``, ``dy``: displacement;
    ``score``: normalised atomic correlation in [0, 1] (0 where ``valid`` is False).
    """

    x: np.ndarray
    y: np.ndarray
    dx: np.ndarray
    dy: np.ndarray
    score: np.ndarray
    valid: np.ndarray
    spacing: float
    offset: float

    def as_array(self) -> np.ndarray:
        """Valid matches as rows ``x1, y1, x2, y2, score`` (DeepMatching's output order)."""
        m = self.valid
        return np.stack(
            [self.x[m], self.y[m], self.x[m] + self.dx[m], self.y[m] + self.dy[m], self.score[m]],
            axis=1,
        ).astype(np.float32)


def pixel_descriptors(image: np.ndarray, params: MatchParams) -> np.ndarray:
    """Per-pixel oriented-gradient descriptors, shape (H, W, 8), float32."""
    im = image.astype(np.float32)
    if params.presmooth_sigma > 0:
        im = cv2.GaussianBlur(im, (0, 0), params.presmooth_sigma)
    gx = cv2.Sobel(im, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    gy = cv2.Sobel(im, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    out = np.empty(im.shape + (N_ORIENT,), np.float32)
    for k in range(N_ORIENT):
        theta = 2.0 * math.pi * k / N_ORIENT
        proj = np.maximum(math.cos(theta) * gx + math.sin(theta) * gy, 0.0)
        if params.desc_sigma > 0:
            proj = cv2.GaussianBlur(proj, (0, 0), params.desc_sigma)
        out[..., k] = proj
    np.power(out, params.desc_power, out=out)
    return out


def _patch_norms(desc: np.ndarray) -> np.ndarray:
    """L2 norm of every 4x4 patch of ``desc``, indexed by its top-left pixel."""
    sq = np.einsum("yxc,yxc->yx", desc, desc, dtype=np.float64)
    ii = np.zeros((sq.shape[0] + 1, sq.shape[1] + 1), np.float64)
    ii[1:, 1:] = sq.cumsum(0).cumsum(1)
    a = ATOMIC
    s = ii[a:, a:] - ii[:-a, a:] - ii[a:, :-a] + ii[:-a, :-a]
    return np.sqrt(np.maximum(s, 0.0)).astype(np.float32)


@njit(parallel=True, cache=True, fastmath=True)
def _atomic_responses(f1, f2, n1, n2, ny, nx, R):
    # Rows of a 4x4 patch of 8-orientation descriptors are 32 contiguous
    # floats; a fixed-length inner loop lets LLVM vectorise the dot product.
    H, W, C = f2.shape
    row = 4 * N_ORIENT
    g1 = f1.reshape(H, W * C)
    g2 = f2.reshape(H, W * C)
    D = 2 * R + 1
    out = np.zeros((ny, nx, D, D), np.float32)
    for gi in prange(ny):
        y0 = 4 * gi
        patch = np.empty((4, row), np.float32)
        for gj in range(nx):
            x0 = 4 * gj
            na = n1[y0, x0]
            if na <= 1e-6:
                continue
            for a in range(4):
                for t in range(row):
                    patch[a, t] = g1[y0 + a, x0 * C + t]
            for kd in range(D):
                ty = y0 + kd - R
                if ty < 0 or ty + 4 > H:
                    continue
                for ke in range(D):
                    tx = x0 + ke - R
                    if tx < 0 or tx + 4 > W:
                        continue
                    nb = n2[ty, tx]
                    if nb <= 1e-6:
                        continue
                    s = np.float32(0.0)
                    base = tx * C
                    for a in range(4):
                        for t in range(row):
                            s += patch[a, t] * g2[ty + a, base + t]
                    out[gi, gj, kd, ke] = s / (na * nb)
    return out


@njit(parallel=True, cache=True, fastmath=True)
def _pool_subsample(child):
    ny, nx, Df, _ = child.shape
    Rf = Df // 2
    Rc = Rf // 2
    Dc = 2 * Rc + 1
    out = np.zeros((ny, nx, Dc, Dc), np.float32)
    for i in prange(ny):
        for j in range(nx):
            for kc in range(Dc):
                k = Rf + 2 * (kc - Rc)
                for lc in range(Dc):
                    kx = Rf + 2 * (lc - Rc)
                    m = np.float32(0.0)
                    for a in range(max(k - 1, 0), min(k + 2, Df)):
                        for b in range(max(kx - 1, 0), min(kx + 2, Df)):
                            v = child[i, j, a, b]
                            if v > m:
                                m = v
                    out[i, j, kc, lc] = m
    return out


@njit(cache=True)
def _children(level, i, j, ny, nx):
    """Child grid cells (at level - 1) of cell (i, j) at ``level``; -1 when outside."""
    ci = np.full(4, -1, np.int64)
    cj = np.full(4, -1, np.int64)
    if level == 1:
        # Level-1 patches sit between four atomic patches.
        di = (0, 1, 0, 1)
        dj = (0, 0, 1, 1)
    else:
        o = 1 << (level - 2)
        di = (-o, o, -o, o)
        dj = (-o, -o, o, o)
    for n in range(4):
        a = i + di[n]
        b = j + dj[n]
        if 0 <= a < ny and 0 <= b < nx:
            ci[n] = a
            cj[n] = b
    return ci, cj


@njit(parallel=True, cache=True, fastmath=True)
def _aggregate(pooled, level, power, out_ny, out_nx):
    ny, nx, D, _ = pooled.shape
    out = np.zeros((out_ny, out_nx, D, D), np.float32)
    for i in prange(out_ny):
        for j in range(out_nx):
            ci, cj = _children(level, i, j, ny, nx)
            cnt = 0
            for n in range(4):
                if ci[n] >= 0:
                    cnt += 1
            if cnt == 0:
                continue
            inv = np.float32(1.0 / cnt)
            for k in range(D):
                for kx in range(D):
                    s = np.float32(0.0)
                    for n in range(4):
                        if ci[n] >= 0:
                            s += pooled[ci[n], cj[n], k, kx]
                    out[i, j, k, kx] = (s * inv) ** power
    return out


@njit(cache=True)
def _top_candidates(top):
    ny, nx, D, _ = top.shape
    n = ny * nx
    ci = np.empty(n, np.int64)
    cj = np.empty(n, np.int64)
    ck = np.empty(n, np.int64)
    cl = np.empty(n, np.int64)
    cs = np.empty(n, np.float32)
    for i in range(ny):
        for j in range(nx):
            best = np.float32(-1.0)
            bk = 0
            bl = 0
            for k in range(D):
                for kx in range(D):
                    if top[i, j, k, kx] > best:
                        best = top[i, j, k, kx]
                        bk = k
                        bl = kx
            m = i * nx + j
            ci[m] = i
            cj[m] = j
            ck[m] = bk
            cl[m] = bl
            cs[m] = best
    return ci, cj, ck, cl, cs


@njit(cache=True)
def _descend(child, level, ci, cj, ck, cl, cs):
    """Follow each candidate at ``level`` into its four children at ``level - 1``."""
    ny, nx, Df, _ = child.shape
    Rf = Df // 2
    Rc = Rf // 2
    n = ci.shape[0]
    oi = np.full(4 * n, -1, np.int64)
    oj = np.full(4 * n, -1, np.int64)
    ok = np.zeros(4 * n, np.int64)
    ol = np.zeros(4 * n, np.int64)
    osc = np.zeros(4 * n, np.float32)
    for m in range(n):
        if ci[m] < 0:
            continue
        chi, chj = _children(level, ci[m], cj[m], ny, nx)
        k0 = Rf + 2 * (ck[m] - Rc)
        l0 = Rf + 2 * (cl[m] - Rc)
        for c in range(4):
            if chi[c] < 0:
                continue
            best = np.float32(-1.0)
            bk = k0
            bl = l0
            for a in range(max(k0 - 1, 0), min(k0 + 2, Df)):
                for b in range(max(l0 - 1, 0), min(l0 + 2, Df)):
                    v = child[chi[c], chj[c], a, b]
                    if v > best:
                        best = v
                        bk = a
                        bl = b
            q = 4 * m + c
            oi[q] = chi[c]
            oj[q] = chj[c]
            ok[q] = bk
            ol[q] = bl
            osc[q] = cs[m] + best
    return oi, oj, ok, ol, osc


@njit(cache=True)
def _best_per_cell(resp0, ci, cj, ck, cl, cs):
    ny, nx, D, _ = resp0.shape
    R = D // 2
    best = np.full((ny, nx), -1.0, np.float32)
    dy = np.zeros((ny, nx), np.float32)
    dx = np.zeros((ny, nx), np.float32)
    corr = np.zeros((ny, nx), np.float32)
    for m in range(ci.shape[0]):
        i = ci[m]
        j = cj[m]
        if i < 0 or cs[m] <= best[i, j]:
            continue
        best[i, j] = cs[m]
        k = ck[m]
        kx = cl[m]
        # Parabolic sub-pixel refinement on the atomic response.
        sy = 0.0
        sx = 0.0
        if 0 < k < D - 1:
            a = resp0[i, j, k - 1, kx]
            b = resp0[i, j, k, kx]
            c = resp0[i, j, k + 1, kx]
            den = a - 2.0 * b + c
            if den < 0.0:
                sy = min(max(0.5 * (a - c) / den, -0.5), 0.5)
        if 0 < kx < D - 1:
            a = resp0[i, j, k, kx - 1]
            b = resp0[i, j, k, kx]
            c = resp0[i, j, k, kx + 1]
            den = a - 2.0 * b + c
            if den < 0.0:
                sx = min(max(0.5 * (a - c) / den, -0.5), 0.5)
        dy[i, j] = k - R + sy
        dx[i, j] = kx - R + sx
        corr[i, j] = resp0[i, j, k, kx]
    return dx, dy, corr, best


def _n_levels(max_patch: int) -> int:
    levels = 0
    size = ATOMIC
    while size * 2 <= max_patch:
        size *= 2
        levels += 1
    return levels


def _match_one_way(f1, f2, radius, params):
    """Grid matches from descriptors f1 to f2 (downscaled pixels)."""
    H, W, _ = f1.shape
    ny, nx = H // ATOMIC, W // ATOMIC
    n1 = _patch_norms(f1)
    n2 = _patch_norms(f2)
    resp = [_atomic_responses(f1, f2, n1, n2, ny, nx, int(radius))]
    levels = _n_levels(params.max_patch)
    shapes = [(ny, nx)]
    for level in range(1, levels + 1):
        cny, cnx = shapes[-1]
        out_ny, out_nx = (cny - 1, cnx - 1) if level == 1 else (cny, cnx)
        if out_ny < 1 or out_nx < 1 or resp[-1].shape[2] < 5:
            break
        pooled = _pool_subsample(resp[-1])
        resp.append(_aggregate(pooled, level, float(params.aggregation_power), out_ny, out_nx))
        shapes.append((out_ny, out_nx))
        del pooled
    top = len(resp) - 1
    ci, cj, ck, cl, cs = _top_candidates(resp[top])
    for level in range(top, 0, -1):
        ci, cj, ck, cl, cs = _descend(resp[level - 1], level, ci, cj, ck, cl, cs)
    dx, dy, corr, _ = _best_per_cell(resp[0], ci, cj, ck, cl, cs)
    return dx, dy, corr


def _centres(n: int) -> np.ndarray:
    return ATOMIC * np.arange(n, dtype=np.float32) + (ATOMIC - 1) / 2.0


def deep_matching(
    reference: np.ndarray, current: np.ndarray, params: MatchParams | None = None
) -> MatchGrid:
    """Quasi-dense matches from ``reference`` to ``current``.

    Parameters
    ----------
    reference, current : ndarray (H, W), uint8 or float32
    params : MatchParams, optional

    Returns
    -------
    MatchGrid
        One match per atomic patch (``valid`` marks the verified ones).
    """
    params = params or MatchParams()
    if params.downscale < 1 or int(params.downscale) != params.downscale:
        raise ValueError(f"downscale must be a positive integer, got {params.downscale!r}")
    ds = int(params.downscale)
    im1 = reference.astype(np.float32)
    im2 = current.astype(np.float32)
    if ds > 1:
        h, w = im1.shape[0] // ds, im1.shape[1] // ds
        im1 = cv2.resize(im1[: h * ds, : w * ds], (w, h), interpolation=cv2.INTER_AREA)
        im2 = cv2.resize(im2[: h * ds, : w * ds], (w, h), interpolation=cv2.INTER_AREA)
    if min(im1.shape) < 2 * ATOMIC:
        raise ValueError(
            f"image {reference.shape[1]}x{reference.shape[0]} is too small to match at downscale {ds}"
        )
    f1 = np.ascontiguousarray(pixel_descriptors(im1, params))
    f2 = np.ascontiguousarray(pixel_descriptors(im2, params))
    H, W = im1.shape
    radius = params.ngh_rad / ds if params.ngh_rad > 0 else max(H, W)
    radius = int(math.ceil(min(radius, max(H, W))))
    dx, dy, corr = _match_one_way(f1, f2, radius, params)
    ny, nx = dx.shape
    valid = corr > params.min_score
    cy = _centres(ny)[:, None] * np.ones((1, nx), np.float32)
    cx = np.ones((ny, 1), np.float32) * _centres(nx)[None, :]
    if params.reciprocal:
        bdx, bdy, bcorr = _match_one_way(f2, f1, radius, params)
        ty = cy + dy
        tx = cx + dx
        bi = np.clip(np.rint((ty - (ATOMIC - 1) / 2.0) / ATOMIC).astype(np.int64), 0, ny - 1)
        bj = np.clip(np.rint((tx - (ATOMIC - 1) / 2.0) / ATOMIC).astype(np.int64), 0, nx - 1)
        # Back from the backward patch nearest to the target, corrected for its offset.
        back_y = ty + bdy[bi, bj]
        back_x = tx + bdx[bi, bj]
        err = np.hypot(back_y - cy, back_x - cx)
        valid &= (err <= params.reciprocal_tol) & (bcorr[bi, bj] > 0)
    score = np.where(valid, np.clip(corr, 0.0, 1.0), 0.0).astype(np.float32)
    spacing = float(ATOMIC * ds)
    return MatchGrid(
        x=((cx + 0.5) * ds - 0.5).astype(np.float32),
        y=((cy + 0.5) * ds - 0.5).astype(np.float32),
        dx=(dx * ds).astype(np.float32),
        dy=(dy * ds).astype(np.float32),
        score=score,
        valid=valid,
        spacing=spacing,
        offset=float((((ATOMIC - 1) / 2.0) + 0.5) * ds - 0.5),
    )


def densify(
    grid: MatchGrid, shape: tuple[int, int], *, nearest: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Dense flow and weight maps from grid matches.

    Invalid grid cells take the flow of the nearest valid one; the flow is then
    interpolated bilinearly (``nearest=False``) or by nearest neighbour between
    patch centres. The weight map is the match score of the nearest patch
    (0 where that patch has no verified match).

    Returns
    -------
    flow : ndarray (H, W, 2) float32
    weight : ndarray (H, W) float32
    """
    from scipy import ndimage

    height, width = shape
    dx = grid.dx.copy()
    dy = grid.dy.copy()
    if not grid.valid.any():
        return np.zeros((height, width, 2), np.float32), np.zeros((height, width), np.float32)
    if not grid.valid.all():
        _, (ii, jj) = ndimage.distance_transform_edt(~grid.valid, return_indices=True)
        dx = dx[ii, jj]
        dy = dy[ii, jj]
    xs = (np.arange(width, dtype=np.float32) - grid.offset) / grid.spacing
    ys = (np.arange(height, dtype=np.float32) - grid.offset) / grid.spacing
    map_x, map_y = np.meshgrid(xs, ys)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    fx = cv2.remap(dx, map_x, map_y, interp, borderMode=cv2.BORDER_REPLICATE)
    fy = cv2.remap(dy, map_x, map_y, interp, borderMode=cv2.BORDER_REPLICATE)
    weight = cv2.remap(grid.score, map_x, map_y, cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
    return np.dstack([fx, fy]).astype(np.float32), weight.astype(np.float32)
