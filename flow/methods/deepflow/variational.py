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
``phi``. It is minimised coarse to fine (pyramid factor ``eta``), warping the
current frame once per level (the cubic B-spline interpolant of the frame, not a
cubic convolution: see :func:`_bspline_coefficients`) and differentiating the warped frame, with ``n_outer`` fixed-point iterations that freeze the robust
weights and ``n_sor`` red-black successive over-relaxation sweeps on the 2x2
per-pixel linear systems.

The solver works on the two colours of the red-black ordering packed into
separate unit-stride rows (see the layout notes below), pipelines the sweeps
along the rows so that the rows in flight stay in cache, and builds each
fixed-point iteration's system in the same pass as its first sweeps. It runs
on one thread: on a busy machine, threads that must meet at every sweep lose
more waiting for each other than they gain.

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
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np
from numba import njit

from flow.methods.deepflow.checks import check_grey_pair, check_shape
from flow.methods.params import bounds, check_fields

# The kernels keep IEEE arithmetic (no fastmath): with LLVM free to reassociate sums, a freshly
# compiled kernel and the same kernel loaded from numba's cache gave different bytes, so the
# first run on a fresh machine differed from every later one (tests/unit/test_determinism.py).


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

    # Ranges (``refflow methods --params deepflow``): where the energy means something and the
    # solver converges (SOR needs 0 < omega < 2), and the work stays bounded (iterations, a
    # pyramid factor close to 1 multiplies the levels, a blur's kernel grows with its sigma).
    alpha: float = field(default=0.7, metadata=bounds(0, 100, "smoothness weight", low_open=True))
    beta: float = field(default=32.0, metadata=bounds(0, 1000, "matching-term weight (0: no matching)"))
    delta: float = field(default=0.5, metadata=bounds(0, 100, "brightness constancy weight"))
    gamma: float = field(default=5.0, metadata=bounds(0, 100, "gradient constancy weight"))
    kappa: float = field(default=10.0, metadata=bounds(0, 100, "edge-aware smoothness (0: isotropic)"))
    sigma: float = field(default=0.6, metadata=bounds(0, 10, "pre-smoothing of both frames, px"))
    eta: float = field(default=0.95, metadata=bounds(0.1, 0.98, "pyramid factor between levels"))
    min_size: int = field(default=25, metadata=bounds(8, 4096, "smallest pyramid level side, px"))
    n_outer: int = field(default=5, metadata=bounds(1, 20, "fixed-point iterations per level"))
    n_sor: int = field(default=25, metadata=bounds(1, 200, "SOR sweeps per fixed-point iteration"))
    omega: float = field(default=1.6, metadata=bounds(0, 2, "SOR relaxation", low_open=True, high_open=True))
    eps: float = field(default=0.001, metadata=bounds(0, 1, "Charbonnier epsilon", low_open=True))
    zeta: float = field(default=0.5, metadata=bounds(0, 10, "data-term normalisation constant", low_open=True))
    match_max_scale: float = field(default=0.5, metadata=bounds(0, 1, "the matching term acts on levels at or "
                                                                "coarser than this scale"))
    contrast_std: float = field(default=0.15, metadata=bounds(0, 1, "frames scaled to this standard deviation "
                                                              "(0: not scaled)"))
    edge_sigma: float = field(default=2.0, metadata=bounds(0, 20, "blur of the reference for the edge map, px"))

    def __post_init__(self) -> None:
        check_fields(self)


# Packed red-black layout
# -----------------------
# Pixel (y, x) has colour c = (x + y) & 1 and lives at [y + 1, ..., c, x // 2 + 1]
# of arrays shaped (H + 2, ..., 2, K + 2), K >= (W + 1) // 2: rows first, so that
# what a sweep needs of one row is close together. Along row y the colour-c pixels sit at
# x = 2k + p with p = (y + c) & 1, so their west and east neighbours are the
# other colour's entries k + p - 1 and k + p of the same row, and their north
# and south neighbours its entries k of rows y -+ 1. A half-sweep is then a
# unit-stride stencil that LLVM vectorises (the x += 2 loop over a full grid
# is not). The ring around the grid and the spare slots at the end of the
# rows (K is rounded up to whole vectors) stand for pixels outside the image:
# their links are zero and their increments stay zero.

_N_DATA = 11  # ix, iy, it, nc, ixx, ixy, iyy, ixt, iyt, ngx, ngy
_N_COEF = 5  # a12, b1, b2, 1 / d11, 1 / d22
_N_LEVEL = 6  # u, v, u - mu, v - mv, beta * match weight / 2, local alpha
# Cache share for the rows in flight of the temporally blocked SOR (see _sor).
_SOR_CACHE_BYTES = 1 << 20
# Keys' cubic convolution parameter of the warps. -0.5 reproduces linear and
# quadratic intensity profiles exactly; the -0.75 of OpenCV's INTER_CUBIC
# shifts them by up to 0.04 px (its weights' first moment at offset 0.3 is
# 0.342), a bias that shows up as a sub-pixel flow error on low-texture scenes.
_CUBIC_A = -0.5
_WARP_BSPLINE = True


