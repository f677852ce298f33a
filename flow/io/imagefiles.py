"""Image files checked before the first frame is measured, without decoding their pixels (PNG
checksums and end chunk, JPEG end marker and header, TIFF strips within the file), and read
with what the decoders print on stderr held back (libpng, libjpeg write there directly): the
complaint belongs in the one-line message, not beside it."""

from __future__ import annotations

import contextlib
import logging
import os
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from flow.io.errors import InputError

_STDERR_HOLD = threading.Lock()


@contextlib.contextmanager
def _held_back_stderr() -> Iterator[list[str]]:
    """Hold back what C libraries write on file descriptor 2 (libpng, libjpeg print there
    directly) while the block runs; the list yielded receives it as lines when the block ends.

    fd 2 is the process's: use it only for reads before any other thread runs (a progress
    bar's output would be held back too), never during tracking. Two holds at once (threads)
    take turns, so that each gives fd 2 back as it found it.
    """
    sys.stderr.flush()
    held: list[str] = []
    with _STDERR_HOLD, tempfile.TemporaryFile() as sink:
        saved = os.dup(2)
        os.dup2(sink.fileno(), 2)
        try:
            yield held
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            sink.seek(0)
            held.extend(sink.read().decode("utf-8", "replace").splitlines())


def _first_complaint(lines: list[str]) -> str:
    return next((line.strip() for line in lines if line.strip()), "")


def read_image(path: str | Path, flags: int) -> tuple[np.ndarray | None, str]:
    """``cv2.imread(path, flags)`` and the decoder's first complaint (``""`` when none).

    What the decoders print is held back, never shown: the image is None when it cannot be
    decoded, and its complaint (``libpng error: IHDR: CRC error``, ``Premature end of JPEG
    file``) then belongs in the caller's one-line message; about an image that decodes (a
    libpng warning on its colour profile, libjpeg's ``Corrupt JPEG data``), it belongs in the
    run's notes (printed, it would be a second line next to any later refusal). For the reads
    before the first frame only (see :func:`_held_back_stderr`).
    """
    with _held_back_stderr() as printed:
        image = cv2.imread(str(path), flags)
    return image, _first_complaint(printed)


def because(complaint: str) -> str:
    """A decoder's complaint as a parenthesis of a one-line message ("" when none)."""
    return f" ({complaint})" if complaint else ""


# A JPEG file's last marker (End Of Image); some cameras pad the file with zeros after it.
JPEG_END = b"\xff\xd9"
# A PNG file's last chunk, IEND: empty, so its length and checksum are always these.
PNG_END = b"\0\0\0\0IEND\xaeB`\x82"
# TIFF tags locating the image data: StripOffsets/StripByteCounts, TileOffsets/TileByteCounts.
TIFF_DATA_TAGS = ((273, 279), (324, 325))


def _image_structure(path: Path) -> tuple[tuple[int, int], str, list[tuple[object, object]]]:
    """``((width, height), format, [(offsets, byte counts)])`` of an image file as its header
    tells, without decoding its pixels (PNG chunks and checksums verified). Pillow's parsers
    raise what they will on a damaged file: callers catch it (see :func:`check_image_file`)."""
    from PIL import Image

    with Image.open(path) as image:
        size, kind = image.size, image.format or ""
        data = [(image.tag_v2.get(where), image.tag_v2.get(count))
                for where, count in TIFF_DATA_TAGS] if kind == "TIFF" else []
        image.verify()  # the file's structure (PNG: every chunk's checksum), not its pixels
    return size, kind, data


def _jpeg_header(data: bytes) -> bytes | None:
    """The bytes of a JPEG up to the end of its first start-of-scan (SOS) segment header, marker
    by marker (an EXIF thumbnail's own markers skipped with its segment); None where the markers
    do not chain (libjpeg may still skip the stray bytes: judged on the whole file then)."""
    at = 2  # after SOI
    while at + 4 <= len(data) and data[at] == 0xFF:
        marker = data[at + 1]
        if marker == 0xFF:  # fill byte
            at += 1
            continue
        end = at + 2 + int.from_bytes(data[at + 2:at + 4], "big")
        if marker == 0xDA:
            return data[:end] if end <= len(data) else None
        at = end
    return None


def _jpeg_problem(path: Path) -> str:
    """Why libjpeg cannot decode the JPEG ``path`` from its header ("" if it can).

    Whether libjpeg decodes a JPEG at all is decided, as a rule, by its header (markers, tables,
    frame and scan headers): damage in the compressed data after it costs pixels (libjpeg warns
    and decodes), unless it forms a marker. So libjpeg is given the header alone, closed by an
    end marker, at 1/8 scale: cheap (no pixel of the file is decoded), and what it refuses, a
    full read refuses too.
    """
    with path.open("rb") as handle:
        head = handle.read(1 << 16)  # the header, EXIF and its thumbnail included, as a rule
    header = _jpeg_header(head)
    if header is None and len(head) == 1 << 16:  # a longer header (large EXIF, ICC, XMP): read on
        header = _jpeg_header(path.read_bytes())
    data = header + JPEG_END if header is not None else path.read_bytes()
    with _held_back_stderr() as printed:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_REDUCED_GRAYSCALE_8)
    return "" if image is not None else f"damaged: {_first_complaint(printed) or 'libjpeg cannot read it'}"


