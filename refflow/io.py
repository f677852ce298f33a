"""Atomic outputs and JSON sidecars shared by every stage."""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import platform
import tempfile
from collections.abc import Iterator, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

_VERSIONED = ("refflow", "numpy", "scipy", "opencv-contrib-python-headless", "mujoco",
              "pyrender", "trimesh", "imageio-ffmpeg", "numba")


def _temporary_beside(final: Path) -> Path:
    final.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".part{final.suffix}",
                                    dir=final.parent)
    os.close(fd)
    return Path(tmp_name)


def _publish(tmp: Path, final: Path) -> None:
    # mkstemp creates 0600; give the result the permissions of an ordinary file.
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(tmp, 0o666 & ~umask)
    os.replace(tmp, final)


@contextlib.contextmanager
def atomic_paths(*paths: str | os.PathLike[str]) -> Iterator[list[Path]]:
    """Yield temporary paths beside ``paths``; rename them all onto ``paths`` on success.

    The outputs of one run (a CSV, its sidecar, an ``.npz``) belong together:
    every file is written to its temporary first, and only when the ``with``
    block has finished without an exception are they renamed, one after the
    other, in the order given (put the file other tools look for first, e.g.
    the CSV, last). On any exception (Ctrl-C included) every temporary is
    removed (and a rename interrupted half-way takes back the files already
    renamed), so a failed run never leaves a CSV without its sidecar. The temporary names keep the suffix, so writers that
    infer the format from it (``np.savez``, ffmpeg, ``cv2.imwrite``) still work.
    """
    finals = [Path(p) for p in paths]
    if len(set(finals)) != len(finals):
        raise ValueError(f"atomic_paths got the same path twice: {[str(p) for p in finals]}")
    temporaries: list[Path] = []
    published: list[Path] = []
    # The file being renamed and its temporary's (device, inode).
    renaming: tuple[Path, tuple[int, int]] | None = None
    try:
        for final in finals:
            temporaries.append(_temporary_beside(final))
        yield list(temporaries)
        for tmp, final in zip(temporaries, finals, strict=True):
            found = os.lstat(tmp)
            renaming = (final, (found.st_dev, found.st_ino))
            _publish(tmp, final)
            published.append(final)
            renaming = None
    except BaseException as err:
        # Interrupted between two renames: take back the ones already made, so the set
        # stays all-or-nothing (their previous versions were replaced already), the one whose
        # rename had just happened when the interruption came included: the file is the
        # temporary itself (device and inode, checked while the temporary's inode is still
        # held); an earlier version of the file still there is left alone.
        if renaming is not None and renaming[0] not in published:
            try:
                found = os.lstat(renaming[0])
                if (found.st_dev, found.st_ino) == renaming[1]:
                    published.append(renaming[0])
            except OSError:
                pass
        for tmp in temporaries:
            tmp.unlink(missing_ok=True)
        for final in published:
            final.unlink(missing_ok=True)
        # A temporary's name means nothing to the user: name the file it stood for.
        names = {str(tmp): final for tmp, final in zip(temporaries, finals, strict=False)}
        if isinstance(err, OSError) and str(err.filename) in names:
            raise OSError(err.errno, err.strerror or str(err), str(names[str(err.filename)])) from err
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` on success.

    On any exception (Ctrl-C included) the temporary file is removed, so a
    failed run never leaves a half-written output under the final name.
    One-file form of :func:`atomic_paths`.
    """
    with atomic_paths(path) as (tmp,):
        yield tmp


def _jsonable(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {str(k): _jsonable(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.ndarray):
        return _jsonable(value.tolist())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    return value


def finite_or_none(value: float | None) -> float | None:
    """``value``, or None where it is missing, NaN or infinite: what a JSON writer stores for an
    unknown number (JSON has no NaN; :func:`json_text` refuses one)."""
    return value if value is not None and math.isfinite(value) else None


def json_text(data: Mapping[str, Any]) -> str:
    """``data`` as indented, key-sorted JSON text (NumPy values and paths converted).

    Raises ``ValueError`` for NaN or infinity: JSON has no such numbers, so
    writers must store ``None`` where a value is unknown.
    """
    return json.dumps(_jsonable(data), indent=2, sort_keys=True, allow_nan=False) + "\n"


def write_json(path: str | os.PathLike[str], data: Mapping[str, Any]) -> None:
    """Write ``data`` as indented, key-sorted JSON, atomically."""
    text = json_text(data)  # serialise first: a bad value must not even create the temporary
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def config_hash(config: Mapping[str, Any]) -> str:
    """Stable short hash of a config dict (key order does not matter)."""
    text = json.dumps(_jsonable(config), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def versions() -> dict[str, str]:
    """Versions of Python and the packages that shape the numbers."""
    found = {"python": platform.python_version()}
    for name in _VERSIONED:
        with contextlib.suppress(metadata.PackageNotFoundError):
            found[name] = metadata.version(name)
    return found


# Subpackages no workflow stage runs: editing them must not re-run the workbench
# (``flow.gui``, the browser page, runs the tool but is no part of it).
NOT_RUN_BY_THE_WORKFLOW = {"flow": ("gui",)}


def source_digest(root: str | Path, package: str) -> str:
    """Short hash of the Python sources of ``package`` under ``root`` and of ``refflow`` (the
    plumbing every stage shares): file names and bytes, in sorted order (the subpackages of
    :data:`NOT_RUN_BY_THE_WORKFLOW` left out)."""
    root = Path(root)
    digest = hashlib.sha256()
    for name in (package, "refflow"):
        skipped = NOT_RUN_BY_THE_WORKFLOW.get(name, ())
        for path in sorted((root / name).rglob("*.py")):
            if path.relative_to(root / name).parts[0] in skipped:
                continue
            digest.update(path.relative_to(root).as_posix().encode())
            digest.update(path.read_bytes())
    return digest.hexdigest()[:16]