class Workspace:
    """Scratch arrays reused across pyramid levels and calls.

    A level needs tens of MB of scratch; reusing it keeps the pages mapped
    instead of faulting fresh ones in for every level of every frame. One
    workspace must not be shared by calls running at the same time.
    """

    def __init__(self) -> None:
        self._buffers: dict[str, np.ndarray] = {}

    def nbytes(self) -> int:
        """Bytes of scratch held."""
        return sum(buffer.nbytes for buffer in self._buffers.values())

    def array(self, name: str, shape: tuple[int, ...], zero: bool = False) -> np.ndarray:
        """A float32 array of ``shape`` backed by the buffer ``name``."""
        size = math.prod(shape)
        buffer = self._buffers.get(name)
        if buffer is None or buffer.size < size:
            buffer = self._buffers[name] = np.empty(size, np.float32)
        view = buffer[:size].reshape(shape)
        if zero:
            view.fill(0.0)
        return view


# Brox et al.'s five-point derivative (1, -8, 0, 8, -1) / 12 as two weights.
_D1 = np.float32(8.0 / 12.0)
_D2 = np.float32(1.0 / 12.0)


@njit(cache=True, error_model="numpy", nogil=True)
def _diff_x_at(s, x, W):
    # Five-point derivative at column x of row s, replicated border.
    return _D1 * (s[min(x + 1, W - 1)] - s[max(x - 1, 0)]) - _D2 * (
        s[min(x + 2, W - 1)] - s[max(x - 2, 0)]
    )


@njit(cache=True, error_model="numpy", nogil=True)
def _diff_x(src, dst):
    """Brox et al.'s five-point derivative (1, -8, 0, 8, -1) / 12 along x."""
    H, W = src.shape
    for y in range(H):
        s = src[y]
        d = dst[y]
        for x in range(2, W - 2):
            d[x] = _D1 * (s[x + 1] - s[x - 1]) - _D2 * (s[x + 2] - s[x - 2])
        for x in range(min(2, W)):
            d[x] = _diff_x_at(s, x, W)
        for x in range(max(W - 2, 2), W):
            d[x] = _diff_x_at(s, x, W)


@njit(cache=True, error_model="numpy", nogil=True)
def _diff_y(src, dst):
    """Five-point derivative along y, replicated border."""
    H, W = src.shape
    for y in range(H):
        m2 = src[max(y - 2, 0)]
        m1 = src[max(y - 1, 0)]
        p1 = src[min(y + 1, H - 1)]
        p2 = src[min(y + 2, H - 1)]
        d = dst[y]
        for x in range(W):
            d[x] = _D1 * (p1[x] - m1[x]) - _D2 * (p2[x] - m2[x])


@njit(cache=True, error_model="numpy", nogil=True)
def _derivatives(image, out):
    """I, Ix, Iy, Ixx, Ixy, Iyy of ``image`` into the planes ``out[0:6]``."""
    out[0] = image
    _diff_x(image, out[1])
    _diff_y(image, out[2])
    _diff_x(out[1], out[3])
    _diff_y(out[1], out[4])
    _diff_y(out[2], out[5])


@njit(cache=True, error_model="numpy", nogil=True)
def _cubic(t):
    # Keys' cubic convolution weights of the taps at -1, 0, 1, 2 for an offset t in [0, 1).
    a = np.float32(_CUBIC_A)
    one = np.float32(1.0)
    t1 = t + one
    s = one - t
    s1 = s + one
    w0 = ((a * t1 - np.float32(5.0) * a) * t1 + np.float32(8.0) * a) * t1 - np.float32(4.0) * a
    w1 = ((a + np.float32(2.0)) * t - (a + np.float32(3.0))) * t * t + one
    w2 = ((a + np.float32(2.0)) * s - (a + np.float32(3.0))) * s * s + one
    w3 = ((a * s1 - np.float32(5.0) * a) * s1 + np.float32(8.0) * a) * s1 - np.float32(4.0) * a
    return w0, w1, w2, w3


# The cubic B-spline's pole (Unser, Aldroubi and Eden 1991): interpolating with the B-spline
# needs the image's spline coefficients, two recursive passes of this pole per axis.
_BSPLINE_POLE = np.sqrt(3.0) - 2.0


@njit(cache=True, error_model="numpy", nogil=True)
def _bspline_line(line, work):
    """The cubic B-spline coefficients of one line in place (mirror border).

    The causal pass starts from the mirrored line's sum weighted by the pole's powers: on a
    long line its first 16 samples (the pole's 16th power is 7e-10), on a shorter one the sum
    over the whole mirrored period in closed form; the anticausal pass from its closed form at
    the far end.
    """
    n = line.shape[0]
    if n < 2:
        return
    z = _BSPLINE_POLE
    for k in range(n):
        work[k] = 6.0 * line[k]
    if n > 16:
        acc = 0.0
        zk = 1.0
        for k in range(16):
            acc += zk * work[k]
            zk *= z
        work[0] = acc
    else:
        # The mirrored line repeats every 2 (n - 1) samples: sample k comes back at
        # 2 (n - 1) - k, and the geometric series over the periods sums in closed form.
        zk = z
        back = z ** (n - 1)
        acc = work[0] + back * work[n - 1]
        back = back * back / z
        for k in range(1, n - 1):
            acc += (zk + back) * work[k]
            zk *= z
            back /= z
        work[0] = acc / (1.0 - zk * zk)
    for k in range(1, n):
        work[k] = work[k] + z * work[k - 1]
    work[n - 1] = (z / (z * z - 1.0)) * (work[n - 1] + z * work[n - 2])
    for k in range(n - 2, -1, -1):
        work[k] = z * (work[k + 1] - work[k])
    for k in range(n):
        line[k] = work[k]


