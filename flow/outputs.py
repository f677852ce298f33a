"""The one check every command makes before any work: its outputs can be written and none of
them is one of its inputs (refflow never writes over what it reads)."""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from flow.io.errors import InputError


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
        if resolved.is_dir():
            raise InputError(f"output {out} is an existing folder, not a file: choose another {option} "
                             "(a file name, in that folder or elsewhere)")
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


# A refflow sidecar is a few kB; a JSON this big is somebody else's (and is not read whole).
_SIDECAR_MAX_BYTES = 16 << 20


def check_sidecar(csv: Path, sidecar: Path, *, option: str = "--out") -> None:
    """Refuse to replace an existing ``sidecar`` that is not refflow's sidecar of ``csv``: a
    JSON of the user's (refflow never replaces a file it did not write), or the sidecar of
    another output that shares it (``--out a`` and ``--out a.csv`` both describe themselves
    in ``a.json``). An earlier run's sidecar of the same CSV is replaced, as the CSV is."""
    if not sidecar.is_file():
        return
    data = None
    try:
        if sidecar.stat().st_size <= _SIDECAR_MAX_BYTES:
            data = json.loads(sidecar.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, ValueError, RecursionError):
        data = None
    ours = isinstance(data, dict) and str(data.get("tool", "")).startswith("refflow ") and "columns" in data
    if not ours:
        raise InputError(f"{sidecar} exists and is not a refflow sidecar: refflow never replaces a file it did not "
                         f"write; move it, or choose another {option}")
    described = data.get("csv")
    # (A sidecar written before sidecars named their CSV is taken for this CSV's.)
    if isinstance(described, str) and described != csv.name:
        raise InputError(f"{sidecar} is the sidecar of {csv.with_name(described)}, not of {csv}: outputs whose "
                         f"names differ only in their extension share one sidecar; choose another {option}")


# What each figure writer can write (matplotlib's figures; OpenCV's images).
PLOT_SUFFIXES = (".png", ".pdf", ".svg")
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff")


def check_suffix(path: Path, suffixes: tuple[str, ...], *, option: str = "--out") -> None:
    """Refuse an output whose name does not say one of the formats the writer can write
    (``myplot``, ``plot.txt``): the format is taken from the suffix."""
    if path.suffix.lower() not in suffixes:
        said = f"ends in {path.suffix!r}" if path.suffix else "has no extension"
        raise InputError(f"{option} {path} {said}: the format is taken from the name; "
                         f"name it {', '.join(suffixes[:-1])} or {suffixes[-1]}")


@contextmanager
def writing(path: Path) -> Iterator[None]:
    """Name ``path`` in an ``OSError`` raised while it is written: a full disk names no file,
    and a temporary's name would mean nothing to the user."""
    try:
        yield
    except OSError as err:
        if err.filename is not None and Path(err.filename) == path:
            raise
        raise OSError(err.errno, err.strerror or str(err), str(path)) from err


def _lock_path(path: Path) -> Path:
    return path.parent / f".{path.name}.refflow-lock"


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # a process of another user
    return True


@contextmanager
def claimed(outputs: list[Path], *, option: str = "--out") -> Iterator[list[Path]]:
    """Hold ``outputs`` for this run: a second run writing the same file while this one
    measures is refused (its CSV and sidecar would interleave with ours), with the first's
    process number. Yields the outputs that exist already (a re-run replaces them). The claim
    is a hidden lock file beside each output, removed when the run ends; one left by a run
    that was killed outright (its process gone) is taken over."""
    taken: list[Path] = []
    try:
        for out in outputs:
            lock = _lock_path(out)
            if not lock.parent.is_dir():
                continue  # the folder does not exist yet (or is no folder): nothing to race for
            for _ in range(2):
                try:
                    fd = os.open(lock, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
                except FileExistsError:
                    try:
                        holder = int(lock.read_text().strip() or 0)
                    except (OSError, ValueError):
                        holder = 0
                    if holder and holder != os.getpid() and _running(holder):
                        raise InputError(f"another refflow run (process {holder}) is writing {out}: wait for "
                                         f"it to end, or choose another {option}") from None
                    lock.unlink(missing_ok=True)  # left by a run that no longer exists
                    continue
                except OSError:
                    break  # a folder we cannot write: the output check says so
                with os.fdopen(fd, "w") as handle:
                    handle.write(str(os.getpid()))
                taken.append(lock)
                break
        yield [out for out in outputs if out.exists()]
    finally:
        for lock in taken:
            lock.unlink(missing_ok=True)
