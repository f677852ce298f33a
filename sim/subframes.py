"""The sub-frames of each frame and every row's weights on them, shared by the image
(``sim.render``) and its ground truth (``sim.truth``) so that both average the same instants.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from sim.camera import SubframeSampling
from sim.masks import Pois
from sim.occlusion import SheetPath
from sim.view import View


class FrameSubframes(NamedTuple):
    """A frame's sub-frames and the weights of the window's rows (float32, rows x bins), of
    the POIs' rows (P x bins) and of the measurement point's row (bins)."""

    sampling: SubframeSampling
    window_weights: np.ndarray
    poi_weights: np.ndarray
    measure_weights: np.ndarray


class SubframeTable:
    """:meth:`at` gives frame ``index``'s :class:`FrameSubframes`: ``camera.motion_blur_subframes``
    bins per exposure, ``occlusion.motion_blur_subframes`` while the sheet moves (its edge
    sweeps ~100 px per exposure at 4K). The choice depends on the whole sensor's read-out,
    never on the window; each bin count's weights are computed once."""

    def __init__(self, view: View, pois: Pois, sheet: SheetPath):
        self.view, self.pois, self.sheet = view, pois, sheet
        self._by_count: dict[int, FrameSubframes] = {}

    def at(self, index: int) -> FrameSubframes:
        view = self.view
        cc, cam = view.cam_cfg, view.camera
        t = index / cc.fps
        span = float(cam.row_times(cam.height - 1)) + cc.exposure_s
        n = cc.motion_blur_subframes
        if self.sheet.moves_during(t, t + span):
            n = max(n, view.occ_cfg.motion_blur_subframes)
        if n not in self._by_count:
            smp = cam.sampling(n)
            rows = np.arange(view.window.y, view.window.y + view.window.height)
            self._by_count[n] = FrameSubframes(smp, smp.weights(rows).astype(np.float32),
                                               smp.weights(self.pois.rows),
                                               smp.weights(np.rint(view.measure_px[1:]))[0])
        return self._by_count[n]
