"""What a run measures: the raw per-POI :class:`Tracks` of its frames (a region's columns
read through a :class:`ColumnView`) and, after the quality flags and the eq. 10-12
filtering, the :class:`Measurement` it reports.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from flow.measure.filtering import FilterResult

# The sidecar's timings that are no sums over a run's frames: a merge of parts recomputes the
# rate and writes its own total; every other entry (seconds, a method's counts) adds up.
NOT_ADDITIVE_TIMINGS = ("frames_per_s", "total_s")


class ColumnView:
    """A column subset of a ``(frames, points)`` matrix (array or :class:`DiskMatrix`), indexed
    by rows like the matrix: what one region's POIs read of a run's tracks."""

    dtype = np.dtype(np.float32)
    ndim = 2

    def __init__(self, matrix: Any, columns: np.ndarray) -> None:
        self._matrix = matrix
        self._columns = np.asarray(columns, np.intp)
        self.shape = (int(matrix.shape[0]), int(self._columns.size))

    def __len__(self) -> int:
        return self.shape[0]

    def __getitem__(self, key: Any) -> np.ndarray:
        """Rows ``m[i]`` or ``m[a:b]`` of the matrix, this view's columns only."""
        return np.asarray(self._matrix[key])[..., self._columns]

    def __array__(self, dtype: Any = None, copy: Any = None) -> np.ndarray:
        whole = np.asarray(self._matrix[0:self.shape[0]])[:, self._columns]
        return whole if dtype is None else whole.astype(dtype)


@dataclass(kw_only=True)
class Tracks:
    """Raw per-POI measurement of a run (or of a range of its frames), before filtering.

    Keyword arguments only: most fields are arrays of like shapes, easily passed in the
    wrong place.
    """

    frame: np.ndarray  # (F,) int
    time_s: np.ndarray  # (F,)
    dx: Any  # (F, P) float32 (a DiskMatrix or an array), px, NaN where unknown
    dy: Any
    residual: np.ndarray  # (F,) mean |I_cur(x + d) - I_ref(x)| over POIs, grey levels
    x_px: np.ndarray  # (P,) POI / feature positions in the reference (ROI pixels)
    y_px: np.ndarray
    reference_frame: int
    # The method's own output at the reference frame (ideally zero), removed by the
    # filtering as the paper's offset; kept here so a range without the reference frame
    # is filtered exactly like the whole run.
    offset_dx: np.ndarray  # (P,) float64
    offset_dy: np.ndarray
    timings_s: dict[str, float] = field(default_factory=dict)
    truncated: bool = False
    header_frames: int = 0
    reference_digest: str = ""  # hash of the reference image the run compared against
    # The camera's own image motion at the POIs' centroid (--background-mask), already
    # taken out of dx, dy; None without a background.
    camera_dx: np.ndarray | None = None  # (F,) px
    camera_dy: np.ndarray | None = None
    # Standard uncertainty of the frame's mean displacement over the POIs (px); None:
    # estimated from the kept POIs' spread when measured (sparse methods).
    sigma_dx: np.ndarray | None = None  # (F,) px
    sigma_dy: np.ndarray | None = None
    # Where the method's sigma already holds the reference frame's own error (a fit whose
    # residuals compare the frame with the reference, a codec floor measured against it), so
    # that the quality step does not add it again (see flow.measure.quality.with_reference_term);
    # None: nowhere. (F,) bool, (F, R) with regions, as the sigmas.
    sigma_holds_reference: np.ndarray | None = None
    # Regions (a labelled mask): each POI's label; None for one region. With regions, the
    # per-frame values above (residual, camera, sigma) are (F, R), one column per label in
    # ascending order, each over (or at the centroid of) that region's POIs.
    region: np.ndarray | None = None  # (P,) int
    # Frames in which the method saw nothing of the scene (a sheet over the whole view, the
    # light gone: see flow.methods.deepflow.hidden); their readings are kept and flagged.
    # None: the method does not tell.
    hidden: np.ndarray | None = None  # (F,) bool
    # The reference is the mean of this many frames from reference_frame, taken while the
    # structure is at rest (--reference-average): their readings should agree (see
    # flow.measure.quality.rest_excess).
    reference_average: int = 1

    def labels(self) -> list[int]:
        """The regions' labels, ascending ([1] for a run of one region)."""
        return [1] if self.region is None else [int(v) for v in np.unique(self.region)]

    def select(self, label: int) -> Tracks:
        """The tracks of one region's POIs, as a run of that region alone would give them."""
        if self.region is None:
            if label != 1:
                raise ValueError(f"no region {label}: the run has one region (1)")
            return self
        labels = self.labels()
        if label not in labels:
            raise ValueError(f"no region {label}: the run's regions are {labels}")
        k = labels.index(label)
        columns = np.flatnonzero(self.region == label)

        def column(values: np.ndarray | None) -> np.ndarray | None:
            return None if values is None else np.asarray(values)[:, k]

        return replace(self, dx=ColumnView(self.dx, columns), dy=ColumnView(self.dy, columns),
                       residual=column(self.residual), x_px=self.x_px[columns], y_px=self.y_px[columns],
                       offset_dx=self.offset_dx[columns], offset_dy=self.offset_dy[columns],
                       camera_dx=column(self.camera_dx), camera_dy=column(self.camera_dy),
                       sigma_dx=column(self.sigma_dx), sigma_dy=column(self.sigma_dy),
                       sigma_holds_reference=column(self.sigma_holds_reference), region=None)


@dataclass(frozen=True)
class Resolution:
    """How well a clip resolves its motion on its better axis (:func:`flow.measure.quality.motion_resolution`):
    the axis, its typical standard uncertainty and the robust (5-95 %) range of its readings, px.
    NaN where not known (no uncertainty from the method, fewer than two valid frames)."""

    axis: str = ""
    sigma_px: float = float("nan")
    range_px: float = float("nan")

    @property
    def ratio(self) -> float:
        """``sigma_px / range_px`` (inf for a motion of no range, NaN where unknown)."""
        if not (np.isfinite(self.sigma_px) and np.isfinite(self.range_px)):
            return float("nan")
        return self.sigma_px / self.range_px if self.range_px > 0 else float("inf")


@dataclass
class Measurement:
    """Filtered, averaged displacement with quality flags."""

    tracks: Tracks
    filtered: FilterResult
    valid: np.ndarray  # (F,) bool
    poi_kept_frac: np.ndarray  # (F,) see :func:`consistent_fraction`
    flow_spread_px: np.ndarray  # (F,) robust spread of the kept POIs' displacement
    residual_threshold: float
    consistency_band_px: float = float("nan")
    sigma_dx: np.ndarray | None = None  # (F,) px, standard uncertainty of dx
    sigma_dy: np.ndarray | None = None
    typical_sigma_px: float = float("nan")  # :func:`flow.measure.quality.typical_sigma`
    unresolved: bool = False  # every frame flagged: resolves neither a sub-pixel reading nor its motion
    resolution: Resolution = field(default_factory=Resolution)
    # (x, y) px added to every frame's sigma: how much more the frames averaged into the
    # reference scatter than their sigmas say (flow.measure.quality.rest_excess)
    rest_excess_px: tuple[float, float] = (0.0, 0.0)