@njit(cache=True, error_model="numpy", nogil=True)
def _bspline_coefficients(image, out):
    """The cubic B-spline coefficients of ``image`` into ``out`` (float64 passes, float32 out):
    sampled at whole pixels the spline returns the image, between them it interpolates with a
    far smaller sub-pixel bias than a cubic convolution (DIC Challenge Sample 14's speckle
    shifted by 0.1 px reads 9 % long through the variational solve with Keys' cubic, 0.8 % with
    the B-spline)."""
    _bspline_rows(image, out)
    _bspline_rows(out.T, out.T)  # the columns: the transpose's rows, in place


@njit(cache=True, error_model="numpy", nogil=True)
def _bspline_rows(src, dst):
    # Each row of src through _bspline_line into the same row of dst (float64 passes).
    H, W = src.shape
    line = np.empty(W, np.float64)
    work = np.empty(W, np.float64)
    for y in range(H):
        for x in range(W):
            line[x] = src[y, x]
        _bspline_line(line, work)
        for x in range(W):
            dst[y, x] = line[x]


@njit(cache=True, error_model="numpy", nogil=True)
def _bspline_weights(t):
    # The cubic B-spline's weights of the taps at -1, 0, 1, 2 for an offset t in [0, 1).
    sixth = np.float32(1.0 / 6.0)
    s = np.float32(1.0) - t
    t2 = t * t
    t3 = t2 * t
    w0 = s * s * s * sixth
    w1 = (np.float32(3.0) * t3 - np.float32(6.0) * t2 + np.float32(4.0)) * sixth
    w2 = (np.float32(-3.0) * t3 + np.float32(3.0) * t2 + np.float32(3.0) * t + np.float32(1.0)) * sixth
    w3 = t3 * sixth
    return w0, w1, w2, w3


@njit(cache=True, error_model="numpy", nogil=True)
def _mirror(i, n):
    # Whole-sample mirror of index i into [0, n) (the B-spline coefficients' border).
    if i < 0:
        i = -i
    if i > n - 1:
        i = 2 * (n - 1) - i
    return min(max(i, 0), n - 1)


@njit(cache=True, error_model="numpy", nogil=True)
def _warp(image, flow, out, inside, bspline):
    """Bicubic ``image(x + flow(x))`` into ``out``.

    ``bspline``: ``image`` holds the frame's cubic B-spline coefficients
    (:func:`_bspline_coefficients`, mirrored border); otherwise it is the frame itself,
    interpolated by Keys' cubic convolution with a replicated border.
    ``inside`` is 1 where the target lies in the frame, else 0 (the sample
    is then taken at the nearest point of the frame).
    """
    H, W = image.shape
    xmax = np.float32(W - 1)
    ymax = np.float32(H - 1)
    zero = np.float32(0.0)
    for y in range(H):
        for x in range(W):
            px = np.float32(x) + flow[y, x, 0]
            py = np.float32(y) + flow[y, x, 1]
            ok = px >= zero and px <= xmax and py >= zero and py <= ymax
            inside[y, x] = 1.0 if ok else 0.0
            if not ok:
                # Written so that NaN lands on the frame as well.
                px = px if px <= xmax else xmax
                px = px if px >= zero else zero
                py = py if py <= ymax else ymax
                py = py if py >= zero else zero
            # np.floor keeps float32 (math.floor returns an int, promoting the weights to float64).
            fx = np.floor(px)
            fy = np.floor(py)
            x0 = int(fx)
            y0 = int(fy)
            if bspline:
                wx0, wx1, wx2, wx3 = _bspline_weights(px - fx)
                wy0, wy1, wy2, wy3 = _bspline_weights(py - fy)
                xa = _mirror(x0 - 1, W)
                xc = _mirror(x0 + 1, W)
                xd = _mirror(x0 + 2, W)
                ra = image[_mirror(y0 - 1, H)]
                rc = image[_mirror(y0 + 1, H)]
                rd = image[_mirror(y0 + 2, H)]
            else:
                wx0, wx1, wx2, wx3 = _cubic(px - fx)
                wy0, wy1, wy2, wy3 = _cubic(py - fy)
                xa = max(x0 - 1, 0)
                xc = min(x0 + 1, W - 1)
                xd = min(x0 + 2, W - 1)
                ra = image[max(y0 - 1, 0)]
                rc = image[min(y0 + 1, H - 1)]
                rd = image[min(y0 + 2, H - 1)]
            rb = image[y0]
            out[y, x] = (
                wy0 * (wx0 * ra[xa] + wx1 * ra[x0] + wx2 * ra[xc] + wx3 * ra[xd])
                + wy1 * (wx0 * rb[xa] + wx1 * rb[x0] + wx2 * rb[xc] + wx3 * rb[xd])
                + wy2 * (wx0 * rc[xa] + wx1 * rc[x0] + wx2 * rc[xc] + wx3 * rc[xd])
                + wy3 * (wx0 * rd[xa] + wx1 * rd[x0] + wx2 * rd[xc] + wx3 * rd[xd])
            )


