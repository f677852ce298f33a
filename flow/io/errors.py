"""The error every reader and option check raises for bad user input (its own module, so that
the readers of :mod:`flow.io.source` and :mod:`flow.io.camfiles` share it without importing
each other)."""

from __future__ import annotations


class InputError(ValueError):
    """Bad user input; the message names the problem and what to do."""
