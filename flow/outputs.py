"""The one check every command makes before any work: its outputs can be written and none of
them is one of its inputs (refflow never writes over what it reads)."""

from __future__ import annotations

import os
from pathlib import Path

from flow.errors import InputError


def check_outputs(outputs: list[Path], inputs: list[tuple[str, Path]], *, option: str = "--out") -> None:
    """Refuse, naming the problem, outputs that share a name, that are one of ``inputs``
    (``(what, path)`` pairs: a CSV, a video, a mask, ...), that lie inside an input folder,
    or whose folder cannot be made or written."""
    if len({path.resolve() for path in outputs}) != len(outputs):
        raise InputError(f"two outputs share a name ({', '.join(map(str, outputs))}): give each its own file")
    taken = {path.resolve(): what for what, path in inputs}
    folders = {path: what for path, what in taken.items() if path.is_dir()}
    for out in outputs:
        resolved = out.resolve()
        if resolved in taken:
            raise InputError(f"output {out} is the run's input ({taken[resolved]}): refflow never writes "
                             f"over an input; choose another {option}")
        if resolved.parent in folders:
            raise InputError(f"output {out} is inside {folders[resolved.parent]} (a folder of input "
                             f"images): refflow never writes among its inputs; choose another {option}")
        parent = resolved.parent
        while not parent.exists():
            parent = parent.parent
        if not parent.is_dir():
            raise InputError(f"output {out}: {parent} is a file, not a folder: choose another {option}")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise InputError(f"output {out}: folder {parent} is not writable: choose another {option}")