@njit(cache=True, error_model="numpy", nogil=True)
def _zero_ring(packed):
    # Zero the first and last rows and slots of a packed array.
    last = packed.shape[-1] - 1
    packed[0] = 0.0
    packed[packed.shape[0] - 1] = 0.0
    for y in range(1, packed.shape[0] - 1):
        row = packed[y]
        for q in range(row.shape[0]):
            for c in range(2):
                row[q, c, 0] = 0.0
                row[q, c, last] = 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def _pack_data(s1, s2, inside, zeta2, out):
    """Linearised data terms (see ``_N_DATA``) from the derivative planes, packed.

    ``s1`` and ``s2`` hold I, Ix, Iy, Ixx, Ixy, Iyy of the reference and of
    the warped current frame. Pixels whose target leaves the frame get zero
    normalisations, which switches their data term off.
    """
    W = s1.shape[2]
    half = np.float32(0.5)
    z2 = np.float32(zeta2)
    _zero_ring(out)
    nk_all = out.shape[3] - 2
    for y in range(s1.shape[1]):
        g = out[y + 1]
        m = inside[y]
        for c in range(2):
            p = (y + c) & 1
            nk = (W - p + 1) // 2
            # Two loops with few output streams each: LLVM vectorises them.
            i1, i1x, i1y = s1[0, y, p:], s1[1, y, p:], s1[2, y, p:]
            i2, i2x, i2y = s2[0, y, p:], s2[1, y, p:], s2[2, y, p:]
            mc = m[p:]
            g_ix, g_iy, g_it, g_nc, g_ixt, g_iyt = (
                g[0, c],
                g[1, c],
                g[2, c],
                g[3, c],
                g[7, c],
                g[8, c],
            )
            for k in range(nk):
                x = 2 * k
                ix = half * (i1x[x] + i2x[x])
                iy = half * (i1y[x] + i2y[x])
                g_ix[k + 1] = ix
                g_iy[k + 1] = iy
                g_it[k + 1] = i2[x] - i1[x]
                g_nc[k + 1] = mc[x] / (ix * ix + iy * iy + z2)
                g_ixt[k + 1] = i2x[x] - i1x[x]
                g_iyt[k + 1] = i2y[x] - i1y[x]
            j1xx, j1xy, j1yy = s1[3, y, p:], s1[4, y, p:], s1[5, y, p:]
            j2xx, j2xy, j2yy = s2[3, y, p:], s2[4, y, p:], s2[5, y, p:]
            g_ixx, g_ixy, g_iyy, g_ngx, g_ngy = g[4, c], g[5, c], g[6, c], g[9, c], g[10, c]
            for k in range(nk):
                x = 2 * k
                ixx = half * (j1xx[x] + j2xx[x])
                ixy = half * (j1xy[x] + j2xy[x])
                iyy = half * (j1yy[x] + j2yy[x])
                g_ixx[k + 1] = ixx
                g_ixy[k + 1] = ixy
                g_iyy[k + 1] = iyy
                g_ngx[k + 1] = mc[x] / (ixx * ixx + ixy * ixy + z2)
                g_ngy[k + 1] = mc[x] / (ixy * ixy + iyy * iyy + z2)
            for k in range(nk + 1, nk_all + 1):
                g[:, c, k] = 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def _pack_level(flow, match, match_scale, half_weight, alpha, out):
    """Per-level constants (see ``_N_LEVEL``), packed.

    ``match`` times ``match_scale`` (x, y) are the matches and
    ``half_weight`` beta / 2 times their weights (zeros switch the term
    off); ``alpha`` is the local smoothness weight.
    """
    H, W = alpha.shape
    sx = np.float32(match_scale[0])
    sy = np.float32(match_scale[1])
    _zero_ring(out)
    nk_all = out.shape[3] - 2
    for y in range(H):
        row = out[y + 1]
        for c in range(2):
            p = (y + c) & 1
            nk = (W - p + 1) // 2
            f = flow[y, p:]
            mt = match[y, p:]
            hw = half_weight[y, p:]
            al = alpha[y, p:]
            l_u, l_v, l_fu, l_fv, l_m, l_a = (
                row[0, c],
                row[1, c],
                row[2, c],
                row[3, c],
                row[4, c],
                row[5, c],
            )
            for k in range(nk):
                x = 2 * k
                l_u[k + 1] = f[x, 0]
                l_v[k + 1] = f[x, 1]
                l_fu[k + 1] = f[x, 0] - sx * mt[x, 0]
                l_fv[k + 1] = f[x, 1] - sy * mt[x, 1]
                l_m[k + 1] = hw[x]
                l_a[k + 1] = al[x]
            for k in range(nk + 1, nk_all + 1):
                row[:, c, k] = 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def _gradient_magnitude(image, out, scratch):
    """``|grad image|`` (five-point derivatives) into ``out``."""
    _diff_x(image, out)
    _diff_y(image, scratch)
    H, W = image.shape
    for y in range(H):
        o = out[y]
        g = scratch[y]
        for x in range(W):
            o[x] = math.sqrt(o[x] * o[x] + g[x] * g[x])


@njit(cache=True, error_model="numpy", nogil=True)
def _prepare_level(
    image1,
    image2,
    flow,
    flow_scale,
    match,
    match_scale,
    half_weight,
    alpha,
    zeta2,
    scratch,
    data,
    level,
    bspline,
):
    """Pack one level's data terms into ``data`` and its constants into ``level``.

    ``flow`` is first multiplied in place by ``flow_scale`` (x, y), which
    turns a flow resampled from another level into this level's pixels.
    ``scratch`` is (13, H, W): derivative planes of both frames and the
    warp mask.
    """
    sx = np.float32(flow_scale[0])
    sy = np.float32(flow_scale[1])
    for y in range(flow.shape[0]):
        f = flow[y]
        for x in range(flow.shape[1]):
            f[x, 0] *= sx
            f[x, 1] *= sy
    s1 = scratch[0:6]
    s2 = scratch[6:12]
    _derivatives(image1, s1)
    _warp(image2, flow, s2[0], scratch[12], bspline)
    _derivatives(s2[0], s2)
    _pack_data(s1, s2, scratch[12], zeta2, data)
    _pack_level(flow, match, match_scale, half_weight, alpha, level)


