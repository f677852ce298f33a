"""What every displacement-measurement method is: the base classes, and ``@register`` to declare one.

Every tracker is an interchangeable part behind one interface (after OpenCV's
``DenseOpticalFlow.calc`` and ptlflow's ``BaseModel``):

* a *dense* method maps ``(reference, current)`` grey images to a flow field
  ``(H, W, 2)`` float32 holding ``(dx, dy)`` in pixels such that
  ``reference[y, x]`` is seen at ``current[y + dy, x + dx]``;
* a *sparse* method follows its own features through the sequence.

The reference-frame driver, POI sampling, filtering (paper eq. 10-12) and
averaging are shared steps outside the methods. A method module imports this module
(the base classes and ``@register``) and nothing else of the methods' plumbing;
:mod:`flow.methods.registry` loads the methods and answers for them.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from flow.measure.window import bounding_box, box_window
from flow.methods.params import Param, check_params


class Method:
    """What every registered method shares: its name, summary, kind and parameters.

    Subclasses set ``summary`` (one line for ``refflow methods``); the registry
    sets ``name``. Parameters are keyword-only constructor arguments with the
    published defaults, each declared in ``parameters`` with its type, range and meaning
    (``refflow methods --params NAME`` lists them) and checked here, before any frame;
    :meth:`params` reports them.
    """

    kind = ""
    name: str = ""
    summary: str = ""
    parameters: tuple[Param, ...] = ()
    # False for methods built on OpenCV functions that take 8-bit images only: they see
    # 10-16-bit data rounded to 8 bits (``flow.io.frames.as_uint8``).
    full_depth = True

    def __init__(self, **params: Any) -> None:
        check_params(type(self).parameters, params)
        self._params = dict(params)

    def params(self) -> dict[str, Any]:
        """Parameters of this instance, for the JSON sidecar."""
        return dict(self._params)


CROP = Param("crop", "bool", True, "solve only around the pixels read (their bounding box plus a margin)")


# A dense method solves the flow on the pixels the driver reads (POIs, background points) plus
# this margin: room for the pyramid's coarse levels and the smoothing to settle before the POIs
# (and for a matching's search, which may ask for more; see :meth:`DenseMethod.window_margin`).
CROP_MARGIN_PX = 64


class Stopped(Exception):
    """A frame abandoned because the run is stopping (Ctrl-C, SIGTERM): raised in a job's thread
    by :meth:`DenseMethod.check_stop`, while the driver unwinds; nobody reads its result."""


class DenseMethod(Method):
    """Base class of dense reference-frame methods: implement :meth:`_solve`.

    A method may also use what the user says about the structure: the driver calls
    :meth:`bind` once with the reference frame and the POI mask before the frames, and
    after each :meth:`calc` reads :attr:`last_sigmas_px`, the method's own standard
    uncertainty ``(sigma_x, sigma_y)`` of the mean displacement over each region's POIs, by
    the region's label in the mask (1 for a bool mask); a region it lacks (or None): the
    driver estimates one. The labels in :attr:`last_sigmas_hold_reference` are those whose sigma
    already holds the reference frame's own error (the quality step adds it to the others':
    :func:`flow.measure.quality.with_reference_term`). A method that measures pixels on their own also leaves, where the
    driver sets :attr:`want_field_sigma` (a run writing a field file), :attr:`last_field_sigma`:
    a list of ``(rows, cols, sigma_u, sigma_v)``, pixels of the flow and their standard
    uncertainty (None: none in this frame).

    Parameters
    ----------
    crop : bool
        After :meth:`bind`, solve only the window around the pixels the driver reads (their
        bounding box plus :meth:`window_margin`; default True): a small member in a 4K
        frame is not solved over the whole frame. The flow outside it is NaN. Without
        :meth:`bind`, or for frames of another size, the whole frame is solved.
    """

    kind = "dense"
    parameters: tuple[Param, ...] = (CROP,)
    last_sigmas_px: dict[int, tuple[float, float]] | None = None
    last_sigmas_hold_reference: set[int] | None = None
    last_field_sigma: list[tuple[np.ndarray, ...]] | None = None
    want_field_sigma: bool = False
    # Set by the driver (one event for all its jobs): set when the run is stopping. A method
    # whose frame takes long calls :meth:`check_stop` between its stages, so that Ctrl-C does
    # not wait for the frames the jobs are measuring.
    stop: threading.Event | None = None

    def __init__(self, *, crop: bool = True, **params: Any) -> None:
        if not isinstance(crop, bool):
            raise ValueError(f"crop must be true or false, got {crop!r}")
        super().__init__(crop=crop, **params)
        self._crop_on = crop
        self._window: tuple[slice, slice] | None = None
        self._needed_box: tuple[int, int, int, int] | None = None
        self._bound_shape: tuple[int, ...] | None = None

    def bind(self, reference: np.ndarray, mask: np.ndarray, *, read: np.ndarray | None = None) -> None:
        """Prepare for frames compared with ``reference``; ``mask`` (same shape) marks the
        POIs, the structure's pixels (bool; or int labels 1..N of regions, 0 elsewhere);
        ``read`` (bool, same shape, optional) the other pixels whose flow the driver reads
        (static background points). The base class cuts out the window it solves (see
        ``crop``); subclasses that use more call it first."""
        self._window = None
        self._needed_box = None
        self._bound_shape = reference.shape
        mask = np.asarray(mask, bool)
        if not self._crop_on or mask.shape != reference.shape:
            return
        self._needed_box = bounding_box(mask if read is None else mask | np.asarray(read, bool))
        margin = self.window_margin(reference.shape)
        if margin is not None:
            self._window = box_window(reference.shape, self._needed_box, margin)

    def check_stop(self) -> None:
        """Raise :class:`Stopped` if the run is stopping (see :attr:`stop`)."""
        if self.stop is not None and self.stop.is_set():
            raise Stopped("the run is stopping")

    def window_with(self, margin: int | None) -> tuple[slice, slice] | None:
        """The window around the pixels read with ``margin`` px of context (None: the whole
        frame), for a method whose context changes from frame to frame (after :meth:`bind`)."""
        if margin is None or self._bound_shape is None:
            return None
        return box_window(self._bound_shape[:2], self._needed_box, margin)

    def window_margin(self, shape: tuple[int, ...]) -> int | None:
        """Pixels of context the method needs around the pixels it is asked for, in a frame
        of ``shape``; None: it must see the whole frame."""
        return CROP_MARGIN_PX

    def max_window_margin(self, shape: tuple[int, ...]) -> int | None:
        """The widest context the method may take around the pixels read in any frame of
        ``shape`` (None: the whole frame). The driver holds and hands over frames cut to the
        POIs' box plus this much, so a small member in a large frame never costs a frame."""
        return self.window_margin(shape) if self._crop_on else None

    def calc(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Flow from ``reference`` to ``current``.

        Parameters
        ----------
        reference, current : ndarray, shape (H, W), uint8 or float32
            Grey images of equal shape.

        Returns
        -------
        ndarray, shape (H, W, 2), float32
            ``flow[..., 0]`` = dx, ``flow[..., 1]`` = dy in pixels (NaN outside the window
            solved, see ``crop``).
        """
        check_pair(reference, current)
        return self._dense(reference, current)

    def _dense(self, reference: np.ndarray, current: np.ndarray) -> np.ndarray:
        return self._dense_in(reference, current, self._window)

    def _dense_in(self, reference: np.ndarray, current: np.ndarray,
                  window: tuple[slice, slice] | None) -> np.ndarray:
        """The flow of the pair solved in ``window`` (None: the whole frame), NaN outside it."""
        if window is None or reference.shape != self._bound_shape:
            return self._solve(reference, current, whole_shape=reference.shape)
        flow = np.full(reference.shape + (2,), np.nan, np.float32)
        # (Contiguous copies: OpenCV's flow objects refuse strided views.)
        flow[window] = self._solve(np.ascontiguousarray(reference[window]),
                                   np.ascontiguousarray(current[window]), whole_shape=reference.shape)
        return flow

    def _solve(self, reference: np.ndarray, current: np.ndarray, *,
               whole_shape: tuple[int, ...]) -> np.ndarray:
        """The flow field of a checked pair, which may be a window cut out of frames of
        ``whole_shape`` (a method whose reach scales with the frame uses that)."""
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


class SparseMethod(Method):
    """Base class of sparse methods that follow their own features: implement
    :meth:`start` and :meth:`step`.

    The driver calls :meth:`start` once with the reference frame, then
    :meth:`step` with every frame in order (frame 0 included). ``step``
    returns the displacement of every feature relative to the reference,
    ``(N, 2)`` float32, NaN where a feature is lost.
    """

    kind = "sparse"

    def start(self, reference: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
        """Find the features in ``reference`` (``mask``: the POIs, bool, if the method uses
        them) and return their positions ``(N, 2)`` float32."""
        raise NotImplementedError

    def step(self, current: np.ndarray) -> np.ndarray:
        """Displacement ``(N, 2)`` float32 of every feature from the reference to ``current``."""
        raise NotImplementedError


# Declaring a method. The table lives here, next to the base classes, so that a method module
# imports this module only: flow.methods.registry loads the method modules and reads the table, and
# nothing imports the registry back.

@dataclass(frozen=True)
class _Entry:
    factory: Callable[..., Any]
    kind: str
    summary: str


_REGISTRY: dict[str, _Entry] = {}
_UNAVAILABLE: dict[str, str] = {}


def register(name: str) -> Callable[[type], type]:
    """Class decorator adding a method to the registry under ``name``."""

    def decorate(cls: type) -> type:
        if name in _REGISTRY:
            raise ValueError(f"method {name!r} is registered twice")
        cls.name = name
        _REGISTRY[name] = _Entry(cls, getattr(cls, "kind", "dense"), getattr(cls, "summary", ""))
        return cls

    return decorate


def register_unavailable(name: str, reason: str) -> None:
    """Record that the method ``name`` cannot run here and why (a dependency is missing), for
    :func:`flow.methods.registry.unavailable`."""
    _UNAVAILABLE[name] = reason
