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
original), with numba kernels. The atomic correlations of both directions
come from one set of per-pixel descriptor products (see :func:`_atomic_both`);
the two halves of that work, then the two directions' aggregation and
backtracking, run side by side on two threads.

References
----------
.. [1] J. Revaud, P. Weinzaepfel, Z. Harchaoui, C. Schmid, "DeepMatching:
   Hierarchical Deformable Dense Matching", IJCV 120(3), 2016.
.. [2] P. Weinzaepfel et al., "DeepFlow: Large displacement optical flow with
   deep matching", ICCV 2013.
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from functools import partial

import cv2
import numpy as np
from numba import njit

from flow.methods.deepflow.checks import check_grey_pair
from flow.methods.params import bounds, check_fields, flag

# The kernels keep IEEE arithmetic (no fastmath): with LLVM free to reassociate sums, a freshly
# compiled kernel and the same kernel loaded from numba's cache gave different bytes, so the
# first run on a fresh machine differed from every later one (tests/unit/test_determinism.py).

ATOMIC = 4  # atomic patch side in (downscaled) pixels
N_ORIENT = 8


# The default search radius: this share of the image's longer side, at least MIN_RADIUS px.
REACH = 0.1
MIN_RADIUS = 32.0


@dataclass(frozen=True)
class MatchParams:
    """Parameters of :func:`deep_matching`.

    downscale : int
        Integer factor the images are reduced by before matching (1 = none).
    ngh_rad : float or None
        Search radius in full-resolution pixels (0: the whole image, matched at a coarser
        downscale where its memory needs it, refused where even downscale 8 would pass the
        budget, see :func:`flow.methods.deepflow.method._match_at`). None (the
        default) scales it with the image: :data:`REACH` of its longer side, at least
        :data:`MIN_RADIUS` px, so that a larger view of a moving structure is searched as far
        (the ``deepflow`` method bound to a mask instead follows the member's motion, see
        :data:`flow.methods.deepflow.method.BASE_REACH_PX`).
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

    # Ranges (``refflow methods --params deepflow``): what the matching means, and what keeps
    # its cost bounded (a radius or patch beyond any frame adds nothing but work).
    downscale: int = field(default=2, metadata=bounds(1, 8, "factor the images are reduced by before matching"))
    ngh_rad: float | None = field(default=None, metadata=bounds(
        0, 10000, "search radius in full-resolution px (0: the whole image, matched coarser where "
        "its memory needs it)",
        none_means=f"deepflow with a mask: from the motion (32 px, widened where the motion passes half "
                   f"of it); a frame solved whole: {REACH:g} of its longer side, at least {MIN_RADIUS:g} px"))
    max_patch: int = field(default=32, metadata=bounds(8, 512, "largest patch side in downscaled px"))
    presmooth_sigma: float = field(default=1.0, metadata=bounds(0, 10, "Gaussian smoothing before the gradient, px"))
    desc_sigma: float = field(default=1.0, metadata=bounds(0, 10, "Gaussian smoothing of each orientation map, px"))
    desc_power: float = field(default=0.5, metadata=bounds(0, 4, "power non-linearity of the orientation maps",
                                                           low_open=True))
    aggregation_power: float = field(default=1.4, metadata=bounds(0, 4, "rectification exponent after each "
                                                                  "aggregation", low_open=True))
    reciprocal: bool = field(default=True, metadata=flag("keep only forward-backward consistent matches"))
    reciprocal_tol: float = field(default=3.0, metadata=bounds(0, 1000, "allowed forward-backward mismatch, "
                                                               "downscaled px"))
    min_score: float = field(default=0.0, metadata=bounds(0, 1, "drop atomic matches correlating below this"))

    def __post_init__(self) -> None:
        check_fields(self)


def search_radius(params: MatchParams, shape: tuple[int, ...]) -> float:
    """The search radius (full-resolution px) ``params`` give for an image of ``shape``."""
    if params.ngh_rad is None:
        return max(MIN_RADIUS, REACH * max(shape[:2]))
    return float(params.ngh_rad)


def _radius_cells(params: MatchParams, shape: tuple[int, ...]) -> tuple[int, int, int]:
    """The downscaled image's patch rows and columns and the search radius in its pixels."""
    ds = int(params.downscale)
    height, width = shape[0] // ds, shape[1] // ds
    reach = search_radius(params, shape)
    radius = reach / ds if reach > 0 else max(height, width)
    return height // ATOMIC, width // ATOMIC, int(math.ceil(min(radius, max(height, width))))


