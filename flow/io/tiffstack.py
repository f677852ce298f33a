"""The TIFF-stack reader: one multi-page TIFF file, one frame per page (ImageJ, scientific
cameras and DIC tools save image sequences so).

OpenCV's video reader decodes such a file's first page only: a stack was measured as one
frame, and nothing said so. The stack is read with tifffile, one frame at a time, so memory
holds one frame whatever the stack's length:

* frames stored one after the other without compression (most stacks, and ImageJ's stacks
  over 4 GB, which list only their first page and say ``images=N`` in its description) are
  read straight from their place in the file;
* others (compressed, or scattered) page by page.

The stack's series must have one axis besides the image's own (rows, columns, colour): an
ImageJ hyperstack of channels and time, or slices and time, is refused (which axis is time is
not for this tool to guess). Like a folder of images, a stack carries no time stamps
(``--fps``), its frames share one size and pixel type, and data deeper than 8 bits is measured
at full depth (:class:`flow.io.frames.ImageSequence`). The page list and the frames' data are
checked to lie within the file before the first frame is measured.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from flow.io.errors import InputError
from flow.io.frames import ImageSequence, Roi

__all__ = ["TIFF_SUFFIXES", "TiffStackSource", "is_tiff_stack", "tiff_pages"]

TIFF_SUFFIXES = (".tif", ".tiff")
_IMAGE_AXES = set("YXS")


def tiff_pages(path: Path) -> tuple[int, str]:
    """The number of pages (image file directories) of the TIFF ``path``, counted by walking
    their chain, and what cuts it short ("" where nothing does): a chain that points past the
    file's end is a file cut short, where readers just find fewer pages (with a warning)."""
    length = path.stat().st_size
    with path.open("rb") as handle:
        head = handle.read(16)
        order = {b"II": "little", b"MM": "big"}.get(head[:2])
        if order is None or len(head) < 8:
            return 0, "not a TIFF"
        big = int.from_bytes(head[2:4], order) == 43
        word, count_size, entry = (8, 8, 20) if big else (4, 2, 12)
        at = int.from_bytes(head[8:16] if big else head[4:8], order)
        pages, seen = 0, set()
        while at:
            if at in seen:
                return pages, f"its page list loops back at page {pages}"
            seen.add(at)
            if at + count_size > length:
                return pages, f"page {pages} lies past the file's end"
            handle.seek(at)
            entries = int.from_bytes(handle.read(count_size), order)
            end = at + count_size + entries * entry + word
            if end > length:
                return pages, f"page {pages} lies past the file's end"
            handle.seek(end - word)
            at = int.from_bytes(handle.read(word), order)
            pages += 1
    return pages, ""


@contextlib.contextmanager
def _quiet() -> Iterator[None]:
    """tifffile logs what it finds odd in a file (a cut ImageJ stack's metadata) as warnings on
    stderr; this reader says what matters in its own one-line message."""
    logger = logging.getLogger("tifffile")
    level = logger.level
    logger.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        logger.setLevel(level)


def _frame_axes(series) -> tuple[list[int], int]:
    """The positions of a series' axes that are not the image's own, and the frame count."""
    others = [i for i, axis in enumerate(series.axes) if axis not in _IMAGE_AXES]
    return others, int(np.prod([series.shape[i] for i in others])) if others else 1


def is_tiff_stack(path: Path) -> bool:
    """Whether ``path`` is a TIFF file of more than one frame (a single image: read as before
    by the video reader); a TIFF whose page list is cut short counts (the reader refuses it)."""
    if path.suffix.lower() not in TIFF_SUFFIXES:
        return False
    pages, problem = tiff_pages(path)
    if problem and pages >= 1:
        return True
    if pages == 0:
        return False
    import tifffile

    try:
        with _quiet(), tifffile.TiffFile(path) as tif:
            return max(_frame_axes(tif.series[0])[1], _imagej_images(tif), len(_main_pages(tif))) > 1
    except Exception:  # noqa: BLE001 - tifffile raises many kinds on odd files: not a stack
        return False


