"""Figures drawn by both ``flow`` and ``analysis``: the POIs against the corners KLT tracks
(paper Fig. 6), written by ``refflow pois`` and by ``python -m analysis figures``."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from refflow.io import atomic_path

# BGR colours of regions 1, 2, ... (a colour-blind-safe palette, Okabe-Ito), repeated beyond 8.
REGION_COLOURS = ((0, 220, 0), (0, 159, 230), (233, 180, 86), (0, 94, 213), (66, 228, 240),
                  (178, 114, 0), (167, 121, 204), (115, 158, 0))


def region_colour(label: int) -> tuple[int, int, int]:
    """BGR colour of region ``label`` (1-based) in the figures."""
    return REGION_COLOURS[(int(label) - 1) % len(REGION_COLOURS)]


def poi_figure(reference: np.ndarray, poi_xy: np.ndarray, corners_xy: np.ndarray | None,
               path: str | Path, *, scale: int | None = None, region: np.ndarray | None = None) -> None:
    """Write a side-by-side PNG: POIs (left, green; each region in its own colour where
    ``region`` gives the POIs' labels) and corners (right, red) on the reference image.

    ``reference`` is a 2-D uint8 image; ``poi_xy`` integer pixel positions (N, 2), x first;
    ``corners_xy`` the corners KLT tracks (M, 2), sub-pixel, in the same pixels; ``None``
    where no KLT run is at hand (the right panel says so). ``scale`` enlarges small images so
    single pixels stay visible (default: to ~600 px wide).
    """
    reference = np.asarray(reference)
    if reference.ndim != 2 or reference.dtype != np.uint8:
        raise ValueError(f"reference must be a 2-D uint8 image, got shape {reference.shape} "
                         f"dtype {reference.dtype}")
    height, width = reference.shape
    if scale is None:
        scale = max(1, int(round(600 / max(width, 1))))
    base = cv2.cvtColor(reference, cv2.COLOR_GRAY2BGR)
    base = cv2.resize(base, (width * scale, height * scale), interpolation=cv2.INTER_NEAREST)
    left, right = base.copy(), base.copy()
    radius = max(1, scale // 2)
    points = np.asarray(poi_xy).reshape(-1, 2)
    labels = np.ones(len(points), int) if region is None else np.asarray(region, int)
    for (x, y), label in zip(points, labels, strict=True):
        cv2.circle(left, (int(x * scale + scale // 2), int(y * scale + scale // 2)), radius,
                   region_colour(label), -1)
    corners = np.zeros((0, 2)) if corners_xy is None else np.asarray(corners_xy).reshape(-1, 2)
    for x, y in corners:
        cv2.circle(right, (int(round(x * scale)), int(round(y * scale))), 3 * radius + 2, (0, 0, 255), 2)
    label = (cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 2)
    cv2.putText(left, f"mask POIs: {len(poi_xy)}", (8, 22), label[0], label[1], label[2], label[3])
    if region is not None and len(np.unique(labels)) > 1:
        for row, value in enumerate(np.unique(labels)):
            cv2.putText(left, f"region {value}", (8, 46 + 22 * row), label[0], label[1],
                        region_colour(value), label[3])
    corners_text = "corners (KLT): no KLT run" if corners_xy is None else f"corners (KLT): {len(corners_xy)}"
    cv2.putText(right, corners_text, (8, 22), label[0], label[1], label[2], label[3])
    gap = np.full((base.shape[0], 8, 3), 255, np.uint8)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.hstack([left, gap, right])):
            raise OSError(f"cannot write {path}")
