"""Registry of displacement-measurement methods (after ptlflow's ``register_model``/``get_model``).

A method module declares its methods with ``@register(name)`` from :mod:`flow.methods.base`
(the base classes' module); this module loads the built-in method modules on first use and
answers for all of them: :func:`available`, :func:`get_method`, and :func:`unavailable` for
those a missing dependency keeps out. Imports go one way: registry -> methods -> base and
registry -> base; nothing imports the registry back, so no import order can meet a
half-initialised module.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

from flow.methods import base
from flow.methods.base import register, register_unavailable

__all__ = ["available", "describe", "get_method", "kinds", "parameters", "register", "register_unavailable",
           "unavailable"]

# The built-in method modules, loaded in this order on first use (a command that asks for no
# method does not import them).
_BUILTIN_MODULES = ("flow.methods.klt", "flow.methods.opencv_dense")
# Built-in modules whose import may fail where a dependency is missing, with the methods they
# hold: those are then unavailable, with the import error as the reason.
_OPTIONAL_MODULES = {"flow.methods.deepflow.method": ("deepflow", "deepflow-dense", "deepmatching")}


@functools.cache
def _load_builtin_methods() -> None:
    for module in _BUILTIN_MODULES:
        importlib.import_module(module)
    for module, names in _OPTIONAL_MODULES.items():
        try:
            importlib.import_module(module)
        except ImportError as err:
            for name in names:
                register_unavailable(name, str(err))


def available() -> list[str]:
    """Names of all registered methods, sorted."""
    _load_builtin_methods()
    return sorted(base._REGISTRY)


def unavailable() -> dict[str, str]:
    """``{name: why it cannot run here}`` of the methods a missing dependency keeps out (an
    OpenCV build without contrib's ``optflow``, say), in the order they were found."""
    _load_builtin_methods()
    return dict(base._UNAVAILABLE)


def describe() -> dict[str, str]:
    """``{name: one-line summary}`` of all registered methods."""
    _load_builtin_methods()
    return {name: base._REGISTRY[name].summary for name in sorted(base._REGISTRY)}


def kinds() -> dict[str, str]:
    """``{name: kind}`` of all registered methods: ``"dense"`` (a flow field against the
    reference frame, frames independent) or ``"sparse"`` (features followed frame to frame)."""
    _load_builtin_methods()
    return {name: base._REGISTRY[name].kind for name in sorted(base._REGISTRY)}


def _entry(name: str) -> Any:
    _load_builtin_methods()
    try:
        return base._REGISTRY[name]
    except KeyError:
        why = base._UNAVAILABLE.get(name)
        if why:
            raise ValueError(f"method {name!r} is not available here: {why}") from None
        raise ValueError(
            f"unknown method {name!r}; available: {', '.join(sorted(base._REGISTRY))}"
        ) from None


def parameters(name: str) -> tuple[Any, ...]:
    """The keyword parameters of the method ``name``, each a :class:`flow.methods.params.Param` (type,
    default, range, meaning), in the order the method declares them."""
    return tuple(getattr(_entry(name).factory, "parameters", ()))


def get_method(name: str, **params: Any) -> Any:
    """Instantiate the method registered as ``name`` with keyword parameters (each checked
    against its declared range before the method is built)."""
    entry = _entry(name)
    declared = [param.name for param in getattr(entry.factory, "parameters", ())]
    unknown = sorted(set(params) - set(declared))
    if declared and unknown:
        raise ValueError(f"unknown parameter(s) {', '.join(unknown)}; {name} takes {', '.join(declared)}")
    return entry.factory(**params)