def _main_pages(tif) -> list:
    """The file's pages that are images of their own (a reduced-resolution thumbnail is not)."""
    return [page for page in tif.pages if not getattr(page, "is_reduced", False)]


def _imagej_images(tif) -> int:
    """The image count an ImageJ stack's description lists (0 for other files)."""
    meta = tif.imagej_metadata or {}
    try:
        return int(meta.get("images", 0))
    except (TypeError, ValueError):
        return 0


def _pillow_page(image, index: int) -> np.ndarray:
    """Page ``index`` of the TIFF open in Pillow as ``image``, decoded by Pillow (LZW and the
    other compressions tifffile leaves to the imagecodecs package), as stored: colour in RGB
    order, native byte order. Pillow finds a page from the one before, so pages read in turn
    cost one step each. Pillow has no 16-bit colour: such pages are refused."""
    image.seek(index)
    bits = image.tag_v2.get(258, (8,))
    if image.mode in ("RGB", "RGBA") and max(bits) > 8:
        raise ValueError(f"{max(bits)}-bit colour in a compression only imagecodecs decodes")
    page = image
    if page.mode not in {"L", "I;16", "I;16B", "I;16L", "I", "F", "RGB", "RGBA"}:
        page = page.convert("RGB" if page.mode not in ("1", "LA", "La") else "L")
    array = np.asarray(page)
    return array.astype(array.dtype.newbyteorder("="), copy=False)