def _structure_problem(path: Path, kind: str, data: list[tuple[object, object]]) -> str:
    """How the file ``path`` of Pillow ``kind`` is damaged or cut short, from its structure
    ("" if it is sound)."""
    length = path.stat().st_size
    with path.open("rb") as handle:
        handle.seek(max(length - 65536, 0))
        tail = handle.read()
    if kind in ("JPEG", "MPO"):
        if not tail.rstrip(b"\0").endswith(JPEG_END):
            return "truncated: the JPEG data has no end marker"
        return _jpeg_problem(path)
    if kind == "PNG" and PNG_END not in tail:  # Pillow's check stops short of IEND's checksum
        return "damaged or truncated: the PNG's end chunk (IEND) is missing or broken"
    for offsets, counts in data:
        if offsets is None:
            continue
        offsets = offsets if isinstance(offsets, tuple) else (offsets,)
        counts = (0,) * len(offsets) if counts is None else counts
        counts = counts if isinstance(counts, tuple) else (counts,)
        if not all(isinstance(v, int) for v in offsets + counts) or len(offsets) != len(counts):
            return "damaged: the TIFF's strip or tile table is broken"
        if any(start < 0 or start + size > length for start, size in zip(offsets, counts, strict=True)):
            return "truncated: its TIFF image data lies beyond the end of the file"
    return ""


@contextlib.contextmanager
def _pillow_quiet() -> Iterator[None]:
    """Pillow says nothing while the block runs: neither its warnings (``Corrupt EXIF data``)
    nor its log (``More samples per pixel than can be decoded``, which Python's logging prints
    on stderr when nothing is configured). Before the first frame only: both are global."""
    logger = logging.getLogger("PIL")
    level = logger.level
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        logger.setLevel(logging.CRITICAL + 1)
        try:
            yield
        finally:
            logger.setLevel(level)


def check_image_file(path: Path) -> tuple[int, int]:
    """``(width, height)`` of the image file ``path`` from its header, after checking its
    structure without decoding its pixels: an unreadable, damaged or truncated file (a PNG
    checksum error, a JPEG without its end marker, a TIFF whose strips lie beyond its end)
    raises :class:`InputError`, in one line. A file Pillow cannot identify (a format only
    OpenCV knows, or a damaged header) is decoded by OpenCV instead.
    """
    from PIL import UnidentifiedImageError

    with _pillow_quiet():
        try:
            size, kind, data = _image_structure(path)
        except UnidentifiedImageError:
            image, complaint = read_image(path, cv2.IMREAD_UNCHANGED)
            if image is not None:
                return image.shape[1], image.shape[0]
            problem = complaint or "not an image Pillow or OpenCV can read"
        # Pillow's parsers raise many kinds on a damaged file (SyntaxError, EOFError,
        # struct.error, DecompressionBombError, ...): each means the file cannot be measured.
        except Exception as err:
            problem = _first_complaint(str(err).splitlines()) or type(err).__name__
        else:
            problem = _structure_problem(path, kind, data)
    if problem:
        raise InputError(f"image {str(path)!r} cannot be read ({problem}): remove or replace it")
    return size


#: EXIF orientation tag (0x0112): how a viewer turns the stored pixels to show them (1: as
#: stored; 2-8: mirrored and/or turned). Cameras and phones store a portrait photo's pixels
#: landscape with 6 or 8.
EXIF_ORIENTATION = 0x0112
#: Orientations that swap the image's width and height.
SWAPPING_ORIENTATIONS = (5, 6, 7, 8)
#: Orientation -> the clockwise display rotation, degrees (the mirrored ones: none).
ORIENTATION_DEGREES = {3: 180, 6: 90, 8: 270}


def exif_orientation(path: Path) -> int:
    """The EXIF orientation of the image file ``path`` (1 where it has none or it cannot be
    read; only the header is read)."""
    from PIL import Image

    try:
        with _pillow_quiet(), Image.open(path) as image:
            tag = image.getexif().get(EXIF_ORIENTATION, 1)
    except Exception:  # noqa: BLE001 - Pillow raises many kinds on odd headers: no tag known
        return 1
    return tag if isinstance(tag, int) and 1 <= tag <= 8 else 1


def oriented(image: np.ndarray, orientation: int) -> np.ndarray:
    """``image`` (H x W or H x W x C, any dtype) turned as a viewer shows it under the EXIF
    ``orientation`` (as OpenCV's and Pillow's readers turn it)."""
    if orientation == 2:
        image = image[:, ::-1]
    elif orientation == 3:
        image = image[::-1, ::-1]
    elif orientation == 4:
        image = image[::-1]
    elif orientation == 5:
        image = image.swapaxes(0, 1)
    elif orientation == 6:
        image = image[::-1].swapaxes(0, 1)
    elif orientation == 7:
        image = image[::-1, ::-1].swapaxes(0, 1)
    elif orientation == 8:
        image = image[:, ::-1].swapaxes(0, 1)
    return np.ascontiguousarray(image)
