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

import cv2
import numpy as np

from flow.deepmatching import MatchParams, deep_matching, densify
from flow.member import MemberEdges
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


# The edge refinement is kept when the POIs' mean photometric mismatch under it is at most
# this factor of the dense flow's plus MATCH_SLACK grey levels (sensor noise moves both alike).
MATCH_TOLERANCE = 1.1
MATCH_SLACK = 0.5


def _mismatch(reference: np.ndarray, current: np.ndarray, cols: np.ndarray, rows: np.ndarray,
              u: np.ndarray, v: np.ndarray) -> float:
    """Mean |current(x + d) - reference(x)| over the points (bilinear, grey levels)."""
    map_x = (cols + u).astype(np.float32).reshape(1, -1)
    map_y = (rows + v).astype(np.float32).reshape(1, -1)
    warped = cv2.remap(current.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR,
                       borderMode=cv2.BORDER_REPLICATE)[0]
    return float(np.mean(np.abs(warped - reference[rows, cols].astype(np.float32))))


@register("deepflow")
class DeepFlow(DenseMethod):
    """DeepFlow: DeepMatching matches blended into a variational energy, then the structure's
    motion refined from its edges.

    The dense flow (DeepMatching + DeepFlow) covers the whole frame. Where the user's POI
    mask marks a member with edges, :mod:`flow.member` measures the outline's sub-pixel
    motion against the background and fits a smooth motion field to it; the POIs take
    that field's values (the dense flow is the starting guess, and keeps the directions
    the outline does not constrain). A member without usable edges keeps the dense flow.

    Parameters (keyword-only; defaults follow the papers, see
    :class:`flow.deepmatching.MatchParams` and
    :class:`flow.variational.VariationalParams`)
    ----------
    preset : {"default", "fast", "large-displacement"}
    member : bool
        Refine the POIs from the member's edges (default True).
    downscale, ngh_rad, max_patch, ... : matching parameters
    alpha, beta, delta, gamma, kappa, sigma, eta, n_outer, n_sor, omega, ... :
        variational parameters; ``beta = 0`` switches the matching term (and
        the matching itself) off.
    """

    summary = ("DeepMatching + DeepFlow (clean-room, numba), POIs refined from the "
               "structure's edges (default)")
    member_default = True

    def __init__(self, *, preset: str = "default", member: bool | None = None, **params: Any) -> None:
        merged = _resolve(preset, params)
        self._match, self._var = _split(merged)
        self._member_on = self.member_default if member is None else bool(member)
        if not isinstance(self._member_on, bool):
            raise ValueError(f"member must be true or false, got {member!r}")
        # Scratch reused from frame to frame: an instance serves one thread at a time.
        self._workspace = Workspace()
        self._member: MemberEdges | None = None
        super().__init__(
            preset=preset, member=self._member_on, **dataclasses.asdict(self._match),
            **dataclasses.asdict(self._var)
        )

    def bind(self, reference: np.ndarray, mask: np.ndarray) -> None:
        self._member = None
        if not self._member_on:
            return
        mask = np.asarray(mask, bool)
        if mask.shape != reference.shape or mask.sum() < 3:
            return
        self._member = MemberEdges.from_reference(reference, mask)
        self._poi_rows, self._poi_cols = np.nonzero(mask)
        self._ref_level = float(np.median(reference[mask])) or 1.0
        # Where the dense flow is read for each outline: its member-side pixel.
        m = self._member
        height, width = reference.shape
        inward_x = np.where(m.vertical, m.px, m.px - 0.5 * m.side)
        inward_y = np.where(m.vertical, m.py - 0.5 * m.side, m.py)
        self._prior_cols = np.clip(np.rint(inward_x).astype(np.intp), 0, width - 1)
        self._prior_rows = np.clip(np.rint(inward_y).astype(np.intp), 0, height - 1)

    def _dense(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
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

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        check_pair(reference, current)
        flow = self._dense(reference, current)
        self.last_sigma_px = None
        member = self._member
        if member is None or member.shape != reference.shape:
            return flow
        prior = flow[self._prior_rows, self._prior_cols].astype(np.float64)
        gain = float(np.median(current[self._poi_rows, self._poi_cols])) / self._ref_level
        fit = member.fit(current, prior, gain=gain if np.isfinite(gain) and gain > 0 else None)
        if not fit.ok:
            return flow
        u, v = member.displacement(fit)
        # The edges must not make the POIs' own match worse than the dense flow's: on a
        # textured member (or outlines that are not the member's) the dense flow is right.
        dense_u = flow[self._poi_rows, self._poi_cols, 0]
        dense_v = flow[self._poi_rows, self._poi_cols, 1]
        if (_mismatch(reference, current, self._poi_cols, self._poi_rows, u, v)
                > MATCH_TOLERANCE * _mismatch(reference, current, self._poi_cols, self._poi_rows,
                                              dense_u, dense_v) + MATCH_SLACK):
            return flow
        flow[self._poi_rows, self._poi_cols, 0] = u
        flow[self._poi_rows, self._poi_cols, 1] = v
        self.last_sigma_px = member.mean_sigma(fit)
        return flow


@register("deepflow-dense")
class DeepFlowDense(DeepFlow):
    """``deepflow`` without the edge refinement: the dense DeepMatching + DeepFlow field at the
    POIs (the paper's method as published; an ablation of the default)."""

    summary = "DeepMatching + DeepFlow dense field at the POIs, no edge refinement (the paper's method)"
    member_default = False


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