@njit(cache=True, error_model="numpy", nogil=True)
def _add_increment(flow, du, dv):
    """``flow`` (H, W, 2) plus the packed increments."""
    H, W, _ = flow.shape
    out = np.empty((H, W, 2), np.float32)
    for y in range(H):
        for x in range(W):
            c = (x + y) & 1
            k = (x >> 1) + 1
            out[y, x, 0] = flow[y, x, 0] + du[y + 1, c, k]
            out[y, x, 1] = flow[y, x, 1] + dv[y + 1, c, k]
    return out


@njit(cache=True, error_model="numpy", nogil=True)
def _sor_row(du, dv, E, S, coef, c, y, omega):
    """Over-relax the colour-``c`` pixels of row ``y`` (Gauss-Seidel on u, then v)."""
    o = 1 - c
    yy = y + 1
    p = (y + c) & 1
    nk = du.shape[2] - 2
    du_c = du[yy, c]
    dv_c = dv[yy, c]
    du_o = du[yy, o]
    dv_o = dv[yy, o]
    du_n = du[yy - 1, o]
    dv_n = dv[yy - 1, o]
    du_s = du[yy + 1, o]
    dv_s = dv[yy + 1, o]
    e_c = E[yy, c]
    e_o = E[yy, o]
    s_c = S[yy, c]
    s_n = S[yy - 1, o]
    a12 = coef[yy, 0, c]
    b1 = coef[yy, 1, c]
    b2 = coef[yy, 2, c]
    i11 = coef[yy, 3, c]
    i22 = coef[yy, 4, c]
    for k in range(1, nk + 1):
        kw = k + p - 1
        ke = k + p
        we = e_c[k]
        ww = e_o[kw]
        ws = s_c[k]
        wn = s_n[k]
        su = we * du_o[ke] + ww * du_o[kw] + ws * du_s[k] + wn * du_n[k]
        sv = we * dv_o[ke] + ww * dv_o[kw] + ws * dv_s[k] + wn * dv_n[k]
        old_u = du_c[k]
        new_u = old_u + omega * ((b1[k] + su - a12[k] * dv_c[k]) * i11[k] - old_u)
        du_c[k] = new_u
        old_v = dv_c[k]
        dv_c[k] = old_v + omega * ((b2[k] + sv - a12[k] * new_u) * i22[k] - old_v)


@njit(cache=True, error_model="numpy", nogil=True)
def _sor_step(du, dv, E, S, coef, t, n, omega):
    """Step ``t`` of ``n`` pipelined red-black SOR sweeps (see :func:`_sor`)."""
    H = du.shape[0] - 2
    for j in range(n):
        y = t - 2 * j
        if 0 <= y < H:
            _sor_row(du, dv, E, S, coef, 0, y, omega)
        if 1 <= y <= H:
            _sor_row(du, dv, E, S, coef, 1, y - 1, omega)


@njit(cache=True, error_model="numpy", nogil=True)
def _sor(du, dv, E, S, coef, n_sor, omega, chunk):
    """``n_sor`` red-black SOR sweeps, ``chunk`` of them per pass over memory.

    Sweeps are pipelined along the rows (temporal blocking): in step t,
    sweep j over-relaxes the red pixels of row t - 2j and then the black
    pixels of row t - 2j - 1. Every pixel is then updated from exactly the
    neighbour values of plain sweep-after-sweep red-black SOR, so the result
    is the same (to rounding: the compiler may fuse multiply-adds
    differently), while the ~2 * chunk rows in flight stay in cache instead
    of the whole level streaming through memory every half-sweep.
    """
    H = du.shape[0] - 2
    om = np.float32(omega)
    done = 0
    while done < n_sor:
        n = min(chunk, n_sor - done)
        for t in range(H + 1 + 2 * (n - 1)):
            _sor_step(du, dv, E, S, coef, t, n, om)
        done += n


@njit(cache=True, error_model="numpy", nogil=True)
def _total_rows(level, du, dv, T, H, W, r0, r1):
    """Total flow u + du, v + dv of rows [r0, r1) into ``T``, ring replicated.

    The ring slots a border pixel's stencil reaches into hold that pixel's
    own value, so central differences see a replicated border.
    """
    nk = T.shape[3] - 2
    for y in range(r0, r1):
        yy = y + 1
        for c in range(2):
            t_u = T[yy, 0, c]
            t_v = T[yy, 1, c]
            l_u = level[yy, 0, c]
            l_v = level[yy, 1, c]
            d_u = du[yy, c]
            d_v = dv[yy, c]
            for k in range(1, nk + 1):
                t_u[k] = l_u[k] + d_u[k]
                t_v[k] = l_v[k] + d_v[k]
        c0 = y & 1  # colour of x = 0
        c1 = (W - 1 + y) & 1  # colour of x = W - 1
        k1 = (W - 1) // 2 + 1
        p1 = (W - 1) & 1
        for q in range(2):
            T[yy, q, 1 - c0, 0] = T[yy, q, c0, 1]
            T[yy, q, 1 - c1, k1 + p1] = T[yy, q, c1, k1]
    if r0 == 0:
        for q in range(2):
            for c in range(2):
                T[0, q, 1 - c] = T[1, q, c]
    if r1 == H:
        for q in range(2):
            for c in range(2):
                T[H + 1, q, 1 - c] = T[H, q, c]


