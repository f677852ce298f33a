"""The one way this project's numeric CSV files are opened: a header line, then rows (blank
rows skipped), the columns a reader needs checked before any cell is parsed. Used by the track
CSV's reader (:mod:`refflow.trackcsv`) and analysis's readers of the stage files."""

from __future__ import annotations

import csv
from collections.abc import Callable, Sequence
from pathlib import Path


def read_rows(path: Path, required: Sequence[str], *, error: type[Exception] = ValueError,
              describe_missing: Callable[[list[str], list[str]], str] | None = None
              ) -> tuple[list[str], list[list[str]]]:
    """``(header, rows)`` of the CSV ``path`` (cells as text). Raises ``error`` naming the file
    when a ``required`` column is missing (``describe_missing(missing, header)`` words it) or
    there is no data row."""
    with path.open(newline="") as handle:
        reader = csv.reader(handle)
        header = [name.strip() for name in next(reader, [])]
        rows = [row for row in reader if any(cell.strip() for cell in row)]
    missing = [name for name in required if name not in header]
    if missing:
        found = ",".join(header) or "no header"
        text = (describe_missing(missing, header) if describe_missing is not None
                else f"missing column(s) {', '.join(missing)}; found {found}")
        raise error(f"{path}: {text}")
    if not rows:
        raise error(f"{path}: no data rows")
    return header, rows