def response_bytes(shape: tuple[int, ...], params: MatchParams) -> int:
    """Bytes of the response volumes :func:`deep_matching` holds for images of ``shape``: the
    atomic responses of both directions (patches x (2 radius + 1)^2, float32) and the coarser
    levels built from them (a third more); the bulk of its memory."""
    ny, nx, radius = _radius_cells(params, shape)
    return int(2 * ny * nx * (2 * radius + 1) ** 2 * 4 * 4 // 3)


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


def _descriptor_planes(image: np.ndarray, params: MatchParams) -> np.ndarray:
    """Per-pixel oriented-gradient descriptors as planes, shape (8, H, W), float32."""
    im = image.astype(np.float32)
    if params.presmooth_sigma > 0:
        im = cv2.GaussianBlur(im, (0, 0), params.presmooth_sigma)
    gx = cv2.Sobel(im, cv2.CV_32F, 1, 0, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    gy = cv2.Sobel(im, cv2.CV_32F, 0, 1, ksize=1, borderType=cv2.BORDER_REPLICATE) * 0.5
    out = np.empty((N_ORIENT,) + im.shape, np.float32)
    for k in range(N_ORIENT):
        theta = 2.0 * math.pi * k / N_ORIENT
        proj = np.maximum(math.cos(theta) * gx + math.sin(theta) * gy, 0.0)
        if params.desc_sigma > 0:
            proj = cv2.GaussianBlur(proj, (0, 0), params.desc_sigma)
        out[k] = proj
    np.power(out, params.desc_power, out=out)
    return out


def _patch_norms(planes: np.ndarray) -> np.ndarray:
    """L2 norm of every 4x4 patch of the descriptor ``planes``, indexed by its top-left pixel."""
    sq = np.einsum("cyx,cyx->yx", planes, planes, dtype=np.float64)
    ii = np.zeros((sq.shape[0] + 1, sq.shape[1] + 1), np.float64)
    ii[1:, 1:] = sq.cumsum(0).cumsum(1)
    a = ATOMIC
    s = ii[a:, a:] - ii[:-a, a:] - ii[a:, :-a] + ii[:-a, :-a]
    return np.sqrt(np.maximum(s, 0.0)).astype(np.float32)


# Response maps are stored displacement-major, ``C[i, k, l, j]`` for the grid
# cell (i, j) and displacement (k - R, l - R): a displacement's responses for
# a row of cells are contiguous, which makes pooling and aggregation unit-stride
# loops that LLVM vectorises.


@njit(cache=True, error_model="numpy", nogil=True)
def _accumulate_products(f1, f2, y, ty, R, fsum, bsum, add_f, add_b):
    """Add (or, starting a block, write) the products of row ``y`` of ``f1`` and ``ty`` of ``f2``.

    For each dx = ke - R, ``<f1[:, y, x], f2[:, ty, x + dx]>`` goes to
    ``fsum[ke, x]`` and ``bsum[ke, x]`` wherever both pixels exist.
    """
    W = f1.shape[2]
    a0, a1, a2, a3 = f1[0, y], f1[1, y], f1[2, y], f1[3, y]
    a4, a5, a6, a7 = f1[4, y], f1[5, y], f1[6, y], f1[7, y]
    for ke in range(2 * R + 1):
        dx = ke - R
        x1 = max(0, -dx)
        x2 = x1 + dx
        fs = fsum[ke, x1:]
        bs = bsum[ke, x1:]
        c0, c1, c2, c3 = a0[x1:], a1[x1:], a2[x1:], a3[x1:]
        c4, c5, c6, c7 = a4[x1:], a5[x1:], a6[x1:], a7[x1:]
        b0, b1, b2, b3 = f2[0, ty, x2:], f2[1, ty, x2:], f2[2, ty, x2:], f2[3, ty, x2:]
        b4, b5, b6, b7 = f2[4, ty, x2:], f2[5, ty, x2:], f2[6, ty, x2:], f2[7, ty, x2:]
        for i in range(min(W, W - dx) - x1):
            p = (
                c0[i] * b0[i]
                + c1[i] * b1[i]
                + c2[i] * b2[i]
                + c3[i] * b3[i]
                + c4[i] * b4[i]
                + c5[i] * b5[i]
                + c6[i] * b6[i]
                + c7[i] * b7[i]
            )
            fs[i] = fs[i] + p if add_f else p
            bs[i] = bs[i] + p if add_b else p


@njit(cache=True, error_model="numpy", nogil=True)
def _normalised_block_sums(rows, x0, n1_row, x1, n2_row, x2, count, out):
    """``out[j]``: sum of ``rows[x0 + 4j .. + 3]`` over the norms at ``n1_row[x1 + 4j]``, ``n2_row[x2 + 4j]``."""
    tiny = np.float32(1e-6)
    for j in range(count):
        x = x0 + 4 * j
        s = rows[x] + rows[x + 1] + rows[x + 2] + rows[x + 3]
        na = n1_row[x1 + 4 * j]
        nb = n2_row[x2 + 4 * j]
        out[j] = s / (na * nb) if (na > tiny and nb > tiny) else 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def _atomic_both(f1, f2, n1, n2, R, kd0, kd1, fwd, bwd):
    """Atomic responses of both directions from one pass over the displacements.

    ``f1``, ``f2`` are descriptor planes (8, H, W). The per-pixel product
    ``P_d(y, x) = <f1(y, x), f2(y + dy, x + dx)>`` summed over a 4x4 block is
    the forward correlation of the reference patch at that block when the
    block is on the reference's grid, and the backward correlation (current
    to reference, displacement -d) of the current frame's grid patch at
    ``(y + dy, x + dx)`` when that is on the current frame's grid. Both come
    from the same products, which halves the multiply-adds. For one dy the
    two rows multiplied stay in L1 while dx runs over the window, and the
    products are summed straight into per-block column sums.

    Fills the rows dy = kd - R, kd0 <= kd < kd1, of the forward and backward
    response maps ``fwd``, ``bwd`` (zeroed, each (ny, D, D, nx) with
    D = 2R + 1) with correlations normalised by the patch norms; entries
    whose window leaves the image or whose patch is blank stay 0.
    """
    H, W = f1.shape[1], f1.shape[2]
    ny, D, _, nx = fwd.shape
    # Column sums over the 4 rows of each forward / backward block, per dx;
    # rows below the last grid row go to a spare block.
    fsum = np.empty((ny + 1, D, W), np.float32)
    bsum = np.empty((ny + 1, D, W), np.float32)
    for kd in range(kd0, kd1):
        dy = kd - R
        for y in range(max(0, -dy), min(H, H - dy)):
            gi = min(y // 4, ny)
            qi = min((y + dy) // 4, ny)
            _accumulate_products(
                f1, f2, y, y + dy, R, fsum[gi], bsum[qi], y % 4 != 0, (y + dy) % 4 != 0
            )
        for ke in range(D):
            dx = ke - R
            # Forward: reference patch (gi, gj), window at (4 gi + dy, 4 gj + dx).
            gj_lo = max(0, (3 - dx) // 4)
            gj_hi = min(nx, (W - 4 - dx) // 4 + 1)
            for gi in range(ny):
                if 0 <= 4 * gi + dy and 4 * gi + dy + 4 <= H and gj_hi > gj_lo:
                    _normalised_block_sums(
                        fsum[gi, ke], 4 * gj_lo, n1[4 * gi], 4 * gj_lo, n2[4 * gi + dy],
                        4 * gj_lo + dx, gj_hi - gj_lo, fwd[gi, kd, ke, gj_lo:],
                    )  # fmt: skip
            # Backward: current patch (qi, qj), window in the reference at
            # (4 qi - dy, 4 qj - dx), stored at the displacement -d.
            qj_lo = max(0, (dx + 3) // 4)
            qj_hi = min(nx, (W - 4 + dx) // 4 + 1)
            for qi in range(ny):
                y0 = 4 * qi - dy
                if 0 <= y0 and y0 + 4 <= H and qj_hi > qj_lo:
                    _normalised_block_sums(
                        bsum[qi, ke], 4 * qj_lo - dx, n1[y0], 4 * qj_lo - dx, n2[4 * qi],
                        4 * qj_lo, qj_hi - qj_lo, bwd[qi, D - 1 - kd, D - 1 - ke, qj_lo:],
                    )  # fmt: skip


@njit(cache=True, error_model="numpy", nogil=True)
def _pool_subsample(child):
    """3x3 max-pooling of the displacements, subsampled by two.

    Also returns where each maximum came from (``a * D + b`` for the child's
    displacement (a, b), the first one in scan order on ties), which the
    backtracking follows.
    """
    ny, Df, _, nx = child.shape
    Rf = Df // 2
    Rc = Rf // 2
    Dc = 2 * Rc + 1
    out = np.empty((ny, Dc, Dc, nx), np.float32)
    arg = np.empty((ny, Dc, Dc, nx), np.int32)
    for i in range(ny):
        for kc in range(Dc):
            k = Rf + 2 * (kc - Rc)
            for lc in range(Dc):
                kx = Rf + 2 * (lc - Rc)
                o = out[i, kc, lc]
                g = arg[i, kc, lc]
                a0 = max(k - 1, 0)
                b0 = max(kx - 1, 0)
                o[:] = child[i, a0, b0]
                g[:] = a0 * Df + b0
                for a in range(a0, min(k + 2, Df)):
                    for b in range(b0, min(kx + 2, Df)):
                        r = child[i, a, b]
                        code = np.int32(a * Df + b)
                        for j in range(nx):
                            better = r[j] > o[j]
                            o[j] = r[j] if better else o[j]
                            g[j] = code if better else g[j]
    return out, arg


@njit(cache=True, nogil=True)
def _child_offsets(level):
    """Row and column offsets of the four children (at level - 1) of a level's cell."""
    if level == 1:
        # Level-1 patches sit between four atomic patches.
        return (0, 1, 0, 1), (0, 0, 1, 1)
    o = 1 << (level - 2)
    return (-o, o, -o, o), (-o, -o, o, o)


@njit(cache=True, nogil=True)
def _children(level, i, j, ny, nx):
    """Child grid cells (at level - 1) of cell (i, j) at ``level``; -1 when outside."""
    di, dj = _child_offsets(level)
    ci = np.full(4, -1, np.int64)
    cj = np.full(4, -1, np.int64)
    for n in range(4):
        a = i + di[n]
        b = j + dj[n]
        if 0 <= a < ny and 0 <= b < nx:
            ci[n] = a
            cj[n] = b
    return ci, cj


@njit(cache=True, error_model="numpy", nogil=True)
def _power(x, p, scratch):
    """``x ** p`` in place for ``x >= 0``, in float32 to about 1e-6 relative.

    log2 and exp2 are split into exponent bits and short series on the
    mantissa, so that the loops vectorise (a libm ``powf`` per element
    would dominate the aggregation).
    """
    bits = x.view(np.int32)
    n = x.shape[0]
    mantissa = np.int32(0x007FFFFF)
    one_bits = np.int32(0x3F800000)
    for j in range(n):
        b = bits[j]
        scratch[j] = (b >> np.int32(23)) - np.int32(127)
        bits[j] = (b & mantissa) | one_bits
    sqrt2 = np.float32(1.4142135)
    half = np.float32(0.5)
    one = np.float32(1.0)
    inv_ln2 = np.float32(1.0 / math.log(2.0))
    ln2 = np.float32(math.log(2.0))
    pf = np.float32(p)
    for j in range(n):
        m = x[j]
        big = m > sqrt2
        m = m * half if big else m
        e = np.float32(scratch[j]) + (one if big else np.float32(0.0))
        # ln m = 2 atanh(s), |s| < 0.172
        s = (m - one) / (m + one)
        s2 = s * s
        ln_m = (np.float32(2.0) * s) * (
            one
            + s2
            * (
                np.float32(1.0 / 3.0)
                + s2 * (np.float32(0.2) + s2 * (np.float32(1.0 / 7.0) + s2 * np.float32(1.0 / 9.0)))
            )
        )
        y = pf * (e + ln_m * inv_ln2)
        k = np.floor(y + half)
        z = (y - k) * ln2
        # exp z, |z| < 0.35
        x[j] = one + z * (
            one
            + z
            * (
                half
                + z
                * (
                    np.float32(1.0 / 6.0)
                    + z
                    * (
                        np.float32(1.0 / 24.0)
                        + z
                        * (
                            np.float32(1.0 / 120.0)
                            + z * (np.float32(1.0 / 720.0) + z * np.float32(1.0 / 5040.0))
                        )
                    )
                )
            )
        )
        scratch[j] = np.int32(max(k, -127.0))
    for j in range(n):
        k = scratch[j]
        bits[j] = bits[j] + (k << np.int32(23)) if k > -127 else np.int32(0)


@njit(cache=True, error_model="numpy", nogil=True)
def _aggregate(pooled, level, power, out_ny, out_nx):
    """Mean of the (existing) children's pooled maps, power-rectified."""
    ny, D, _, nx = pooled.shape
    di, dj = _child_offsets(level)
    out = np.zeros((out_ny, D, D, out_nx), np.float32)
    for i in range(out_ny):
        inv = np.zeros(out_nx, np.float32)
        scratch = np.empty(out_nx, np.int32)
        for n in range(4):
            if 0 <= i + di[n] < ny:
                for j in range(max(0, -dj[n]), min(out_nx, nx - dj[n])):
                    inv[j] += 1.0
        for j in range(out_nx):
            inv[j] = 1.0 / inv[j] if inv[j] > 0 else 0.0
        for k in range(D):
            for kx in range(D):
                o = out[i, k, kx]
                for n in range(4):
                    a = i + di[n]
                    if not 0 <= a < ny:
                        continue
                    r = pooled[a, k, kx]
                    s = dj[n]
                    for j in range(max(0, -s), min(out_nx, nx - s)):
                        o[j] += r[j + s]
                for j in range(out_nx):
                    o[j] *= inv[j]
                _power(o, power, scratch)
    return out


@njit(cache=True, nogil=True)
def _top_candidates(top):
    ny, D, _, nx = top.shape
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
                    if top[i, k, kx, j] > best:
                        best = top[i, k, kx, j]
                        bk = k
                        bl = kx
            m = i * nx + j
            ci[m] = i
            cj[m] = j
            ck[m] = bk
            cl[m] = bl
            cs[m] = best
    return ci, cj, ck, cl, cs


@njit(cache=True, nogil=True)
def _descend(child, arg, level, ci, cj, ck, cl, cs):
    """Follow each candidate at ``level`` into its four children at ``level - 1``.

    ``arg`` is where the pooling of ``child`` found each maximum.
    """
    ny, Df, _, nx = child.shape
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
        for c in range(4):
            if chi[c] < 0:
                continue
            code = arg[chi[c], ck[m], cl[m], chj[c]]
            bk = code // Df
            bl = code % Df
            q = 4 * m + c
            oi[q] = chi[c]
            oj[q] = chj[c]
            ok[q] = bk
            ol[q] = bl
            osc[q] = cs[m] + child[chi[c], bk, bl, chj[c]]
    return oi, oj, ok, ol, osc


@njit(cache=True, nogil=True)
def _best_per_cell(resp0, ci, cj, ck, cl, cs):
    ny, D, _, nx = resp0.shape
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
            a = resp0[i, k - 1, kx, j]
            b = resp0[i, k, kx, j]
            c = resp0[i, k + 1, kx, j]
            den = a - 2.0 * b + c
            if den < 0.0:
                sy = min(max(0.5 * (a - c) / den, -0.5), 0.5)
        if 0 < kx < D - 1:
            a = resp0[i, k, kx - 1, j]
            b = resp0[i, k, kx, j]
            c = resp0[i, k, kx + 1, j]
            den = a - 2.0 * b + c
            if den < 0.0:
                sx = min(max(0.5 * (a - c) / den, -0.5), 0.5)
        dy[i, j] = k - R + sy
        dx[i, j] = kx - R + sx
        corr[i, j] = resp0[i, k, kx, j]
    return dx, dy, corr, best


def _n_levels(max_patch: int) -> int:
    levels = 0
    size = ATOMIC
    while size * 2 <= max_patch:
        size *= 2
        levels += 1
    return levels


def _match_from_responses(atomic, params):
    """Grid matches (downscaled pixels) from the atomic response maps of one direction."""
    ny, _, _, nx = atomic.shape
    resp = [atomic]
    args = []
    levels = _n_levels(params.max_patch)
    shapes = [(ny, nx)]
    for level in range(1, levels + 1):
        cny, cnx = shapes[-1]
        out_ny, out_nx = (cny - 1, cnx - 1) if level == 1 else (cny, cnx)
        if out_ny < 1 or out_nx < 1 or resp[-1].shape[1] < 5:
            break
        pooled, arg = _pool_subsample(resp[-1])
        resp.append(_aggregate(pooled, level, float(params.aggregation_power), out_ny, out_nx))
        args.append(arg)
        shapes.append((out_ny, out_nx))
        del pooled
    top = len(resp) - 1
    ci, cj, ck, cl, cs = _top_candidates(resp[top])
    for level in range(top, 0, -1):
        ci, cj, ck, cl, cs = _descend(resp[level - 1], args[level - 1], level, ci, cj, ck, cl, cs)
    dx, dy, corr, _ = _best_per_cell(resp[0], ci, cj, ck, cl, cs)
    return dx, dy, corr


_POOL: ThreadPoolExecutor | None = None
_POOL_LOCK = threading.Lock()


def _run_both(first, second):
    """Results of the callables ``first`` and ``second`` (``None`` skips one), run side by side.

    The kernels release the GIL, so two cores work at once. One pool of two
    threads serves every caller: concurrent callers (``refflow track
    --jobs``) queue up instead of multiplying threads, and each caller waits
    only for its own two tasks, so a busy machine costs at most one wait per
    call instead of one per parallel loop.
    """
    global _POOL
    if second is None or (os.cpu_count() or 1) < 2:
        return first(), (second() if second is not None else None)
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(max_workers=2, thread_name_prefix="deepmatching")
    future = _POOL.submit(second)
    result = first()
    return result, future.result()


def _no_check() -> None:
    pass


def _centres(n: int) -> np.ndarray:
    return ATOMIC * np.arange(n, dtype=np.float32) + (ATOMIC - 1) / 2.0


def deep_matching(
    reference: np.ndarray, current: np.ndarray, params: MatchParams | None = None, *,
    checkpoint: Callable[[], None] | None = None,
) -> MatchGrid:
    """Quasi-dense matches from ``reference`` to ``current``.

    Parameters
    ----------
    reference, current : ndarray (H, W), uint8 or float32
        Grey images of one shape.
    params : MatchParams, optional
    checkpoint : callable, optional
        Called between the matching's stages; it raises to abandon the matching (a run that
        is stopping, :meth:`flow.methods.base.DenseMethod.check_stop`).

    Returns
    -------
    MatchGrid
        One match per atomic patch (``valid`` marks the verified ones).

    Raises
    ------
    ValueError
        If the images differ in shape, are not 2-D or not uint8 / float32 (the numba
        kernels do not bounds-check), or ``params.downscale`` is not a positive integer.
    """
    check_grey_pair(reference, current)
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
    check = checkpoint if checkpoint is not None else _no_check
    f1 = _descriptor_planes(im1, params)
    f2 = _descriptor_planes(im2, params)
    check()
    ny, nx, radius = _radius_cells(params, reference.shape)
    D = 2 * radius + 1
    n1, n2 = _patch_norms(f1), _patch_norms(f2)
    forward = np.zeros((ny, D, D, nx), np.float32)
    backward = np.zeros((ny, D, D, nx), np.float32)
    # Two tasks of equal work (the displacement rows alternate between them)
    # would need strided outputs; contiguous halves are close enough.
    halves = [(0, (D + 1) // 2), ((D + 1) // 2, D)]
    _run_both(
        *(partial(_atomic_both, f1, f2, n1, n2, radius, a, b, forward, backward) for a, b in halves)
    )
    check()
    (dx, dy, corr), backward_matches = _run_both(
        partial(_match_from_responses, forward, params),
        partial(_match_from_responses, backward, params) if params.reciprocal else None,
    )
    del forward, backward
    valid = corr > params.min_score
    cy = _centres(ny)[:, None] * np.ones((1, nx), np.float32)
    cx = np.ones((ny, 1), np.float32) * _centres(nx)[None, :]
    if params.reciprocal:
        bdx, bdy, bcorr = backward_matches
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
