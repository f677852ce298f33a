"""A method's parameters: each declared with its type, default, range and meaning, and checked
at construction (not at the first frame).

A ``--param winsize=100000000`` from the command line would have OpenCV allocate gigabytes
and run for a quarter of an hour before anything is said; ``--param alpha=abc`` arrives as a
string. Every parameter of every registered method is therefore declared as a :class:`Param`
(a method class lists them in its ``parameters``; a frozen dataclass of parameters declares
them in its fields' metadata with :func:`bounds` and calls :func:`check_fields` in its
``__post_init__``), so that a bad value is named at once, with its range, as a ``ValueError``
the CLI turns into its one-line message. ``refflow methods --params NAME`` prints the same
table.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

_METADATA_KEY = "refflow_param"


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number_text(value: float) -> str:
    return f"{value:g}" if isinstance(value, float) else str(value)


@dataclass(frozen=True)
class Param:
    """One keyword parameter of a method.

    ``kind`` is ``"int"``, ``"float"``, ``"bool"`` or ``"choice"`` (one of ``choices``);
    ``optional``: None is accepted too (``none_means`` says what it does). A number lies in
    ``low`` .. ``high`` (either end excluded where ``low_open`` / ``high_open``).
    """

    name: str
    kind: str
    default: Any
    meaning: str
    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False
    choices: tuple[str, ...] = ()
    optional: bool = False
    none_means: str = ""

    def range_text(self) -> str:
        """The accepted values in words: ``3..101``, ``0 < x < 1``, ``one of a, b``, ``true or false``."""
        if self.kind == "bool":
            text = "true, false" if self.optional else "true or false"
        elif self.kind == "choice":
            text = "one of " + ", ".join(self.choices)
        elif self.low_open or self.high_open or self.low is None or self.high is None:
            low = "" if self.low is None else f"{_number_text(self.low)} {'<' if self.low_open else '<='} "
            high = "" if self.high is None else f" {'<' if self.high_open else '<='} {_number_text(self.high)}"
            text = f"{low}{self.name}{high}"
        else:
            text = f"{_number_text(self.low)}..{_number_text(self.high)}"
        if self.optional:
            text += " or none" + (f" ({self.none_means})" if self.none_means else "")
        return text

    def type_text(self) -> str:
        return ("text" if self.kind == "choice" else self.kind) + (" or none" if self.optional else "")

    def check(self, value: Any) -> None:
        """Raise ``ValueError`` naming the parameter, the value and the range where ``value``
        does not fit."""
        if value is None and self.optional:
            return
        if self.kind == "bool":
            ok, want = isinstance(value, bool), "true or false"
        elif self.kind == "int":
            ok, want = _is_int(value), "an integer"
        elif self.kind == "float":
            ok = (_is_int(value) or isinstance(value, float)) and math.isfinite(value)
            want = "a finite number"
        else:
            ok, want = isinstance(value, str) and value in self.choices, "one of " + ", ".join(self.choices)
        if not ok and self.kind in ("int", "float"):
            raise ValueError(f"parameter {self.name} must be {want}, got {value!r} (range {self.range_text()})")
        if not ok:
            none = " (or none)" if self.optional else ""
            raise ValueError(f"parameter {self.name} must be {want}{none}, got {value!r}")
        if self.kind in ("int", "float") and not self._inside(value):
            raise ValueError(f"parameter {self.name}={value!r} is outside its range {self.range_text()}")

    def _inside(self, value: float) -> bool:
        if self.low is not None and (value < self.low or (self.low_open and value == self.low)):
            return False
        return not (self.high is not None and (value > self.high or (self.high_open and value == self.high)))


def check_params(table: Iterable[Param], values: Mapping[str, Any]) -> None:
    """Check each of ``values`` that ``table`` declares (raise ``ValueError`` on the first bad one)."""
    declared = {param.name: param for param in table}
    for name, value in values.items():
        if name in declared:
            declared[name].check(value)


def with_defaults(table: tuple[Param, ...], **defaults: Any) -> tuple[Param, ...]:
    """``table`` with the defaults of some parameters changed (a method that derives from another)."""
    return tuple(dataclasses.replace(param, default=defaults[param.name]) if param.name in defaults else param
                 for param in table)


def bounds(low: float | None, high: float | None, meaning: str, *, low_open: bool = False,
           high_open: bool = False, none_means: str = "") -> dict[str, Any]:
    """The metadata of a dataclass field that is a method parameter: its range and meaning
    (``dataclasses.field(default=..., metadata=bounds(...))``; type and default come from the field)."""
    return {_METADATA_KEY: {"low": low, "high": high, "meaning": meaning, "low_open": low_open,
                            "high_open": high_open, "none_means": none_means}}


def flag(meaning: str) -> dict[str, Any]:
    """The metadata of a boolean dataclass field that is a method parameter."""
    return {_METADATA_KEY: {"meaning": meaning}}


def declared(cls: type) -> tuple[Param, ...]:
    """The parameters a frozen dataclass of parameters declares (every field is one)."""
    table = []
    for field in dataclasses.fields(cls):
        kind = str(field.type).replace(" ", "")
        optional = kind.endswith("|None")
        spec = dict(field.metadata.get(_METADATA_KEY) or {})
        if not spec:
            raise TypeError(f"{cls.__name__}.{field.name} declares no range (flow.methods.params.bounds)")
        table.append(Param(name=field.name, kind=kind.removesuffix("|None"), default=field.default,
                           optional=optional, **spec))
    return tuple(table)


def check_fields(params: Any) -> None:
    """Raise ``ValueError`` naming the first field of the dataclass ``params`` whose value
    does not have the field's declared type (bool, int, float, optionally ``| None``) or
    lies outside its declared range."""
    for param in declared(type(params)):
        param.check(getattr(params, param.name))
