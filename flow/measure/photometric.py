"""What the images say about a measured displacement: the photometric residual
``|I_cur(x + d) - I_ref(x)|`` at the POIs, and the standard uncertainty of their mean
displacement that the residual implies (the Lucas-Kanade covariance).
"""

from __future__ import annotations

import cv2
import numpy as np


def sample(image: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of ``image`` at float positions (NaN outside the image)."""
    height, width = image.shape
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    inside = np.isfinite(x) & np.isfinite(y) & (x >= 0) & (y >= 0) & (x <= width - 1) & (y <= height - 1)
    xc = np.clip(np.where(inside, x, 0.0), 0, width - 1)
    yc = np.clip(np.where(inside, y, 0.0), 0, height - 1)
    x0 = np.minimum(xc.astype(np.intp), max(width - 2, 0))
    y0 = np.minimum(yc.astype(np.intp), max(height - 2, 0))
    fx, fy = xc - x0, yc - y0
    x1, y1 = np.minimum(x0 + 1, width - 1), np.minimum(y0 + 1, height - 1)
    # The four neighbours gathered first, then converted: a whole-frame float copy per call
    # cost a 4K frame 33 MB and more time than the samples (the values are the same).
    def at(rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        return image[rows, cols].astype(np.float32)

    top = at(y0, x0) * (1 - fx) + at(y0, x1) * fx
    bottom = at(y1, x0) * (1 - fx) + at(y1, x1) * fx
    return np.where(inside, top * (1 - fy) + bottom * fy, np.nan).astype(np.float32)


def mean_abs(error: np.ndarray) -> float:
    """Mean |error| over its finite values (NaN where none is): a photometric residual."""
    diff = np.abs(error)
    diff = diff[np.isfinite(diff)]
    return float(diff.mean()) if diff.size else float("nan")


def photometric_residual(reference_values: np.ndarray, current: np.ndarray, x: np.ndarray, y: np.ndarray,
                         dx: np.ndarray, dy: np.ndarray) -> float:
    """Mean ``|I_cur(x + d) - I_ref(x)|`` over the points (grey levels): how well ``d`` explains the frame."""
    return mean_abs(sample(current, x + dx, y + dy) - reference_values)


class LucasKanadeSigma:
    """Standard uncertainty of a mean displacement over the POIs from the photometric residual.

    The least-squares translation of the POIs has covariance ``s^2 (sum g g^T)^-1``
    (``g`` the reference's gradients, ``s^2`` the residual variance), for independent
    pixels; the residuals of a smoothed flow are correlated over neighbouring POIs, so it
    is scaled by their design effect along rows and columns (``1 + 2 sum rho``).
    """

    def __init__(self, reference: np.ndarray, poi_xy: np.ndarray) -> None:
        grey = reference.astype(np.float32)
        gx = cv2.Sobel(grey, cv2.CV_32F, 1, 0, ksize=3) / 8.0
        gy = cv2.Sobel(grey, cv2.CV_32F, 0, 1, ksize=3) / 8.0
        cols, rows = poi_xy[:, 0], poi_xy[:, 1]
        g = np.stack([gx[rows, cols], gy[rows, cols]], axis=1).astype(np.float64)
        self._tensor = g.T @ g
        self._x0, self._y0 = int(cols.min()), int(rows.min())
        self._shape = (int(rows.max()) - self._y0 + 1, int(cols.max()) - self._x0 + 1)
        self._rows, self._cols = rows - self._y0, cols - self._x0

    def sigma(self, residual: np.ndarray) -> tuple[float, float]:
        ok = np.isfinite(residual)
        if ok.sum() < 3 or not np.all(np.isfinite(self._tensor)):
            return float("nan"), float("nan")
        r = np.where(ok, residual, 0.0) - residual[ok].mean()
        var = float(np.mean(r[ok] ** 2))
        image = np.full(self._shape, np.nan)
        image[self._rows, self._cols] = np.where(ok, r, np.nan)
        effect = _design_effect(image, var, axis=1) * _design_effect(image, var, axis=0)
        try:
            cov = np.linalg.inv(self._tensor) * var * effect
        except np.linalg.LinAlgError:
            return float("nan"), float("nan")
        return float(np.sqrt(max(cov[0, 0], 0.0))), float(np.sqrt(max(cov[1, 1], 0.0)))


def _design_effect(image: np.ndarray, var: float, *, axis: int, max_lag: int = 32) -> float:
    """``1 + 2 sum rho(lag)`` of an image with NaN holes along one axis, while rho > 0."""
    total = 1.0
    if var <= 0:
        return total
    for lag in range(1, min(max_lag, image.shape[axis] - 1) + 1):
        a = image[:, :-lag] if axis == 1 else image[:-lag]
        b = image[:, lag:] if axis == 1 else image[lag:]
        both = np.isfinite(a) & np.isfinite(b)
        if both.sum() < 10:
            break
        rho = float(np.mean(a[both] * b[both])) / var
        if rho <= 0:
            break
        total += 2.0 * rho
    return total

