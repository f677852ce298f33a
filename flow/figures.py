"""POI versus corner figure (paper Fig. 6): what the mask selects and what KLT would track."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from refflow.io import atomic_path


def poi_figure(reference: np.ndarray, poi_xy: np.ndarray, corners_xy: np.ndarray,
               path: str | Path, *, scale: int | None = None) -> None:
    """Write a side-by-side PNG: POIs (left, green) and corners (right, red) on the reference ROI.

    ``scale`` enlarges small ROIs so single pixels stay visible (default: to ~600 px wide).
    """
    height, width = reference.shape
    if scale is None:
        scale = max(1, int(round(600 / max(width, 1))))
    base = cv2.cvtColor(reference, cv2.COLOR_GRAY2BGR)
    base = cv2.resize(base, (width * scale, height * scale), interpolation=cv2.INTER_NEAREST)
    left, right = base.copy(), base.copy()
    radius = max(1, scale // 2)
    for x, y in np.asarray(poi_xy).reshape(-1, 2):
        cv2.circle(left, (int(x * scale + scale // 2), int(y * scale + scale // 2)), radius, (0, 220, 0), -1)
    for x, y in np.asarray(corners_xy).reshape(-1, 2):
        cv2.circle(right, (int(round(x * scale)), int(round(y * scale))), 3 * radius + 2, (0, 0, 255), 2)
    label = (cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 0), 2)
    cv2.putText(left, f"mask POIs: {len(poi_xy)}", (8, 22), label[0], label[1], label[2], label[3])
    cv2.putText(right, f"corners (KLT): {len(corners_xy)}", (8, 22), label[0], label[1], label[2], label[3])
    gap = np.full((base.shape[0], 8, 3), 255, np.uint8)
    with atomic_path(path) as tmp:
        if not cv2.imwrite(str(tmp), np.hstack([left, gap, right])):
            raise OSError(f"cannot write {path}")


def displacement_plot(series: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]], path: str | Path,
                      *, title: str = "", ylabel: str = "displacement (px)") -> None:
    """Plot displacement time series ``{label: (time_s, dx, dy)}`` (needs matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=True)
    for label, (time_s, dx, dy) in series.items():
        axes[0].plot(time_s, dx, label=label, lw=1.2)
        axes[1].plot(time_s, dy, label=label, lw=1.2)
    axes[0].set_ylabel(f"dx {ylabel}")
    axes[1].set_ylabel(f"dy {ylabel}")
    axes[1].set_xlabel("time (s)")
    axes[0].legend(loc="upper right", fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    if title:
        axes[0].set_title(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=120)
    plt.close(fig)
