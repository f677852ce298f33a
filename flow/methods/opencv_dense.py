"""Dense reference-frame methods backed by OpenCV (contrib) optical flow.

References
----------
P. Weinzaepfel, J. Revaud, Z. Harchaoui, C. Schmid, "DeepFlow: Large displacement
optical flow with deep matching", ICCV 2013 (OpenCV ``optflow.createOptFlow_DeepFlow``).
T. Kroeger, R. Timofte, D. Dai, L. Van Gool, "Fast optical flow using dense inverse
search", ECCV 2016 (``cv2.DISOpticalFlow``).
G. Farneback, "Two-frame motion estimation based on polynomial expansion", SCIA 2003.
C. Zach, T. Pock, H. Bischof, "A duality based approach for realtime TV-L1 optical
flow", DAGM 2007 (``optflow.DualTVL1OpticalFlow``).
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from flow.io.frames import as_uint8
from flow.methods.base import CROP, DenseMethod, register, register_unavailable
from flow.methods.params import Param


def _has_optflow() -> bool:
    return hasattr(cv2, "optflow") and hasattr(cv2.optflow, "createOptFlow_DeepFlow")


class _OpenCVDense(DenseMethod):
    """Shared plumbing: build the OpenCV object lazily, one per instance (not thread-safe)."""

    full_depth = False

    def __init__(self, **params: Any) -> None:
        super().__init__(**params)
        self._engine = None

    def _build(self) -> Any:
        raise NotImplementedError

    def _solve(self, reference: np.ndarray, current: np.ndarray, *,
               whole_shape: tuple[int, ...]) -> np.ndarray:
        if self._engine is None:
            self._engine = self._build()
        flow = self._engine.calc(as_uint8(reference), as_uint8(current), None)
        return np.asarray(flow, dtype=np.float32)


if _has_optflow():

    @register("deepflow-opencv")
    class OpenCVDeepFlow(_OpenCVDense):
        """OpenCV contrib DeepFlow (variational refinement, no DeepMatching)."""

        summary = "OpenCV contrib DeepFlow (Weinzaepfel 2013) without DeepMatching; dense, vs reference frame"

        def __init__(self, *, crop: bool = True) -> None:
            super().__init__(crop=crop)

        def _build(self) -> Any:
            return cv2.optflow.createOptFlow_DeepFlow()
else:
    register_unavailable("deepflow-opencv", f"this OpenCV {cv2.__version__} build lacks "
                         "optflow.createOptFlow_DeepFlow (opencv-contrib)")


_DIS_PRESETS = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST,
                "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
                "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}


@register("dis")
class DIS(_OpenCVDense):
    """Dense inverse search.

    Parameters
    ----------
    preset : {"ultrafast", "fast", "medium"}
        OpenCV preset; ``finest_scale=0`` (full resolution) and extra variational
        refinement make the default reach ~0.01 px on textured surfaces.
    finest_scale : int or None
        Overrides the preset's finest pyramid level (0 = full resolution).
    refinement_iterations : int or None
        Overrides the preset's variational refinement iterations.
    """

    summary = "OpenCV DIS (Kroeger 2016), preset ultrafast|fast|medium, full-resolution refinement; dense, vs reference frame"
    parameters = (
        Param("preset", "choice", "medium", "OpenCV preset (also --preset)", choices=tuple(_DIS_PRESETS)),
        Param("finest_scale", "int", 0, "finest pyramid level solved (0: full resolution)", 0, 10,
              optional=True, none_means="the preset's"),
        Param("refinement_iterations", "int", 10, "variational refinement iterations", 0, 200,
              optional=True, none_means="the preset's"),
        CROP)

    def __init__(self, *, preset: str = "medium", finest_scale: int | None = 0,
                 refinement_iterations: int | None = 10, crop: bool = True) -> None:
        if preset not in _DIS_PRESETS:
            raise ValueError(f"DIS preset {preset!r} unknown; use one of {', '.join(_DIS_PRESETS)}")
        super().__init__(crop=crop, preset=preset, finest_scale=finest_scale,
                         refinement_iterations=refinement_iterations)

    def _build(self) -> Any:
        dis = cv2.DISOpticalFlow_create(_DIS_PRESETS[self._params["preset"]])
        if self._params["finest_scale"] is not None:
            dis.setFinestScale(int(self._params["finest_scale"]))
        if self._params["refinement_iterations"] is not None:
            dis.setVariationalRefinementIterations(int(self._params["refinement_iterations"]))
        return dis


@register("farneback")
class Farneback(DenseMethod):
    """Farneback polynomial-expansion flow (keyword parameters as in OpenCV)."""

    summary = "OpenCV Farneback polynomial expansion (2003); dense, vs reference frame"
    # Beyond these OpenCV asserts (pyr_scale >= 1) or allocates and runs without end (a window or
    # polynomial neighbourhood of millions of pixels).
    parameters = (
        Param("pyr_scale", "float", 0.5, "scale between pyramid levels", 0.1, 0.9),
        Param("levels", "int", 4, "pyramid levels above the image (OpenCV stops at small sizes)", 0, 20),
        Param("winsize", "int", 15, "averaging window side, px", 3, 101),
        Param("iterations", "int", 5, "iterations per pyramid level", 1, 50),
        Param("poly_n", "int", 7, "pixel neighbourhood of the polynomial expansion (5 or 7 typical)", 3, 11),
        Param("poly_sigma", "float", 1.5, "Gaussian sigma of the expansion (1.1 for poly_n 5, 1.5 for 7)", 0.5, 5),
        CROP)
    full_depth = False

    def __init__(self, *, pyr_scale: float = 0.5, levels: int = 4, winsize: int = 15,
                 iterations: int = 5, poly_n: int = 7, poly_sigma: float = 1.5,
                 crop: bool = True) -> None:
        super().__init__(crop=crop, pyr_scale=pyr_scale, levels=levels, winsize=winsize,
                         iterations=iterations, poly_n=poly_n, poly_sigma=poly_sigma)

    def _solve(self, reference: np.ndarray, current: np.ndarray, *,
               whole_shape: tuple[int, ...]) -> np.ndarray:
        p = self._params
        flow = cv2.calcOpticalFlowFarneback(
            as_uint8(reference), as_uint8(current), None, p["pyr_scale"], p["levels"],
            p["winsize"], p["iterations"], p["poly_n"], p["poly_sigma"],
            cv2.OPTFLOW_FARNEBACK_GAUSSIAN)
        return np.asarray(flow, dtype=np.float32)


if _has_optflow() and hasattr(cv2.optflow, "DualTVL1OpticalFlow_create"):

    @register("tvl1")
    class TVL1(_OpenCVDense):
        """Dual TV-L1 optical flow.

        Parameters
        ----------
        lambda_ : float
            Data-term weight; 0.05 (OpenCV default 0.15) keeps displacements of several
            pixels on smooth textures from being flattened by the TV term; 6 scales and
            10 warps (OpenCV: 5, 5) reach 5 px shifts.
        warps, scales, epsilon : as OpenCV ``setWarpingsNumber``/``setScalesNumber``/``setEpsilon``.
        """

        summary = "OpenCV contrib dual TV-L1 (Zach 2007); dense, vs reference frame; slow"
        parameters = (
            Param("lambda_", "float", 0.05, "data-term weight", 0, 10, low_open=True),
            Param("warps", "int", 10, "warpings per scale", 1, 50),
            Param("scales", "int", 6, "pyramid scales", 1, 20),
            Param("epsilon", "float", 0.001, "stopping tolerance", 0, 1, low_open=True),
            CROP)

        def __init__(self, *, lambda_: float = 0.05, warps: int = 10, scales: int = 6,
                     epsilon: float = 0.001, crop: bool = True) -> None:
            super().__init__(crop=crop, lambda_=lambda_, warps=warps, scales=scales, epsilon=epsilon)

        def _build(self) -> Any:
            p = self._params
            tvl1 = cv2.optflow.DualTVL1OpticalFlow_create()
            tvl1.setLambda(float(p["lambda_"]))
            tvl1.setWarpingsNumber(int(p["warps"]))
            tvl1.setScalesNumber(int(p["scales"]))
            tvl1.setEpsilon(float(p["epsilon"]))
            return tvl1
else:
    register_unavailable("tvl1", f"this OpenCV {cv2.__version__} build lacks optflow.DualTVL1OpticalFlow")
