"""Type checks of a method's numeric parameters, at construction (not at the first frame).

A ``--param alpha=abc`` from the command line arrives as a string; a frozen dataclass of
parameters calls :func:`check_fields` in its ``__post_init__`` so that the bad value is
named at once, as a ``ValueError`` the CLI turns into its one-line message.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _check(name: str, kind: str, value: Any) -> None:
    optional = kind.replace(" ", "").endswith("|None")
    kind = kind.replace(" ", "").removesuffix("|None")
    if value is None and optional:
        return
    if kind == "bool":
        ok = isinstance(value, bool)
        want = "true or false"
    elif kind == "int":
        ok = _is_int(value)
        want = "an integer"
    elif kind == "float":
        ok = (_is_int(value) or isinstance(value, float)) and math.isfinite(value)
        want = "a finite number"
    else:
        return
    if not ok:
        none = " (or none)" if optional else ""
        raise ValueError(f"parameter {name} must be {want}{none}, got {value!r}")


def check_fields(params: Any) -> None:
    """Raise ``ValueError`` naming the first field of the dataclass ``params`` whose value
    does not have the field's declared type (bool, int, float, optionally ``| None``)."""
    for field in dataclasses.fields(params):
        _check(field.name, str(field.type), getattr(params, field.name))