class TiffStackSource(ImageSequence):
    """The frames of a multi-page TIFF file.

    Parameters
    ----------
    path : Path
        The file (it exists: :func:`flow.io.source.open_source` checked).
    roi, fps, require_fps
        As for :class:`flow.io.folder.ImageFolderSource`.
    """

    def __init__(self, path: Path, *, roi: Roi | None = None, fps: float | None = None,
                 require_fps: bool = True) -> None:
        import tifffile

        super().__init__(path)
        if fps is None and require_fps:
            raise InputError(f"{str(path)!r} is a TIFF stack of images without timestamps: pass --fps (the camera "
                             "frame rate)")
        listed, problem = tiff_pages(path)
        if problem:
            raise InputError(f"{path.name}: {problem} ({listed} page(s) before it; cut short?): copy the stack "
                             "again, or save it anew")
        length = path.stat().st_size
        try:
            with _quiet(), tifffile.TiffFile(path) as tif:
                series = tif.series[0]
                others, frames = _frame_axes(series)
                if sum(series.shape[i] > 1 for i in others) > 1:
                    raise InputError(f"{path.name} is a hyperstack ({series.axes} {tuple(series.shape)}): save the "
                                     "time series of one channel and one slice as its own stack")
                main = _main_pages(tif)
                images = _imagej_images(tif)
                self._compression = str(main[0].compression).lower()
                if images > len(main):
                    # ImageJ's layout for stacks over 4 GB: the first page listed alone, the
                    # frames one after the other from its data on.
                    if frames < images or series.dataoffset is None:
                        raise InputError(f"{path.name} lists {images} ImageJ images but holds {frames} (cut "
                                         "short): copy the stack again, or save it anew")
                    self._contiguous(main[0], series.dataoffset, images, tif.byteorder, length)
                    count = images
                else:
                    self._paged(main, length)
                    count = len(main)
                first = self._read(tif, 0)
        except InputError:
            raise
        except Exception as error:  # noqa: BLE001 - tifffile raises many kinds on a damaged file
            raise InputError(f"{str(path)!r} cannot be read as a TIFF stack ({error or type(error).__name__}): "
                             "check the file") from None
        self._take_first(first, fps, "TIFF pages")
        self.header_frames = count
        self._set_roi(roi)

    def _contiguous(self, page, offset: int, images: int, byteorder: str, length: int) -> None:
        """Frames read from their place in the file: ``images`` of ``page``'s shape from ``offset``."""
        self._offset = offset
        self._page_shape, self._axes = page.shape, page.axes
        self._stored = page.dtype.newbyteorder(byteorder)
        frame_bytes = int(np.prod(self._page_shape)) * self._stored.itemsize
        if offset + images * frame_bytes > length:
            whole = max((length - offset) // frame_bytes, 0)
            raise InputError(f"{self.path.name} holds {whole} whole frame(s) of the {images} it lists (cut short): "
                             "copy the stack again, or save it anew")

    def _paged(self, main: list, length: int) -> None:
        """One frame per page (``main``: the pages that are images of their own), all of one
        size and pixel type, their data within the file."""
        self._offset = None
        self._via_pillow = False  # set on the first page tifffile cannot decode without imagecodecs
        self._pages = [page.index for page in main]
        self._axes = main[0].axes
        for k, page in enumerate(main):
            if page.shape != main[0].shape or page.dtype != main[0].dtype:
                raise InputError(f"page {k} of {self.path.name} is {page.shape[1]}x{page.shape[0]} {page.dtype} but "
                                 f"the first is {main[0].shape[1]}x{main[0].shape[0]} {main[0].dtype}: all pages "
                                 "must have one size and pixel type")
            ends = [int(o) + int(n) for o, n in zip(page.dataoffsets, page.databytecounts, strict=False)]
            if ends and max(ends) > length:
                raise InputError(f"page {k} of {self.path.name} lies past the file's end (cut short): copy the "
                                 "stack again, or save it anew")

    @property
    def lossless(self) -> bool:
        """TIFF frames hold what was saved, unless JPEG-compressed."""
        return "jpeg" not in self._compression

    def _read(self, tif, index: int, pillow: contextlib.ExitStack | None = None) -> np.ndarray:
        """Frame ``index`` as OpenCV reads images: native byte order, rows x columns (x colour,
        in BGR order). ``pillow``: where the file stays open in Pillow between pages, if its
        compression needs it (opened on the first such page)."""
        if self._offset is not None:
            count = int(np.prod(self._page_shape))
            with self.path.open("rb") as handle:
                handle.seek(self._offset + index * count * self._stored.itemsize)
                array = np.frombuffer(handle.read(count * self._stored.itemsize), self._stored)
            array = array.reshape(self._page_shape)
        else:
            array = None
            if not self._via_pillow:
                try:
                    array = tif.pages[self._pages[index]].asarray()
                except ValueError as error:  # a compression tifffile decodes only with imagecodecs (LZW)
                    if "imagecodecs" not in str(error):
                        raise
                    self._via_pillow = True
            if array is None:
                array = self._pillow_read(self._pages[index], pillow)
        array = array.astype(array.dtype.newbyteorder("="), copy=False)
        own = [axis for axis in self._axes if axis in _IMAGE_AXES]
        if array.ndim == len(own) and own != [axis for axis in "YXS" if axis in own]:
            array = array.transpose([own.index(axis) for axis in "YXS" if axis in own])  # planar colour
        if array.ndim == 3 and array.shape[2] in (3, 4):
            array = array[..., [2, 1, 0, 3][:array.shape[2]]]
        return np.ascontiguousarray(array)

    def _pillow_read(self, page: int, pillow: contextlib.ExitStack | None) -> np.ndarray:
        from PIL import Image

        if pillow is None:
            with Image.open(self.path) as image:
                return _pillow_page(image, page)
        if not hasattr(pillow, "image"):
            pillow.image = pillow.enter_context(Image.open(self.path))
        return _pillow_page(pillow.image, page)

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        import tifffile

        last = self.header_frames if stop is None else min(stop, self.header_frames)
        with _quiet(), tifffile.TiffFile(self.path) as tif, contextlib.ExitStack() as pillow:
            for index in range(last):
                self.frames_read = index + 1
                if index < start:
                    continue
                try:
                    image = self._read(tif, index, pillow)
                except Exception as error:  # noqa: BLE001 - a damaged page, whatever tifffile raises
                    raise InputError(f"frame {index} of {self.path.name} cannot be read ({error}): check the "
                                     "file") from None
                yield index, self._time(index), self._checked(image, f"frame {index} of {self.path.name}")
