"""Registry of displacement-measurement methods (after ptlflow's ``register_model``/``get_model``).

The methods' interface is in :mod:`flow.methods.base`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any


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
