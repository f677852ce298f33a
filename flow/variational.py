"""Variational refinement of DeepFlow (coarse-to-fine, robust, edge-aware).

Energy (Weinzaepfel et al. 2013, after Brox et al. 2004 and Brox & Malik 2011)::

    E(w) = int  delta * psi(normalised |I2(x+w) - I1(x)|^2)
              + gamma * psi(normalised |grad I2(x+w) - grad I1(x)|^2)
              + alpha(x) * psi(|grad u|^2 + |grad v|^2)
              + beta * c(x) phi(x) * psi(|w - w'|^2)  dx

with ``psi(s2) = sqrt(s2 + eps^2)`` (Charbonnier), the linearised data
constraints normalised by ``1 / (|grad|^2 + zeta^2)`` (Zimmer et al. 2011), a
local smoothness weight ``alpha(x) = alpha * exp(-kappa * |grad I1(x)|)``
(DeepFlow's edge-aware weight) and ``w'`` the matches with per-match weight
``phi``. It is minimised coarse to fine (pyramid factor ``eta``), warping once
per level (bicubic), with ``n_outer`` fixed-point iterations that freeze the robust
weights and ``n_sor`` successive over-relaxation sweeps on the 2x2 per-pixel
linear systems.

References
----------
.. [1] P. Weinzaepfel, J. Revaud, Z. Harchaoui, C. Schmid, "DeepFlow: Large
   displacement optical flow with deep matching", ICCV 2013.
.. [2] T. Brox, A. Bruhn, N. Papenberg, J. Weickert, "High accuracy optical
   flow estimation based on a theory for warping", ECCV 2004.
.. [3] T. Brox, J. Malik, "Large displacement optical flow: descriptor
   matching in variational motion estimation", TPAMI 2011.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numba import njit

# Brox et al.'s five-point derivative stencil.
_DERIV = np.array([[1.0, -8.0, 0.0, 8.0, -1.0]], dtype=np.float32) / 12.0


@dataclass(frozen=True)
class VariationalParams:
    """Parameters of the variational energy and its solver (see module doc).

    The solver settings (``sigma`` 0.6, ``eta`` 0.95, ``min_size`` 25,
    ``n_outer`` 5, ``n_sor`` 25, ``omega`` 1.6, ``delta`` 0.5, ``gamma`` 5)
    are the published DeepFlow / OpenCV ``DeepFlow`` defaults. ``alpha``,
    ``zeta``, ``kappa`` and ``edge_sigma`` are in *our* units (frames scaled
    to a standard deviation of ``contrast_std``, data terms normalised) and
    were tuned on synthetic pairs so that ``beta = 0`` matches OpenCV's
    DeepFlow accuracy.

    alpha : smoothness weight; the local weight is
        ``alpha * exp(-kappa * |grad G_edge_sigma * I1|)``.
    beta : matching-term weight (0 switches matches off).
    delta, gamma : brightness and gradient constancy weights.
    kappa, edge_sigma : edge-aware smoothness; the edge map is taken on the
        reference blurred by ``edge_sigma`` (object edges survive, fine
        texture does not). ``kappa = 0`` gives isotropic smoothness.
    sigma : pre-smoothing of both frames.
    eta, min_size : pyramid factor and smallest level side.
    n_outer, n_sor, omega : fixed-point iterations, SOR sweeps, relaxation.
    eps : Charbonnier epsilon; zeta : data-term normalisation constant.
    match_max_scale : the matching term acts only on pyramid levels at or
        coarser than this scale; finer levels refine the flow to sub-pixel
        accuracy without the (pixel-quantised) matches pulling on it.
    contrast_std : frames are scaled by one common gain so that the reference
        has this standard deviation (0 disables).
    """

    alpha: float = 0.7
    beta: float = 32.0
    delta: float = 0.5
    gamma: float = 5.0
    kappa: float = 10.0
    sigma: float = 0.6
    eta: float = 0.95
    min_size: int = 25
    n_outer: int = 5
    n_sor: int = 25
    omega: float = 1.6
    eps: float = 0.001
    zeta: float = 0.5
    match_max_scale: float = 0.5
    contrast_std: float = 0.15
    edge_sigma: float = 2.0


@njit(cache=True, fastmath=True)
def _psi_prime(s2, eps2):
    return 0.5 / math.sqrt(s2 + eps2)


@njit(cache=True, fastmath=True)
def _sor(dup, dvp, wE, wW, wS, wN, inv11, inv22, A12, b1, b2, n_sor, omega):
    """Red-black SOR on padded increments.

    Serial on purpose: thread start-up per half-sweep costs more than the
    sweep itself on the many small pyramid levels.
    """
    H, W = wE.shape
    one = np.float32(1.0)
    for _it in range(n_sor):
        for colour in range(2):
            for y in range(H):
                yy = y + 1
                for x in range((y + colour) & 1, W, 2):
                    xx = x + 1
                    e = wE[y, x]
                    w = wW[y, x]
                    s = wS[y, x]
                    n = wN[y, x]
                    su = (
                        e * dup[yy, xx + 1]
                        + w * dup[yy, xx - 1]
                        + s * dup[yy + 1, xx]
                        + n * dup[yy - 1, xx]
                    )
                    sv = (
                        e * dvp[yy, xx + 1]
                        + w * dvp[yy, xx - 1]
                        + s * dvp[yy + 1, xx]
                        + n * dvp[yy - 1, xx]
                    )
                    a12 = A12[y, x]
                    old_u = dup[yy, xx]
                    nu = (b1[y, x] + su - a12 * dvp[yy, xx]) * inv11[y, x]
                    new_u = (one - omega) * old_u + omega * nu
                    dup[yy, xx] = new_u
                    nv = (b2[y, x] + sv - a12 * new_u) * inv22[y, x]
                    dvp[yy, xx] = (one - omega) * dvp[yy, xx] + omega * nv
    return dup, dvp


@njit(cache=True, fastmath=True)
def _solve_level(
    Ix,
    Iy,
    It,
    Ixx,
    Ixy,
    Iyy,
    Ixt,
    Iyt,
    valid,
    alpha_map,
    u,
    v,
    mu,
    mv,
    mw,
    delta,
    gamma,
    beta,
    zeta2,
    eps2,
    n_outer,
    n_sor,
    omega,
):
    H, W = u.shape
    du = np.zeros((H, W), np.float32)
    dv = np.zeros((H, W), np.float32)
    a_s = np.empty((H, W), np.float32)
    wx = np.zeros((H, W), np.float32)  # link (y, x) - (y, x + 1)
    wy = np.zeros((H, W), np.float32)  # link (y, x) - (y + 1, x)
    A11 = np.empty((H, W), np.float32)
    A12 = np.empty((H, W), np.float32)
    A22 = np.empty((H, W), np.float32)
    b1 = np.empty((H, W), np.float32)
    b2 = np.empty((H, W), np.float32)
    wE = np.empty((H, W), np.float32)
    wW = np.empty((H, W), np.float32)
    wS = np.empty((H, W), np.float32)
    wN = np.empty((H, W), np.float32)
    inv11 = np.empty((H, W), np.float32)
    inv22 = np.empty((H, W), np.float32)
    # Zero-padded copies of the increments remove all border tests from the sweeps.
    dup = np.zeros((H + 2, W + 2), np.float32)
    dvp = np.zeros((H + 2, W + 2), np.float32)
    for _outer in range(n_outer):
        # Robust smoothness weights from the current total flow.
        for y in range(H):
            ym = y - 1 if y > 0 else 0
            yp = y + 1 if y < H - 1 else H - 1
            for x in range(W):
                xm = x - 1 if x > 0 else 0
                xp = x + 1 if x < W - 1 else W - 1
                ux = 0.5 * (u[y, xp] + du[y, xp] - u[y, xm] - du[y, xm])
                uy = 0.5 * (u[yp, x] + du[yp, x] - u[ym, x] - du[ym, x])
                vx = 0.5 * (v[y, xp] + dv[y, xp] - v[y, xm] - dv[y, xm])
                vy = 0.5 * (v[yp, x] + dv[yp, x] - v[ym, x] - dv[ym, x])
                a_s[y, x] = alpha_map[y, x] * _psi_prime(
                    ux * ux + uy * uy + vx * vx + vy * vy, eps2
                )
        for y in range(H):
            for x in range(W):
                if x < W - 1:
                    wx[y, x] = 0.5 * (a_s[y, x] + a_s[y, x + 1])
                if y < H - 1:
                    wy[y, x] = 0.5 * (a_s[y, x] + a_s[y + 1, x])
        # Linearised data and matching terms with frozen robust weights.
        for y in range(H):
            for x in range(W):
                a11 = 0.0
                a12 = 0.0
                a22 = 0.0
                r1 = 0.0
                r2 = 0.0
                if valid[y, x]:
                    ix = Ix[y, x]
                    iy = Iy[y, x]
                    it = It[y, x]
                    nc = 1.0 / (ix * ix + iy * iy + zeta2)
                    rc = it + ix * du[y, x] + iy * dv[y, x]
                    pc = delta * nc * _psi_prime(nc * rc * rc, eps2)
                    ixx = Ixx[y, x]
                    ixy = Ixy[y, x]
                    iyy = Iyy[y, x]
                    ixt = Ixt[y, x]
                    iyt = Iyt[y, x]
                    ngx = 1.0 / (ixx * ixx + ixy * ixy + zeta2)
                    ngy = 1.0 / (ixy * ixy + iyy * iyy + zeta2)
                    rx = ixt + ixx * du[y, x] + ixy * dv[y, x]
                    ry = iyt + ixy * du[y, x] + iyy * dv[y, x]
                    pg = gamma * _psi_prime(ngx * rx * rx + ngy * ry * ry, eps2)
                    gx = pg * ngx
                    gy = pg * ngy
                    a11 = pc * ix * ix + gx * ixx * ixx + gy * ixy * ixy
                    a12 = pc * ix * iy + gx * ixx * ixy + gy * ixy * iyy
                    a22 = pc * iy * iy + gx * ixy * ixy + gy * iyy * iyy
                    r1 = -(pc * ix * it + gx * ixx * ixt + gy * ixy * iyt)
                    r2 = -(pc * iy * it + gx * ixy * ixt + gy * iyy * iyt)
                if beta > 0.0 and mw[y, x] > 0.0:
                    eu = u[y, x] + du[y, x] - mu[y, x]
                    ev = v[y, x] + dv[y, x] - mv[y, x]
                    pm = beta * mw[y, x] * _psi_prime(eu * eu + ev * ev, eps2)
                    a11 += pm
                    a22 += pm
                    r1 -= pm * (u[y, x] - mu[y, x])
                    r2 -= pm * (v[y, x] - mv[y, x])
                # Smoothness acting on the fixed part of the flow.
                su = 0.0
                sv = 0.0
                if x < W - 1:
                    su += wx[y, x] * (u[y, x + 1] - u[y, x])
                    sv += wx[y, x] * (v[y, x + 1] - v[y, x])
                if x > 0:
                    su += wx[y, x - 1] * (u[y, x - 1] - u[y, x])
                    sv += wx[y, x - 1] * (v[y, x - 1] - v[y, x])
                if y < H - 1:
                    su += wy[y, x] * (u[y + 1, x] - u[y, x])
                    sv += wy[y, x] * (v[y + 1, x] - v[y, x])
                if y > 0:
                    su += wy[y - 1, x] * (u[y - 1, x] - u[y, x])
                    sv += wy[y - 1, x] * (v[y - 1, x] - v[y, x])
                A11[y, x] = a11
                A12[y, x] = a12
                A22[y, x] = a22
                b1[y, x] = r1 + su
                b2[y, x] = r2 + sv
        # Per-pixel link weights and inverse diagonals are fixed during the sweeps.
        for y in range(H):
            for x in range(W):
                e = wx[y, x] if x < W - 1 else np.float32(0.0)
                w_ = wx[y, x - 1] if x > 0 else np.float32(0.0)
                s_ = wy[y, x] if y < H - 1 else np.float32(0.0)
                n_ = wy[y - 1, x] if y > 0 else np.float32(0.0)
                wE[y, x] = e
                wW[y, x] = w_
                wS[y, x] = s_
                wN[y, x] = n_
                sw = e + w_ + s_ + n_
                d11 = A11[y, x] + sw
                d22 = A22[y, x] + sw
                inv11[y, x] = 1.0 / d11 if d11 > 0.0 else 0.0
                inv22[y, x] = 1.0 / d22 if d22 > 0.0 else 0.0
                dup[y + 1, x + 1] = du[y, x]
                dvp[y + 1, x + 1] = dv[y, x]
        _sor(dup, dvp, wE, wW, wS, wN, inv11, inv22, A12, b1, b2, n_sor, np.float32(omega))
        for y in range(H):
            for x in range(W):
                du[y, x] = dup[y + 1, x + 1]
                dv[y, x] = dvp[y + 1, x + 1]
    return du, dv


def _deriv(image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    gx = cv2.filter2D(image, cv2.CV_32F, _DERIV, borderType=cv2.BORDER_REPLICATE)
    gy = cv2.filter2D(image, cv2.CV_32F, _DERIV.T, borderType=cv2.BORDER_REPLICATE)
    return gx, gy


def _warp(image: np.ndarray, map_x: np.ndarray, map_y: np.ndarray) -> np.ndarray:
    # Bicubic: bilinear warping biases quarter-pixel shifts by ~0.05 px on smooth texture.
    return cv2.remap(image, map_x, map_y, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)


def _level_sizes(
    height: int, width: int, eta: float, min_size: int
) -> list[tuple[int, int, float]]:
    """(h, w, scale) from finest to coarsest."""
    sizes = [(height, width, 1.0)]
    scale = 1.0
    while True:
        scale *= eta
        h = int(round(height * scale))
        w = int(round(width * scale))
        if min(h, w) < min_size or eta >= 1.0:
            break
        sizes.append((h, w, scale))
    return sizes


def _resize_flow(u: np.ndarray, v: np.ndarray, h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    sx = w / u.shape[1]
    sy = h / u.shape[0]
    u2 = cv2.resize(u, (w, h), interpolation=cv2.INTER_LINEAR) * np.float32(sx)
    v2 = cv2.resize(v, (w, h), interpolation=cv2.INTER_LINEAR) * np.float32(sy)
    return u2, v2


def refine(
    reference: np.ndarray,
    current: np.ndarray,
    params: VariationalParams,
    *,
    init_flow: np.ndarray | None = None,
    match_flow: np.ndarray | None = None,
    match_weight: np.ndarray | None = None,
) -> np.ndarray:
    """Coarse-to-fine minimisation of the DeepFlow energy.

    Parameters
    ----------
    reference, current : ndarray (H, W)
        Grey images (any range; scaled to [0, 1] internally using 255 for uint8).
    params : VariationalParams
    init_flow : ndarray (H, W, 2), optional
        Start flow at the coarsest level (resized down).
    match_flow, match_weight : ndarray (H, W, 2) and (H, W), optional
        Dense rasterised matches ``w'`` and their weights ``c * phi`` in [0, 1].

    Returns
    -------
    ndarray (H, W, 2) float32
    """
    scale_in = 1.0 / 255.0 if reference.dtype == np.uint8 else 1.0
    im1 = reference.astype(np.float32) * np.float32(scale_in)
    im2 = current.astype(np.float32) * np.float32(scale_in)
    if params.contrast_std > 0:
        # One gain for both frames: zeta, eps and kappa then mean the same on
        # low-contrast footage as on well-lit texture.
        spread = float(im1.std())
        if spread > 1e-6:
            gain = np.float32(params.contrast_std / spread)
            offset = np.float32(im1.mean())
            im1 = (im1 - offset) * gain
            im2 = (im2 - offset) * gain
    if params.sigma > 0:
        im1 = cv2.GaussianBlur(im1, (0, 0), params.sigma)
        im2 = cv2.GaussianBlur(im2, (0, 0), params.sigma)
    height, width = im1.shape
    levels = _level_sizes(height, width, params.eta, params.min_size)
    use_matches = match_flow is not None and match_weight is not None and params.beta > 0
    h0, w0, _ = levels[-1]
    if init_flow is not None:
        u, v = _resize_flow(
            init_flow[..., 0].astype(np.float32), init_flow[..., 1].astype(np.float32), h0, w0
        )
    else:
        u = np.zeros((h0, w0), np.float32)
        v = np.zeros((h0, w0), np.float32)
    zeta2 = params.zeta**2
    eps2 = params.eps**2
    for h, w, scale in reversed(levels):
        if u.shape != (h, w):
            u, v = _resize_flow(u, v, h, w)
        if (h, w) == (height, width):
            i1, i2 = im1, im2
        else:
            i1 = cv2.resize(im1, (w, h), interpolation=cv2.INTER_AREA)
            i2 = cv2.resize(im2, (w, h), interpolation=cv2.INTER_AREA)
        i1x, i1y = _deriv(i1)
        i2x, i2y = _deriv(i2)
        grid_x, grid_y = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        map_x = grid_x + u
        map_y = grid_y + v
        valid = ((map_x >= 0) & (map_x <= w - 1) & (map_y >= 0) & (map_y <= h - 1)).astype(np.uint8)
        i2w = _warp(i2, map_x, map_y)
        i2xw = _warp(i2x, map_x, map_y)
        i2yw = _warp(i2y, map_x, map_y)
        # Derivatives of the mean of both frames are less biased than either alone.
        ix = 0.5 * (i1x + i2xw)
        iy = 0.5 * (i1y + i2yw)
        it = i2w - i1
        i1xx, i1xy = _deriv(i1x)
        _, i1yy = _deriv(i1y)
        i2xx, i2xy = _deriv(i2x)
        _, i2yy = _deriv(i2y)
        ixx = 0.5 * (i1xx + _warp(i2xx, map_x, map_y))
        ixy = 0.5 * (i1xy + _warp(i2xy, map_x, map_y))
        iyy = 0.5 * (i1yy + _warp(i2yy, map_x, map_y))
        ixt = i2xw - i1x
        iyt = i2yw - i1y
        if params.edge_sigma > 0:
            # Edges of objects survive this blur, fine texture does not.
            ex, ey = _deriv(cv2.GaussianBlur(i1, (0, 0), params.edge_sigma * scale))
        else:
            ex, ey = i1x, i1y
        grad_mag = np.sqrt(ex * ex + ey * ey)
        alpha_map = (params.alpha * np.exp(-params.kappa * grad_mag)).astype(np.float32)
        beta_level = params.beta if (use_matches and scale <= params.match_max_scale) else 0.0
        if beta_level > 0:
            mu, mv = _resize_flow(match_flow[..., 0], match_flow[..., 1], h, w)
            mw = cv2.resize(match_weight.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA)
        else:
            mu = mv = mw = np.zeros((1, 1), np.float32)
        du, dv = _solve_level(
            ix,
            iy,
            it,
            ixx,
            ixy,
            iyy,
            ixt,
            iyt,
            valid,
            alpha_map,
            u,
            v,
            mu,
            mv,
            mw,
            float(params.delta),
            float(params.gamma),
            float(beta_level),
            float(zeta2),
            float(eps2),
            int(params.n_outer),
            int(params.n_sor),
            float(params.omega),
        )
        u = u + du
        v = v + dv
    return np.dstack([u, v]).astype(np.float32)
