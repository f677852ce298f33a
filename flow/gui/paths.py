"""The one folder ``refflow gui`` writes in, and the check every path of a request goes through.

The page names files (a run's name, a file to download); each name is resolved (symbolic
links followed) and must land inside the output folder the user chose on the command line,
and never on an input (the video, its frames file, the calibration). Anything else is
refused with a one-line reason (:class:`PathRefused`, an HTTP 403 for the server).
"""

from __future__ import annotations

import os
from pathlib import Path

from flow.io.errors import InputError


class PathRefused(InputError):
    """A request named a path outside the output folder, or an input."""


class OutputFolder:
    """The folder ``root`` and the inputs no output may replace.

    ``inputs``: files the run reads (refused as outputs); a folder among them (an image
    sequence) refuses everything inside it, the output folder included.
    """

    def __init__(self, root: str | Path, inputs: list[str | Path] = ()) -> None:
        self.given = Path(root)
        root_path = self.given.resolve()
        self.inputs = [Path(p).resolve() for p in inputs if p]
        for path in self.inputs:
            if root_path == path or (path.is_dir() and root_path.is_relative_to(path)):
                raise InputError(f"output folder {str(self.given)!r} is inside the input {str(path)!r}: refflow "
                                 "never writes among its inputs; pass another --out-dir")
        existing = root_path
        while not existing.exists():
            existing = existing.parent
        if not existing.is_dir():
            raise InputError(f"output folder {str(self.given)!r}: {existing} is a file, not a folder: "
                             "pass another --out-dir")
        if not os.access(existing, os.W_OK | os.X_OK):
            raise InputError(f"output folder {str(self.given)!r}: {existing} is not writable: pass another --out-dir")
        root_path.mkdir(parents=True, exist_ok=True)
        self.root = root_path

    def path(self, name: object) -> Path:
        """The resolved path of ``name`` (relative to the folder, or absolute inside it);
        :class:`PathRefused` if it leaves the folder (``..``, an absolute path elsewhere, a
        symbolic link pointing out) or is one of the inputs."""
        if not isinstance(name, str) or not name.strip():
            raise PathRefused("no file name given: name a file inside the output folder")
        if any(ord(c) < 32 for c in name):
            raise PathRefused(f"file name {name!r} holds control characters: name a file inside the output folder")
        given = Path(name)
        if ".." in given.parts:
            raise PathRefused(f"{name!r} climbs out with '..': refflow gui reads and writes only inside "
                              f"the output folder {self.root}")
        resolved = (given if given.is_absolute() else self.root / given).resolve()
        if resolved == self.root or not resolved.is_relative_to(self.root):
            why = "is a symbolic link that points" if not given.is_absolute() else "lies"
            raise PathRefused(f"{name!r} {why} outside the output folder {self.root}: refflow gui reads "
                              "and writes only there")
        for path in self.inputs:
            if resolved == path or (path.is_dir() and resolved.is_relative_to(path)):
                raise PathRefused(f"{name!r} is the run's input {str(path)!r}: refflow never writes over an "
                                  "input; choose another name")
        return resolved

    def existing(self, name: object, suffixes: tuple[str, ...]) -> Path:
        """:meth:`path` of a file that exists and ends in one of ``suffixes`` (for reading)."""
        path = self.path(name)
        if path.suffix.lower() not in suffixes:
            raise PathRefused(f"{name!r} is not a file the page offers ({', '.join(suffixes)})")
        if not path.is_file():
            raise FileNotFoundError(f"{name!r} does not exist in the output folder {self.root}: run first")
        return path
