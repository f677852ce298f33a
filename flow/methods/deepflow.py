"""``deepflow`` (DeepMatching + variational refinement) and ``deepmatching``.

Both are clean-room implementations from the papers (see
:mod:`flow.deepmatching` and :mod:`flow.variational`).

References
----------
.. [1] P. Weinzaepfel, J. Revaud, Z. Harchaoui, C. Schmid, "DeepFlow: Large
   displacement optical flow with deep matching", ICCV 2013.
.. [2] J. Revaud et al., "DeepMatching: Hierarchical Deformable Dense
   Matching", IJCV 2016.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from flow.deepmatching import MatchParams, deep_matching, densify
from flow.registry import DenseMethod, check_pair, register
from flow.variational import VariationalParams, Workspace, refine

_MATCH_FIELDS = {f.name for f in dataclasses.fields(MatchParams)}
_VAR_FIELDS = {f.name for f in dataclasses.fields(VariationalParams)}

# Presets in the spirit of DeepFlow's published settings; "fast" trades a few
# hundredths of a pixel for speed (coarser pyramid, fewer sweeps).
PRESETS: dict[str, dict[str, Any]] = {
    "default": {},
    "fast": {"eta": 0.8, "n_outer": 4, "n_sor": 15},
    "large-displacement": {"ngh_rad": 96.0, "max_patch": 64},
}


def _split(params: dict[str, Any]) -> tuple[MatchParams, VariationalParams]:
    unknown = set(params) - _MATCH_FIELDS - _VAR_FIELDS
    if unknown:
        raise ValueError(
            f"unknown parameter(s) {sorted(unknown)}; valid: {sorted(_MATCH_FIELDS | _VAR_FIELDS)}"
        )
    match = MatchParams(**{k: v for k, v in params.items() if k in _MATCH_FIELDS})
    var = VariationalParams(**{k: v for k, v in params.items() if k in _VAR_FIELDS})
    return match, var


def _resolve(preset: str, overrides: dict[str, Any]) -> dict[str, Any]:
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; available: {', '.join(PRESETS)}")
    merged = dict(PRESETS[preset])
    merged.update(overrides)
    return merged


@register("deepflow")
class DeepFlow(DenseMethod):
    """DeepFlow: DeepMatching matches blended into a variational energy.

    Parameters (keyword-only; defaults follow the papers, see
    :class:`flow.deepmatching.MatchParams` and
    :class:`flow.variational.VariationalParams`)
    ----------
    preset : {"default", "fast", "large-displacement"}
    downscale, ngh_rad, max_patch, ... : matching parameters
    alpha, beta, delta, gamma, kappa, sigma, eta, n_outer, n_sor, omega, ... :
        variational parameters; ``beta = 0`` switches the matching term (and
        the matching itself) off.
    """

    summary = "DeepMatching + DeepFlow variational refinement (clean-room, numba)"

    def __init__(self, *, preset: str = "default", **params: Any) -> None:
        merged = _resolve(preset, params)
        self._match, self._var = _split(merged)
        # Scratch reused from frame to frame: an instance serves one thread at a time.
        self._workspace = Workspace()
        super().__init__(
            preset=preset, **dataclasses.asdict(self._match), **dataclasses.asdict(self._var)
        )

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        check_pair(reference, current)
        if self._var.beta > 0:
            grid = deep_matching(reference, current, self._match)
            match_flow, match_weight = densify(grid, reference.shape, nearest=True)
            return refine(
                reference,
                current,
                self._var,
                match_flow=match_flow,
                match_weight=match_weight,
                workspace=self._workspace,
            )
        return refine(reference, current, self._var, workspace=self._workspace)


@register("deepmatching")
class DeepMatchingDense(DenseMethod):
    """DeepMatching alone, interpolated densely (ablation of the variational part).

    Parameters
    ----------
    interpolation : {"linear", "nearest"}
        Interpolation between atomic-patch centres.
    downscale, ngh_rad, max_patch, ... : see :class:`flow.deepmatching.MatchParams`.
    """

    summary = "DeepMatching quasi-dense matches interpolated to a dense field"

    def __init__(self, *, interpolation: str = "linear", **params: Any) -> None:
        if interpolation not in ("linear", "nearest"):
            raise ValueError(f"interpolation must be 'linear' or 'nearest', got {interpolation!r}")
        unknown = set(params) - _MATCH_FIELDS
        if unknown:
            raise ValueError(
                f"unknown parameter(s) {sorted(unknown)}; valid: {sorted(_MATCH_FIELDS)}"
            )
        self._match = MatchParams(**params)
        self._nearest = interpolation == "nearest"
        super().__init__(interpolation=interpolation, **dataclasses.asdict(self._match))

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        check_pair(reference, current)
        grid = deep_matching(reference, current, self._match)
        flow, _ = densify(grid, reference.shape, nearest=self._nearest)
        return flow
