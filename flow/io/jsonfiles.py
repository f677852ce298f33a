"""Reading the JSON files a user hands the tool (scale, calibration, video origin, project):
every failure becomes one line naming the file and what to do."""

from __future__ import annotations

import json
import math
import reprlib
from pathlib import Path
from typing import Any

from flow.io.errors import InputError


def load_json(path: str | Path, what: str) -> Any:
    """The JSON document in the file ``path``, which the messages call ``what`` (e.g. "scale
    file X"): a file that is missing, unreadable or not JSON raises :class:`InputError`.

    JSON as Python reads it (NaN and Infinity included); what its parser refuses besides
    syntax errors (a number of thousands of digits, nesting deeper than the recursion limit)
    is not JSON here either.
    """
    try:
        # utf-8-sig: Windows editors (Notepad) start a UTF-8 file with a byte-order mark
        text = Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(f"{what} does not exist: check the path") from None
    except UnicodeDecodeError:
        raise InputError(f"{what} is not readable JSON (not UTF-8 text): pass the JSON file") from None
    except OSError as err:
        raise InputError(f"{what} cannot be read ({err.strerror or err}): check the path and "
                         "permissions") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as err:
        detail = str(err)
    except RecursionError:
        detail = "nested too deeply"
    except ValueError:  # int() refuses a literal of more than sys.get_int_max_str_digits() digits
        detail = "a number with too many digits"
    raise InputError(f"{what} is not readable JSON ({detail}): fix or write the file again")


def json_number(value: Any) -> float | None:
    """A JSON number as a float (an integer too large for one: +-inf, which every finiteness
    check then refuses); None for anything else, booleans included (``true`` is no number)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        return None
    try:
        return float(value)
    except OverflowError:
        return math.inf if value > 0 else -math.inf


def shown(value: Any) -> str:
    """``repr`` of a value read from a user's file, shortened for a one-line message."""
    return reprlib.repr(value)