@njit(cache=True, error_model="numpy", nogil=True)
def _smoothness_rows(T, level, a, eps2, W, r0, r1):
    """Robust smoothness weights ``alpha(x) psi'(|grad w|^2)`` of rows [r0, r1)."""
    half = np.float32(0.5)
    quarter = np.float32(0.25)
    e2 = np.float32(eps2)
    for y in range(r0, r1):
        yy = y + 1
        for c in range(2):
            o = 1 - c
            p = (y + c) & 1
            u_o = T[yy, 0, o]
            u_n = T[yy - 1, 0, o]
            u_s = T[yy + 1, 0, o]
            v_o = T[yy, 1, o]
            v_n = T[yy - 1, 1, o]
            v_s = T[yy + 1, 1, o]
            alpha = level[yy, 5, c]
            out = a[yy, c]
            for k in range(1, (W - p + 1) // 2 + 1):
                ux = u_o[k + p] - u_o[k + p - 1]
                uy = u_s[k] - u_n[k]
                vx = v_o[k + p] - v_o[k + p - 1]
                vy = v_s[k] - v_n[k]
                g2 = quarter * (ux * ux + uy * uy + vx * vx + vy * vy)
                out[k] = alpha[k] * half / math.sqrt(g2 + e2)


@njit(cache=True, error_model="numpy", nogil=True)
def _link_rows(a, E, S, H, W, r0, r1):
    """Links to the east and south neighbours (mean of both weights; 0 off the image)."""
    half = np.float32(0.5)
    for y in range(r0, r1):
        yy = y + 1
        for c in range(2):
            o = 1 - c
            p = (y + c) & 1
            nk = (W - p + 1) // 2
            a_c = a[yy, c]
            a_o = a[yy, o]
            a_s = a[yy + 1, o]
            e = E[yy, c]
            s = S[yy, c]
            for k in range(1, nk + 1):
                e[k] = half * (a_c[k] + a_o[k + p])
            if 2 * (nk - 1) + p == W - 1:
                e[nk] = 0.0
            if y < H - 1:
                for k in range(1, nk + 1):
                    s[k] = half * (a_c[k] + a_s[k])
            else:
                s[:] = 0.0


@njit(cache=True, error_model="numpy", nogil=True)
def _coef_rows(level, data, du, dv, E, S, coef, delta, gamma, eps2, r0, r1):
    """Frozen linear system of rows [r0, r1): data, matching and smoothness terms.

    Slots outside the image come out with zero inverse diagonals (their
    data, matching weight and links are zero), which keeps them at zero.
    """
    half = np.float32(0.5)
    zero = np.float32(0.0)
    one = np.float32(1.0)
    dl = np.float32(delta) * half
    gm = np.float32(gamma) * half
    e2 = np.float32(eps2)
    nk = coef.shape[3] - 2
    for y in range(r0, r1):
        yy = y + 1
        g = data[yy]
        out = coef[yy]
        for c in range(2):
            o = 1 - c
            p = (y + c) & 1
            e_c = E[yy, c]
            e_o = E[yy, o]
            s_c = S[yy, c]
            s_n = S[yy - 1, o]
            u_c = level[yy, 0, c]
            u_o = level[yy, 0, o]
            u_n = level[yy - 1, 0, o]
            u_s = level[yy + 1, 0, o]
            v_c = level[yy, 1, c]
            v_o = level[yy, 1, o]
            v_n = level[yy - 1, 1, o]
            v_s = level[yy + 1, 1, o]
            f_u = level[yy, 2, c]
            f_v = level[yy, 3, c]
            m_w = level[yy, 4, c]
            d_u = du[yy, c]
            d_v = dv[yy, c]
            o_a12, o_b1, o_b2, o_i11, o_i22 = out[0, c], out[1, c], out[2, c], out[3, c], out[4, c]
            # The smoothness acting on the fixed part of the flow and the sum
            # of the links are parked in the output rows: split in two, each
            # loop has few enough memory streams for LLVM to vectorise it.
            for k in range(1, nk + 1):
                west = k + p - 1
                u0 = u_c[k]
                v0 = v_c[k]
                o_b1[k] = (
                    e_c[k] * (u_o[k + p] - u0)
                    + e_o[west] * (u_o[west] - u0)
                    + s_c[k] * (u_s[k] - u0)
                    + s_n[k] * (u_n[k] - u0)
                )
                o_b2[k] = (
                    e_c[k] * (v_o[k + p] - v0)
                    + e_o[west] * (v_o[west] - v0)
                    + s_c[k] * (v_s[k] - v0)
                    + s_n[k] * (v_n[k] - v0)
                )
                o_i11[k] = e_c[k] + e_o[west] + s_c[k] + s_n[k]
            for k in range(1, nk + 1):
                xu = d_u[k]
                xv = d_v[k]
                ix = g[0, c, k]
                iy = g[1, c, k]
                it = g[2, c, k]
                nc = g[3, c, k]
                ixx = g[4, c, k]
                ixy = g[5, c, k]
                iyy = g[6, c, k]
                ixt = g[7, c, k]
                iyt = g[8, c, k]
                ngx = g[9, c, k]
                ngy = g[10, c, k]
                rc = it + ix * xu + iy * xv
                pc = dl * nc / math.sqrt(nc * rc * rc + e2)
                rx = ixt + ixx * xu + ixy * xv
                ry = iyt + ixy * xu + iyy * xv
                pg = gm / math.sqrt(ngx * rx * rx + ngy * ry * ry + e2)
                gx = pg * ngx
                gy = pg * ngy
                eu = f_u[k] + xu
                ev = f_v[k] + xv
                pm = m_w[k] / math.sqrt(eu * eu + ev * ev + e2)
                sw = o_i11[k]
                d11 = pc * ix * ix + gx * ixx * ixx + gy * ixy * ixy + pm + sw
                d22 = pc * iy * iy + gx * ixy * ixy + gy * iyy * iyy + pm + sw
                o_a12[k] = pc * ix * iy + gx * ixx * ixy + gy * ixy * iyy
                o_b1[k] = o_b1[k] - (pc * ix * it + gx * ixx * ixt + gy * ixy * iyt) - pm * f_u[k]
                o_b2[k] = o_b2[k] - (pc * iy * it + gx * ixy * ixt + gy * iyy * iyt) - pm * f_v[k]
                o_i11[k] = one / d11 if d11 > zero else zero
                o_i22[k] = one / d22 if d22 > zero else zero


# Rows between the row the setup starts on and the first SOR sweep's red row
# in :func:`_outer_iteration`: the setup's four stages reach 3 rows back, and
# the sweep must not touch a row before the setup has read its increments.
_SETUP_LAG = 4


@njit(cache=True, error_model="numpy", nogil=True)
def _outer_iteration(
    level, data, du, dv, T, a, E, S, coef, delta, gamma, eps2, W, n_sor, omega, chunk
):
    """One fixed-point iteration: freeze the robust weights, then ``n_sor`` SOR sweeps.

    The four setup stages (total flow, smoothness weights, links, linear
    system) run one row behind each other, and the first ``chunk`` sweeps
    follow ``_SETUP_LAG`` rows behind them, all in one pass over the rows:
    what a stage writes is still in cache when the next one reads it. Each
    row sees the same values as running the stages and sweeps one after
    the other, so the result is the same (to rounding).
    """
    H = level.shape[0] - 2
    om = np.float32(omega)
    n = min(chunk, n_sor)
    for t in range(H + _SETUP_LAG + 1 + 2 * (n - 1)):
        if t < H:
            _total_rows(level, du, dv, T, H, W, t, t + 1)
        if 0 <= t - 1 < H:
            _smoothness_rows(T, level, a, eps2, W, t - 1, t)
        if 0 <= t - 2 < H:
            _link_rows(a, E, S, H, W, t - 2, t - 1)
        if 0 <= t - 3 < H:
            _coef_rows(level, data, du, dv, E, S, coef, delta, gamma, eps2, t - 3, t - 2)
        _sor_step(du, dv, E, S, coef, t - _SETUP_LAG, n, om)
    if n_sor > n:
        _sor(du, dv, E, S, coef, n_sor - n, omega, chunk)


def _sor_chunk(width: int, n_sor: int) -> int:
    """Sweeps per pass over memory so that the rows in flight fit ``_SOR_CACHE_BYTES``."""
    row_bytes = 4 * (4 + _N_COEF) * max(width, 1)
    rows = _SOR_CACHE_BYTES // row_bytes
    return int(max(1, min(n_sor, (rows - 2) // 2)))


def _packed_width(width: int) -> int:
    """Last dimension of the packed arrays: whole 8-float vectors plus the ring."""
    return ((width + 1) // 2 + 7) // 8 * 8 + 2


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


class _Pyramid:
    """Area-averaged versions of an image at any scale.

    Each level is resampled from the finest power-of-two reduction at or
    above its scale (exact 2x2 box averages of one another), not from the
    full image: the cost then follows the level's size, not the frame's.
    """

    def __init__(self, image: np.ndarray) -> None:
        self._octaves = [image]

    def level(self, h: int, w: int) -> np.ndarray:
        """The image area-resampled to ``h`` x ``w``."""
        if (h, w) == self._octaves[0].shape:
            return self._octaves[0]
        source = self._octaves[0]
        k = 1
        while True:
            if k == len(self._octaves):
                sh, sw = source.shape
                if sh // 2 < h or sw // 2 < w:
                    break
                self._octaves.append(
                    cv2.resize(source, (sw // 2, sh // 2), interpolation=cv2.INTER_AREA)
                )
            if self._octaves[k].shape[0] < h or self._octaves[k].shape[1] < w:
                break
            source = self._octaves[k]
            k += 1
        return cv2.resize(source, (w, h), interpolation=cv2.INTER_AREA)


def _solve(
    ws: Workspace,
    params: VariationalParams,
    level: np.ndarray,
    data: np.ndarray,
    h: int,
    w: int,
    checkpoint: Callable[[], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Packed flow increments ``du``, ``dv`` of one pyramid level.

    ``n_outer`` fixed-point iterations freeze the robust weights at the current flow and
    solve the linearised system with ``n_sor`` SOR sweeps, each iteration one kernel call
    with the ``checkpoint`` before it: a large level's solve takes seconds, and a run that
    is stopping must not wait for it.
    """
    shape = (h + 2, 2, _packed_width(w))
    n_sor = int(params.n_sor)
    # du, dv (the increments) and E, S (the links) start at zero; T, a and coef are scratch.
    du, dv, E, S = (ws.array(name, shape, zero=True) for name in ("du", "dv", "E", "S"))
    T, a = ws.array("T", (h + 2, 2, 2, shape[2])), ws.array("a", shape)
    coef = ws.array("coef", (h + 2, _N_COEF) + shape[1:])
    chunk = _sor_chunk(w, n_sor)
    for _outer in range(int(params.n_outer)):
        if checkpoint is not None:
            checkpoint()
        _outer_iteration(level, data, du, dv, T, a, E, S, coef, float(params.delta), float(params.gamma),
                         float(params.eps**2), w, n_sor, float(params.omega), chunk)
    return du, dv


def _normalised_pair(reference: np.ndarray, current: np.ndarray,
                     params: VariationalParams) -> tuple[np.ndarray, np.ndarray]:
    """The two images as float32 on [0, 1] (uint8 / 255), brought to ``params.contrast_std``
    by one gain for both and pre-smoothed by ``params.sigma``."""
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
    return im1, im2


def _warp_source(image: np.ndarray, ws: Workspace) -> np.ndarray:
    """What :func:`_warp` samples for ``image``: its B-spline coefficients (in the workspace)
    or the image itself."""
    if not _WARP_BSPLINE:
        return image
    coef = ws.array("bspline", image.shape)
    _bspline_coefficients(image, coef)
    return coef


def _smoothness_weight(image: np.ndarray, params: VariationalParams, scale: float, ws: Workspace) -> np.ndarray:
    """The local smoothness weight ``alpha exp(-kappa |grad|)`` of one pyramid level (in the
    workspace's ``alpha`` array), from the gradient of ``image`` blurred by ``edge_sigma``."""
    h, w = image.shape
    if params.edge_sigma > 0:
        # Edges of objects survive this blur, fine texture does not.
        edges = cv2.GaussianBlur(image, (0, 0), params.edge_sigma * scale)
    else:
        edges = image
    alpha = ws.array("alpha", (h, w))
    _gradient_magnitude(edges, alpha, ws.array("gy", (h, w)))
    alpha *= np.float32(-params.kappa)
    np.exp(alpha, out=alpha)
    alpha *= np.float32(params.alpha)
    return alpha


def refine(
    reference: np.ndarray,
    current: np.ndarray,
    params: VariationalParams,
    *,
    match_flow: np.ndarray | None = None,
    match_weight: np.ndarray | None = None,
    workspace: Workspace | None = None,
    checkpoint: Callable[[], None] | None = None,
) -> np.ndarray:
    """Coarse-to-fine minimisation of the DeepFlow energy.

    Parameters
    ----------
    reference, current : ndarray (H, W), uint8 or float32
        Grey images of one shape (any range; scaled to [0, 1] internally using 255 for uint8).
    params : VariationalParams
    match_flow, match_weight : ndarray (H, W, 2) and (H, W), optional
        Dense rasterised matches ``w'`` and their weights ``c * phi`` in [0, 1].
    workspace : Workspace, optional
        Scratch arrays to reuse (one per thread); a fresh one by default.
    checkpoint : callable, optional
        Called before each pyramid level and each fixed-point iteration; it raises to abandon
        the solve (a run that is stopping, :meth:`flow.methods.base.DenseMethod.check_stop`).

    Returns
    -------
    ndarray (H, W, 2) float32

    Raises
    ------
    ValueError
        If the images differ in shape, are not 2-D or not uint8 / float32, or the matches do
        not have the reference's shape (the numba kernels do not bounds-check).
    """
    check_grey_pair(reference, current)
    if match_flow is not None:
        check_shape("match_flow", match_flow, reference.shape, (2,))
    if match_weight is not None:
        check_shape("match_weight", match_weight, reference.shape)
    ws = workspace if workspace is not None else Workspace()
    im1, im2 = _normalised_pair(reference, current, params)
    height, width = im1.shape
    levels = _level_sizes(height, width, params.eta, params.min_size)
    use_matches = match_flow is not None and match_weight is not None and params.beta > 0
    h0, w0, _ = levels[-1]
    flow = np.zeros((h0, w0, 2), np.float32)
    pyr1, pyr2 = _Pyramid(im1), _Pyramid(im2)
    if use_matches:
        matches = np.ascontiguousarray(match_flow, dtype=np.float32)
        weights = _Pyramid(np.float32(0.5 * params.beta) * match_weight.astype(np.float32))
    for h, w, scale in reversed(levels):
        if checkpoint is not None:
            checkpoint()
        flow_scale = (w / flow.shape[1], h / flow.shape[0])
        if flow_scale != (1.0, 1.0):
            flow = cv2.resize(flow, (w, h), interpolation=cv2.INTER_LINEAR)
        i1 = pyr1.level(h, w)
        alpha = _smoothness_weight(i1, params, scale, ws)
        if use_matches and scale <= params.match_max_scale:
            match = cv2.resize(matches, (w, h), interpolation=cv2.INTER_LINEAR)
            match_scale = (w / width, h / height)
            half_weight = weights.level(h, w)
        else:
            match = ws.array("no_match", (h, w, 2), zero=True)
            match_scale = (1.0, 1.0)
            half_weight = ws.array("no_weight", (h, w), zero=True)
        packed = (2, _packed_width(w))
        data = ws.array("data", (h + 2, _N_DATA) + packed)
        level = ws.array("level", (h + 2, _N_LEVEL) + packed)
        _prepare_level(
            i1,
            _warp_source(pyr2.level(h, w), ws),
            flow,
            flow_scale,
            match,
            match_scale,
            half_weight,
            alpha,
            float(params.zeta**2),
            ws.array("planes", (13, h, w)),
            data,
            level,
            _WARP_BSPLINE,
        )
        du, dv = _solve(ws, params, level, data, h, w, checkpoint)
        flow = _add_increment(flow, du, dv)
    return flow
