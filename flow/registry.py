"""Registry of displacement-measurement methods.

Every tracker is an interchangeable part behind one interface (after OpenCV's
``DenseOpticalFlow.calc`` and ptlflow's ``register_model``/``get_model``):

* a *dense* method maps ``(reference, current)`` grey images to a flow field
  ``(H, W, 2)`` float32 holding ``(dx, dy)`` in pixels such that
  ``reference[y, x]`` is seen at ``current[y + dy, x + dx]``;
* a *sparse* method (KLT) follows its own features through the sequence.

The reference-frame driver, POI sampling, filtering (paper eq. 10-12) and
averaging are shared steps outside the methods.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np


class Method:
    """What every registered method shares: its name, summary, kind and parameters.

    Subclasses set ``summary`` (one line for ``refflow methods``); the registry
    sets ``name``. Parameters are keyword-only constructor arguments with the
    published defaults; :meth:`params` reports them.
    """

    kind = ""
    name: str = ""
    summary: str = ""

    def __init__(self, **params: Any) -> None:
        self._params = dict(params)

    def params(self) -> dict[str, Any]:
        """Parameters of this instance, for the JSON sidecar."""
        return dict(self._params)


class DenseMethod(Method):
    """Base class of dense reference-frame methods: implement :meth:`calc`.

    A method may also use what the user says about the structure: the driver calls
    :meth:`bind` once with the reference frame and the POI mask before the frames, and
    after each :meth:`calc` reads :attr:`last_sigma_px`, the method's own standard
    uncertainty of the mean displacement over the POIs (None: the driver estimates one).
    """

    kind = "dense"
    last_sigma_px: tuple[float, float] | None = None

    def bind(self, reference: np.ndarray, mask: np.ndarray, *, read: np.ndarray | None = None) -> None:
        """Prepare for frames compared with ``reference``; ``mask`` (bool, same shape) marks
        the POIs, the structure's pixels; ``read`` (bool, same shape, optional) the other
        pixels whose flow the driver reads (static background points). A method may leave
        the flow elsewhere unsolved (NaN). The default ignores all three."""

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Flow from ``reference`` to ``current``.

        Parameters
        ----------
        reference, current : ndarray, shape (H, W), uint8 or float32
            Grey images of equal shape.

        Returns
        -------
        ndarray, shape (H, W, 2), float32
            ``flow[..., 0]`` = dx, ``flow[..., 1]`` = dy in pixels.
        """
        raise NotImplementedError


def check_pair(reference: np.ndarray, current: np.ndarray) -> None:
    """Raise ``ValueError`` naming the problem if the pair cannot be compared."""
    for label, image in (("reference", reference), ("current", current)):
        if not isinstance(image, np.ndarray) or image.ndim != 2:
            shape = getattr(image, "shape", None)
            raise ValueError(f"{label} image must be a 2-D grey array, got shape {shape}")
        if image.dtype not in (np.uint8, np.float32):
            raise ValueError(f"{label} image must be uint8 or float32, got {image.dtype}")
    if reference.shape != current.shape:
        raise ValueError(
            f"reference is {reference.shape[1]}x{reference.shape[0]} but current is "
            f"{current.shape[1]}x{current.shape[0]}: frames must have equal size"
        )


@dataclass(frozen=True)
class _Entry:
    factory: Callable[..., Any]
    kind: str
    summary: str


_REGISTRY: dict[str, _Entry] = {}


def register(name: str) -> Callable[[type], type]:
    """Class decorator adding a method to the registry under ``name``."""

    def decorate(cls: type) -> type:
        if name in _REGISTRY:
            raise ValueError(f"method {name!r} is registered twice")
        cls.name = name
        _REGISTRY[name] = _Entry(cls, getattr(cls, "kind", "dense"), getattr(cls, "summary", ""))
        return cls

    return decorate


def _load_builtin_methods() -> None:
    # Importing the package registers every built-in method exactly once.
    import flow.methods  # noqa: F401


def available() -> list[str]:
    """Names of all registered methods, sorted."""
    _load_builtin_methods()
    return sorted(_REGISTRY)


def describe() -> dict[str, str]:
    """``{name: one-line summary}`` of all registered methods."""
    _load_builtin_methods()
    return {name: _REGISTRY[name].summary for name in sorted(_REGISTRY)}


def kinds() -> dict[str, str]:
    """``{name: kind}`` of all registered methods: ``"dense"`` (a flow field against the
    reference frame, frames independent) or ``"sparse"`` (features followed frame to frame)."""
    _load_builtin_methods()
    return {name: _REGISTRY[name].kind for name in sorted(_REGISTRY)}


def get_method(name: str, **params: Any) -> Any:
    """Instantiate the method registered as ``name`` with keyword parameters."""
    _load_builtin_methods()
    try:
        entry = _REGISTRY[name]
    except KeyError:
        raise ValueError(
            f"unknown method {name!r}; available: {', '.join(sorted(_REGISTRY))}"
        ) from None
    return entry.factory(**params)
