"""The TIFF-stack reader: one multi-page TIFF file, one frame per page (ImageJ, scientific
cameras and DIC tools save image sequences so).

OpenCV's video reader decodes such a file's first page only: a stack was measured as one
frame, and nothing said so. Pages are read one at a time in order with Pillow (whose next page
is found from the one before, where OpenCV walks the file's page list from its start for each
page read), so memory holds one page whatever the stack's length. Like a folder of images, a
stack carries no time stamps (``--fps``), its pages share one size and pixel type, and data
deeper than 8 bits is measured at full depth (:class:`flow.io.frames.ImageSequence`). Every
page's strips are checked to lie within the file before the first frame is measured.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from flow.io.errors import InputError
from flow.io.frames import ImageSequence, Roi
from flow.io.imagefiles import TIFF_DATA_TAGS

__all__ = ["TIFF_SUFFIXES", "TiffStackSource", "is_tiff_stack", "page_array"]

TIFF_SUFFIXES = (".tif", ".tiff")
# Pillow modes that numpy takes as they are (grey 8/16/32-bit, float, colour); the others
# (bilevel, palette, grey with alpha, CMYK...) are converted to one of these first.
_DIRECT_MODES = {"L", "I;16", "I;16B", "I;16L", "I", "F", "RGB", "RGBA"}


def tiff_pages(path: Path) -> tuple[int, str]:
    """The number of pages (image file directories) of the TIFF ``path``, counted by walking
    their chain, and what cuts it short ("" where nothing does): a chain that points past the
    file's end is a file cut short, where Pillow just finds fewer pages (with a warning)."""
    length = path.stat().st_size
    with path.open("rb") as handle:
        head = handle.read(16)
        order = {b"II": "<", b"MM": ">"}.get(head[:2])
        if order is None or len(head) < 8:
            return 0, "not a TIFF"
        big = int.from_bytes(head[2:4], "little" if order == "<" else "big") == 43
        word, count_size, entry = (8, 8, 20) if big else (4, 2, 12)
        unpack = "little" if order == "<" else "big"
        at = int.from_bytes(head[8:16] if big else head[4:8], unpack)
        pages, seen = 0, set()
        while at:
            if at in seen:
                return pages, f"its page list loops back at page {pages}"
            seen.add(at)
            if at + count_size > length:
                return pages, f"page {pages} lies past the file's end"
            handle.seek(at)
            entries = int.from_bytes(handle.read(count_size), unpack)
            end = at + count_size + entries * entry + word
            if end > length:
                return pages, f"page {pages} lies past the file's end"
            handle.seek(end - word)
            at = int.from_bytes(handle.read(word), unpack)
            pages += 1
    return pages, ""


def is_tiff_stack(path: Path) -> bool:
    """Whether ``path`` is a TIFF file of more than one page (a single page: an image, read as
    before by the video reader)."""
    if path.suffix.lower() not in TIFF_SUFFIXES:
        return False
    pages, problem = tiff_pages(path)
    return pages > 1 or (pages == 1 and "past the file's end" in problem)


def page_array(page) -> np.ndarray:
    """The pixels of the Pillow image ``page`` as OpenCV reads images: native byte order, colour
    in BGR(A) order."""
    if page.mode not in _DIRECT_MODES:
        page = page.convert("RGBA" if "A" in page.mode or "transparency" in page.info
                            else "L" if page.mode == "1" else "RGB")
    array = np.asarray(page)
    if not array.dtype.isnative:
        array = array.astype(array.dtype.newbyteorder("="))
    if array.ndim == 3:
        array = array[..., [2, 1, 0, 3][:array.shape[2]]]
    return np.ascontiguousarray(array)


class TiffStackSource(ImageSequence):
    """The pages of a multi-page TIFF file, one frame each.

    Parameters
    ----------
    path : Path
        The file (it exists: :func:`flow.io.source.open_source` checked).
    roi, fps, require_fps
        As for :class:`flow.io.folder.ImageFolderSource`.
    """

    def __init__(self, path: Path, *, roi: Roi | None = None, fps: float | None = None,
                 require_fps: bool = True) -> None:
        from PIL import Image

        super().__init__(path)
        if fps is None and require_fps:
            raise InputError(f"{str(path)!r} is a TIFF stack of images without timestamps: pass --fps (the camera "
                             "frame rate)")
        length = path.stat().st_size
        listed, problem = tiff_pages(path)
        if problem:
            raise InputError(f"{path.name}: {problem} ({listed} page(s) before it; cut short?): copy the stack "
                             "again, or save it anew")
        try:
            with Image.open(path) as stack:
                first = page_array(stack)
                self._compression = str(stack.info.get("compression", "raw"))
                pages = 0
                while True:  # every page's header and strips, not its pixels
                    for where, count in TIFF_DATA_TAGS:
                        starts, sizes = stack.tag_v2.get(where), stack.tag_v2.get(count)
                        if starts is not None and sizes is not None and \
                                max(int(a) + int(b) for a, b in zip(starts, sizes, strict=False)) > length:
                            raise InputError(f"page {pages} of {path.name} lies past the file's end (cut short): "
                                             "copy the stack again, or save it anew")
                    size = stack.size
                    if size != (first.shape[1], first.shape[0]):
                        raise InputError(f"page {pages} of {path.name} is {size[0]}x{size[1]} but the first is "
                                         f"{first.shape[1]}x{first.shape[0]}: all pages must have the same size")
                    pages += 1
                    try:
                        stack.seek(pages)
                    except EOFError:
                        break
        except InputError:
            raise
        except (OSError, ValueError, SyntaxError) as error:
            raise InputError(f"{str(path)!r} cannot be read as a TIFF ({error}): check the file") from None
        if pages != listed:
            raise InputError(f"{path.name} lists {listed} pages but {pages} could be read: check the file")
        self._take_first(first, fps, "TIFF pages")
        self.header_frames = pages
        self._set_roi(roi)

    @property
    def lossless(self) -> bool:
        """TIFF pages hold what was saved, unless JPEG-compressed (the first page's compression)."""
        return "jpeg" not in self._compression.lower()

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        from PIL import Image

        last = self.header_frames if stop is None else min(stop, self.header_frames)
        with Image.open(self.path) as stack:
            for index in range(last):
                self.frames_read = index + 1
                if index < start:
                    continue
                try:
                    stack.seek(index)
                    image = page_array(stack)
                except (OSError, ValueError, EOFError) as error:
                    raise InputError(f"page {index} of {self.path.name} cannot be read ({error}): check the "
                                     "file") from None
                yield index, self._time(index), self._checked(image, f"page {index} of {self.path.name}")
