"""Readers for high-speed camera recordings: Photron ``.cih``/``.cihx`` + ``.mraw``, Phantom ``.cine``.

Clean-room readers written from public descriptions of the two formats (no
vendor SDK code). Opening a file parses its header only; :meth:`CameraFile.read`
then seeks to ONE frame and reads just that frame's bytes, so memory stays
constant whatever the size of the recording.

Photron
    The ``.cih`` header is text, one ``Key : Value`` per line; a ``.cihx``
    holds the same information as XML (``<cih>...</cih>``) after a binary
    preamble. The frames are in the ``.mraw`` file of the same name beside it,
    back to back, without headers: 8 bit, 16 bit (little-endian unless told
    otherwise) or 12 bit packed (two pixels in three bytes, most significant
    bits first).
Phantom
    A ``.cine`` starts with CINEFILEHEADER (magic ``"CI"``), whose offsets give
    the BITMAPINFOHEADER (image geometry and packing), the SETUP (camera
    settings), the tagged information blocks after SETUP (type 1002: one TIME64
    time stamp per image) and the array of 64-bit file positions of the
    images; each image is preceded by an annotation block whose last four bytes
    are the image's size. Images are 8 or 16 bit (stored bottom-up, as in a
    Windows DIB), 10 bit packed (four pixels in five bytes: companded codes of
    the 12-bit sensor values, returned as stored) or 12 bit packed (two pixels
    in three bytes).

All integers are little-endian. Colour recordings are refused with an
:class:`~flow.io.errors.InputError` (the readers return grey frames only), as is
every malformed file, with a message naming the problem and what to do.
"""

from __future__ import annotations

import operator
import os
import struct
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Literal

import numpy as np

from flow.io.errors import InputError

__all__ = [
    "CAMERA_SUFFIXES",
    "CameraFile",
    "PhantomCine",
    "PhotronMraw",
    "companion_files",
    "open_camera_file",
    "unpack_bits",
]

CAMERA_SUFFIXES = (".cih", ".cihx", ".cine")


def open_camera_file(path: str | os.PathLike[str]) -> CameraFile | None:
    """Open a high-speed camera recording by its suffix.

    Parameters
    ----------
    path : str or os.PathLike
        A Photron header (``.cih`` or ``.cihx``, with its ``.mraw`` beside it)
        or a Phantom ``.cine``. The suffix is matched case-insensitively.

    Returns
    -------
    CameraFile or None
        A reader with the header parsed, or None when the suffix is none of
        :data:`CAMERA_SUFFIXES` (the caller then tries other readers).

    Raises
    ------
    flow.io.errors.InputError
        The file is missing, malformed, truncated or in a variant these
        readers do not support.
    """
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix in (".cih", ".cihx"):
        return PhotronMraw(p)
    if suffix == ".cine":
        return PhantomCine(p)
    return None


_MRAW_SUFFIXES = (".mraw", ".MRAW", ".Mraw")


def companion_files(path: str | os.PathLike[str]) -> list[Path]:
    """The files beside ``path`` that its recording reads: a Photron header's ``.mraw``."""
    p = Path(path)
    if p.suffix.lower() not in (".cih", ".cihx"):
        return []
    return [c for c in (p.with_suffix(suffix) for suffix in _MRAW_SUFFIXES) if c.is_file()][:1]


class CameraFile:
    """A recording read one frame at a time from disk.

    Attributes
    ----------
    path : pathlib.Path
        The file the user named (the ``.cih``/``.cihx`` or the ``.cine``).
    data_path : pathlib.Path
        The file holding the frames (the ``.mraw``, or the ``.cine`` itself).
    width, height : int
        Frame size in pixels; :meth:`read` returns ``(height, width)`` arrays.
    frame_count : int
        Frames in the file.
    fps : float
        Recording rate from the header, frames per second.
    frame_step : int
        Recorded frames per stored frame (Photron's ``Save Step``: a file saved
        with step 100 keeps every 100th frame); 1 for Phantom. Consecutive
        stored frames are ``frame_step / fps`` seconds apart.
    bit_depth : int
        Bits the returned pixel values occupy: they lie in
        ``[0, 2**bit_depth - 1]``.
    dtype : numpy.dtype
        ``uint8`` or ``uint16``, the dtype :meth:`read` returns.
    first_frame_number : int
        Camera frame number of the first stored frame, the trigger frame
        being 0 (Photron ``Start Frame``, Phantom ``FirstImageNo``).
    trigger_mode : str or None
        Photron ``Trigger Mode`` (e.g. ``"Start"``); None where the header
        has none.
    trigger_time_posix : float or None
        Phantom trigger time, seconds since 1970-01-01 UTC; None for Photron.
    has_timestamps : bool
        Whether :meth:`time_s` comes from per-frame time stamps stored in the
        file (Phantom's TIME64 block) rather than from ``fps``.
    timestamps_note : str or None
        Why stored time stamps were set aside, where they were.
    header : dict
        The header fields the reader parsed, by their names in the format.
    """

    path: Path
    data_path: Path
    width: int
    height: int
    frame_count: int
    fps: float
    frame_step: int = 1
    bit_depth: int
    dtype: np.dtype
    first_frame_number: int = 0
    trigger_mode: str | None = None
    trigger_time_posix: float | None = None
    has_timestamps: bool = False
    timestamps_note: str | None = None
    header: dict[str, object]
    _times: np.ndarray | None = None  # per-frame stamps where the file has them

    def __len__(self) -> int:
        return self.frame_count

    def __repr__(self) -> str:
        return (f"{type(self).__name__}({str(self.path)!r}: {self.frame_count} frames of "
                f"{self.width}x{self.height} px, {self.bit_depth}-bit, {self.fps:g} fps)")

    @property
    def frame_interval_s(self) -> float:
        """Nominal time between consecutive stored frames, ``frame_step / fps`` seconds."""
        return self.frame_step / self.fps

    def read(self, index: int) -> np.ndarray:
        """Read one frame from disk.

        Parameters
        ----------
        index : int
            Position of the frame in the file, 0-based; negative counts from
            the end as for a sequence.

        Returns
        -------
        numpy.ndarray
            A new ``(height, width)`` array of :attr:`dtype`, grey values in
            ``[0, 2**bit_depth - 1]``, row 0 at the top of the image.

        Raises
        ------
        IndexError
            ``index`` is outside the file's frames.
        flow.io.errors.InputError
            The frame's bytes are missing or inconsistent with the header.
        """
        return self._read_frame(self._check_index(index))

    def time_s(self, index: int) -> float:
        """Time of one frame in seconds after the first stored frame.

        Parameters
        ----------
        index : int
            Position of the frame in the file (as for :meth:`read`).

        Returns
        -------
        float
            ``index * frame_step / fps`` unless the file stores per-frame time
            stamps (Phantom's TIME64 block), which are then used.
        """
        i = self._check_index(index)
        if self._times is not None:
            return float(self._times[i])
        return i * self.frame_step / self.fps

    def timestamps_s(self) -> np.ndarray:
        """Times of all frames in seconds after the first stored frame.

        Returns
        -------
        numpy.ndarray
            ``(frame_count,)`` float64, as :meth:`time_s` gives them.
        """
        if self._times is not None:
            return self._times.copy()
        return np.arange(self.frame_count, dtype=np.float64) * (self.frame_step / self.fps)

    # -- for the readers ------------------------------------------------------------------

    def _check_index(self, index: int) -> int:
        i = operator.index(index)
        if not -self.frame_count <= i < self.frame_count:
            raise IndexError(f"frame {i} is outside {self.path.name}'s "
                             f"{self.frame_count} frames (0..{self.frame_count - 1})")
        return i % self.frame_count

    def _read_frame(self, index: int) -> np.ndarray:
        raise NotImplementedError

    def _read_bytes(self, offset: int, size: int) -> bytes:
        """Read exactly ``size`` bytes at ``offset`` of :attr:`data_path`, and no more."""
        with open(self.data_path, "rb") as f:
            f.seek(offset)
            data = f.read(size)
        if len(data) != size:
            raise InputError(f"{self.data_path.name} ends at byte {offset + len(data)}, inside "
                             f"data the header places at bytes {offset}..{offset + size}: the "
                             "file is truncated; copy it again from the camera or its computer")
        return data


# ---------------------------------------------------------------------------------------
# Photron
# ---------------------------------------------------------------------------------------

# .cihx element paths (below <cih>) that carry the .cih keys this reader uses
_CIHX_KEYS = {
    "Record Rate(fps)": "recordInfo/recordRate",
    "Total Frame": "frameInfo/totalFrame",
    "Original Total Frame": "frameInfo/recordedFrame",
    "Start Frame": "frameInfo/startFrame",
    "Image Width": "imageDataInfo/resolution/width",
    "Image Height": "imageDataInfo/resolution/height",
    "Color Type": "imageDataInfo/colorInfo/type",
    "Color Bit": "imageDataInfo/colorInfo/bit",
    "EffectiveBit Depth": "imageDataInfo/effectiveBit/depth",
    "EffectiveBit Side": "imageDataInfo/effectiveBit/side",
    "File Format": "imageFileInfo/fileFormat",
    "Camera Type": "deviceInfo/deviceName",
    "Date": "fileInfo/date",
}
_PHOTRON_REQUIRED = ("Record Rate(fps)", "Total Frame", "Image Width", "Image Height", "Color Bit")


def _parse_cih(path: Path) -> dict[str, str]:
    """``Key : Value`` lines of a .cih; the first occurrence of a key wins."""
    text = path.read_bytes().decode("utf-8", errors="replace")
    fields: dict[str, str] = {}
    for line in text.splitlines():
        key, sep, value = line.partition(":")
        key = key.strip()
        if sep and key and not key.startswith("#"):
            fields.setdefault(key, value.strip())
    return fields


def _parse_cihx(path: Path) -> dict[str, str]:
    """The .cihx XML block, mapped onto the .cih key names of :data:`_CIHX_KEYS`."""
    data = path.read_bytes()
    start, end = data.find(b"<cih>"), data.rfind(b"</cih>")
    if start < 0 or end < start:
        raise InputError(f"{path.name} holds no <cih>...</cih> XML header: it is not a Photron "
                         ".cihx file; open the recording's .cih or re-save it from PFV")
    try:
        root = ET.fromstring(data[start:end + len(b"</cih>")])
    except ET.ParseError as e:
        raise InputError(f"{path.name}: its XML header is malformed ({e}); re-save the "
                         "recording from PFV") from None
    fields: dict[str, str] = {}
    for key, where in _CIHX_KEYS.items():
        node = root.find(where)
        if node is not None and node.text is not None and node.text.strip():
            fields[key] = node.text.strip()
    return fields


class PhotronMraw(CameraFile):
    """A Photron recording: a ``.cih``/``.cihx`` header and its ``.mraw`` frames.

    Header keys used (``.cih`` names; :data:`_CIHX_KEYS` gives the ``.cihx``
    elements): ``Record Rate(fps)``, ``Total Frame``, ``Image Width``,
    ``Image Height``, ``Color Bit`` (8, 12 packed, 16) are required;
    ``Color Type`` (must be ``Mono``), ``File Format`` (must be ``MRaw``),
    ``EffectiveBit Depth`` and ``EffectiveBit Side``, ``Save Step``,
    ``Start Frame`` and ``Trigger Mode`` are used where present.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.cih`` or ``.cihx`` file; the ``.mraw`` of the same name must be
        beside it.
    byteorder : {"<", ">"}
        Byte order of 16-bit frames: little-endian (PFV's default) or
        big-endian. Ignored for 8 and 12-bit files.

    Notes
    -----
    ``bit_depth`` is the ``Color Bit`` of the stored data, narrowed to
    ``EffectiveBit Depth`` where the sensor's bits sit in the low end of a
    wider container (``EffectiveBit Side`` ``Lower``). A 16-bit file with the
    effective bits on the ``Higher`` side keeps its values as stored and
    reports 16.
    """

    def __init__(self, path: str | os.PathLike[str], *, byteorder: Literal["<", ">"] = "<") -> None:
        self.path = Path(path)
        if byteorder not in ("<", ">"):
            raise ValueError(f"byteorder must be '<' or '>', not {byteorder!r}")
        if not self.path.is_file():
            raise InputError(f"{self.path} does not exist: give the recording's .cih or .cihx "
                             "header file")
        if self.path.suffix.lower() == ".cihx":
            fields = _parse_cihx(self.path)
        else:
            fields = _parse_cih(self.path)
        self.header = dict(fields)
        name = self.path.name
        missing = [k for k in _PHOTRON_REQUIRED if k not in fields]
        if missing:
            raise InputError(f"{name} lacks the header keys {', '.join(map(repr, missing))}: "
                             "it is not a complete Photron header; re-save the recording from "
                             "PFV")
        fmt = fields.get("File Format", "MRaw")
        if fmt.lower() != "mraw":
            raise InputError(f"{name}: File Format {fmt!r} is not supported, only MRaw frames "
                             "are; save the recording as MRAW from PFV")
        colour = fields.get("Color Type", "Mono")
        if colour.lower() != "mono":
            raise InputError(f"{name}: Color Type {colour!r}: colour recordings are not "
                             "supported; save the recording as monochrome from PFV")
        self.fps = _header_number(fields, "Record Rate(fps)", name)
        self.frame_count = _header_int(fields, "Total Frame", name)
        self.width = _header_int(fields, "Image Width", name)
        self.height = _header_int(fields, "Image Height", name)
        bits = _header_int(fields, "Color Bit", name)
        self.frame_step = _header_int(fields, "Save Step", name, default=1)
        self.first_frame_number = _header_int(fields, "Start Frame", name, default=0)
        self.trigger_mode = fields.get("Trigger Mode")
        self.trigger_time_posix = None
        for label, value in (("Record Rate(fps)", self.fps), ("Total Frame", self.frame_count),
                             ("Image Width", self.width), ("Image Height", self.height),
                             ("Save Step", self.frame_step)):
            if not value > 0:
                raise InputError(f"{name}: {label} is {value}; a recording needs a positive "
                                 f"value: the header is damaged, re-save it from PFV")
        if bits not in (8, 12, 16):
            raise InputError(f"{name}: Color Bit {bits} is not supported (8, 12 packed or 16 "
                             "only); save the recording with one of these from PFV")
        pixels = self.width * self.height
        if bits == 12 and pixels % 2:
            raise InputError(f"{name}: 12-bit packing of a {self.width}x{self.height} frame "
                             "(odd pixel count) is not supported; save the recording as 8 or 16 "
                             "bit from PFV")
        self._bits = bits
        self._frame_bytes = pixels * bits // 8
        self._byteorder = byteorder
        self.dtype = np.dtype(np.uint8 if bits == 8 else np.uint16)
        effective = _header_int(fields, "EffectiveBit Depth", name, default=bits)
        higher = fields.get("EffectiveBit Side", "Lower").lower() == "higher"
        if 0 < effective < bits and not higher:
            self.bit_depth = effective
        else:
            self.bit_depth = bits

        self.data_path = self._find_mraw()
        size = self.data_path.stat().st_size
        expected = self._frame_bytes * self.frame_count
        if size < expected:
            complete = size // self._frame_bytes
            raise InputError(f"{self.data_path.name} is truncated: its {size} bytes hold "
                             f"{complete} complete frames of the {self.frame_count} that {name} "
                             f"declares ({self._frame_bytes} bytes each, {expected} in all); "
                             "copy the file again, or fix Total Frame in the header to "
                             f"{complete} to use the complete ones")

    def _find_mraw(self) -> Path:
        for candidate in companion_files(self.path):
            return candidate
        raise InputError(f"{self.path.with_suffix('.mraw').name} is missing beside "
                         f"{self.path.name}: the header holds no frames; put the .mraw saved "
                         "with it in the same folder under the same name")

    def _read_frame(self, index: int) -> np.ndarray:
        raw = self._read_bytes(index * self._frame_bytes, self._frame_bytes)
        shape = (self.height, self.width)
        if self._bits == 8:
            return np.frombuffer(raw, np.uint8).reshape(shape).copy()
        if self._bits == 16:
            stored = np.frombuffer(raw, np.dtype(np.uint16).newbyteorder(self._byteorder))
            return stored.astype(np.uint16).reshape(shape)
        return unpack_bits(raw, 12, self.width * self.height).reshape(shape)


def _header_number(fields: dict[str, str], key: str, name: str) -> float:
    """Header value ``key`` of the file ``name`` as a float; InputError if not a number."""
    text = fields[key]
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{name}: header key {key!r} is {text!r}, not a number; the header is "
                         "damaged, re-save it from PFV") from None
    if not np.isfinite(value):
        raise InputError(f"{name}: header key {key!r} is {text!r}, not a finite number; the "
                         "header is damaged, re-save it from PFV")
    return value


def _header_int(fields: dict[str, str], key: str, name: str, default: int | None = None) -> int:
    """Header value ``key`` as an int, ``default`` where absent; InputError if not whole."""
    if key not in fields and default is not None:
        return default
    value = _header_number(fields, key, name)
    if not value.is_integer():
        raise InputError(f"{name}: header key {key!r} is {fields[key]!r}, not a whole number; "
                         "the header is damaged, re-save it from PFV")
    return int(value)


# ---------------------------------------------------------------------------------------
# Phantom
# ---------------------------------------------------------------------------------------

_CINE_HEADER = struct.Struct("<2sHHHiIiIIIIII")  # CINEFILEHEADER, 44 bytes
_BITMAP_HEADER = struct.Struct("<IiiHHIIiiII")  # BITMAPINFOHEADER, 40 bytes
# SETUP fields (byte offset from the start of SETUP; the structure is packed, 1-byte aligned)
_SETUP_FRAMERATE16 = 0  # uint16, the old frame rate field
_SETUP_LENGTH = 142  # uint16, bytes of SETUP in this file (tagged blocks follow)
_SETUP_FRAMERATE = 768  # uint32, frames per second
_SETUP_CFA = 808  # uint32, colour filter array code, 0 = grey sensor
_SETUP_REALBPP = 896  # uint32, significant bits per pixel
_SETUP_READ = 900  # bytes of SETUP this reader needs
_TAG_TIME64 = 1002  # tagged block: one TIME64 per image
_BI_RGB, _BI_PACKED10, _BI_PACKED12 = 0, 256, 1024  # biCompression values

class PhantomCine(CameraFile):
    """A Phantom ``.cine`` recording (grey sensors; uncompressed, 10 or 12-bit packed images).

    Header fields used (byte offsets within their structure; the file
    positions of BITMAPINFOHEADER and SETUP come from CINEFILEHEADER):

    * CINEFILEHEADER at 0: ``Type`` 0 (``"CI"``), ``Compression`` 4 (0 grey,
      1 JPEG: refused, 2 raw), ``FirstImageNo`` 16, ``ImageCount`` 20,
      ``OffImageHeader`` 24, ``OffSetup`` 28, ``OffImageOffsets`` 32,
      ``TriggerTime`` 36 (TIME64).
    * BITMAPINFOHEADER: ``biWidth`` 4, ``biHeight`` 8 (positive: rows stored
      bottom-up), ``biBitCount`` 14, ``biCompression`` 16 (0, 256 = 10-bit
      packed, 1024 = 12-bit packed), ``biSizeImage`` 20.
    * SETUP: ``FrameRate16`` 0, ``Length`` 142, ``FrameRate`` 768, ``CFA``
      808 (0 for a grey sensor), ``RealBPP`` 896.
    * Tagged blocks from ``OffSetup + Length`` to ``OffImageOffsets``, each
      ``BlockSize`` (uint32), ``Type`` (uint16), reserved (uint16), data;
      type 1002 holds a TIME64 (uint32 fractions of 2**-32 s, uint32 seconds)
      per image.
    * ``ImageCount`` int64 file positions at ``OffImageOffsets``; at each, an
      annotation block of ``AnnotationSize`` (uint32) bytes ending with the
      image's ``ImageSize`` (uint32), then the image.

    Parameters
    ----------
    path : str or os.PathLike
        The ``.cine`` file.

    Notes
    -----
    ``bit_depth`` is ``RealBPP`` for uncompressed 16-bit images (8 for 8-bit
    ones) and the packing's bits for packed images. 10-bit packed images are
    returned as their stored codes (a companded code of the 12-bit sensor value,
    monotonic; not linearised: displacements do not depend on it). ``time_s`` uses the TIME64 block
    where the file has a consistent one (``has_timestamps``), else
    ``index / fps``; ``timestamps_note`` says why a block was set aside.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = self.data_path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path} does not exist: give the Phantom .cine file")
        name = self.path.name
        self._size = size = self.path.stat().st_size
        (compression, first_no, count, off_bitmap, off_setup, off_offsets, trig_frac,
         trig_sec) = self._read_file_header(name, size)
        (_bi_size, width, height, _planes, bit_count, bi_compression, size_image,
         *_rest) = _BITMAP_HEADER.unpack(self._read_bytes(off_bitmap, _BITMAP_HEADER.size))
        setup_length, rate, cfa, real_bpp = self._read_setup(name, off_setup, size)
        if cfa != 0 or bit_count in (24, 48):
            raise InputError(f"{name} is a colour recording (CFA {cfa}, {bit_count} bits per "
                             "pixel), which is not supported; save it as grey (monochrome) "
                             "from the Phantom software")
        if width <= 0 or height == 0:
            raise InputError(f"{name}: the image size in its header is {width}x{height}; the "
                             "header is damaged, save the recording again")

        self.width, self.height = width, abs(height)
        self.frame_count = count
        self.fps = float(rate)
        self.frame_step = 1
        self.first_frame_number = first_no
        self.trigger_mode = None
        self.trigger_time_posix = trig_sec + (trig_frac & ~3) / 2.0**32
        self._set_image_layout(name, bi_compression, bit_count, real_bpp, height, size_image)
        self._read_image_offsets(name, off_offsets, count, size)

        self.timestamps_note = None
        self._times = self._read_time_block(off_setup + setup_length, off_offsets, count)
        self.has_timestamps = self._times is not None
        self.header = {
            "Compression": compression, "FirstImageNo": first_no, "ImageCount": count,
            "OffImageHeader": off_bitmap, "OffSetup": off_setup,
            "OffImageOffsets": off_offsets, "TriggerTime": self.trigger_time_posix,
            "biWidth": width, "biHeight": height, "biBitCount": bit_count,
            "biCompression": bi_compression, "biSizeImage": size_image,
            "FrameRate": rate, "CFA": cfa, "RealBPP": real_bpp, "SetupLength": setup_length,
        }

    def _read_file_header(self, name: str, size: int) -> tuple[int, ...]:
        """The CINEFILEHEADER's fields the reader uses, checked: ``(compression, first_no, count,
        off_bitmap, off_setup, off_offsets, trig_frac, trig_sec)``."""
        if size < _CINE_HEADER.size:
            raise InputError(f"{name} is {size} bytes, shorter than a cine header: it is "
                             "truncated or not a cine file; copy it again")
        (magic, _header_size, compression, _version, _first_movie, _total, first_no, count,
         off_bitmap, off_setup, off_offsets, trig_frac, trig_sec) = _CINE_HEADER.unpack(
            self._read_bytes(0, _CINE_HEADER.size))
        if magic != b"CI":
            raise InputError(f"{name} does not start with the cine magic 'CI' (it starts with "
                             f"{magic!r}): it is not a Phantom cine file")
        if compression == 1:
            raise InputError(f"{name} is a compressed (JPEG) cine, which is not supported; save "
                             "the recording uncompressed (Cine RAW) from the Phantom software")
        if compression not in (0, 2):
            raise InputError(f"{name}: unknown cine Compression code {compression}; save the "
                             "recording uncompressed (Cine RAW) from the Phantom software")
        if count == 0:
            raise InputError(f"{name} holds no images; save the recording again with its range")
        for label, offset, length in (("BITMAPINFOHEADER", off_bitmap, _BITMAP_HEADER.size),
                                      ("SETUP", off_setup, _SETUP_LENGTH + 2),
                                      ("image offset array", off_offsets, 8 * count)):
            if offset < _CINE_HEADER.size or offset + length > size:
                raise InputError(f"{name}: the header places its {label} at bytes {offset}.."
                                 f"{offset + length}, beyond the file's {size} bytes: the file "
                                 "is truncated or damaged; copy it again")
        return compression, first_no, count, off_bitmap, off_setup, off_offsets, trig_frac, trig_sec

    def _read_setup(self, name: str, off_setup: int, size: int) -> tuple[int, int, int, int]:
        """``(Length, frame rate, CFA, RealBPP)`` of the SETUP block (CFA and RealBPP 0 in a
        SETUP older than 2002)."""
        setup = self._read_bytes(off_setup, min(_SETUP_READ, size - off_setup))
        setup_length = struct.unpack_from("<H", setup, _SETUP_LENGTH)[0]
        rate = rate16 = struct.unpack_from("<H", setup, _SETUP_FRAMERATE16)[0]
        cfa = real_bpp = 0
        if setup_length >= _SETUP_READ and len(setup) >= _SETUP_READ:  # SETUP of 2002 or later
            rate = struct.unpack_from("<I", setup, _SETUP_FRAMERATE)[0] or rate16
            cfa = struct.unpack_from("<I", setup, _SETUP_CFA)[0] & 0x00FFFFFF
            real_bpp = struct.unpack_from("<I", setup, _SETUP_REALBPP)[0]
        if rate <= 0:
            raise InputError(f"{name}: the SETUP holds no frame rate (FrameRate is 0); the "
                             "header is damaged, save the recording again")
        return setup_length, rate, cfa, real_bpp

    def _set_image_layout(self, name: str, bi_compression: int, bit_count: int, real_bpp: int, height: int,
                          size_image: int) -> None:
        """Bytes per image and row, row order, dtype and bit depth of the image packing."""
        self._packing = bi_compression
        self._bottom_up = False
        pixels = self.width * self.height
        if bi_compression == _BI_RGB:
            if bit_count not in (8, 16):
                raise InputError(f"{name}: {bit_count} bits per pixel is not supported (8 or 16 "
                                 "only); save the recording as 8 or 16-bit Cine RAW")
            row = self.width * bit_count // 8
            padded = (row + 3) // 4 * 4  # DIB rows may be padded to 4 bytes
            self._stride = padded if size_image == padded * self.height else row
            self._frame_bytes = self._stride * self.height
            self._bottom_up = height > 0
            self.dtype = np.dtype(np.uint8 if bit_count == 8 else np.uint16)
            self.bit_depth = 8 if bit_count == 8 else (real_bpp if 8 < real_bpp <= 16 else 16)
        elif bi_compression in (_BI_PACKED10, _BI_PACKED12):
            bits = 10 if bi_compression == _BI_PACKED10 else 12
            if pixels * bits % 8:
                raise InputError(f"{name}: {bits}-bit packing of a {self.width}x{self.height} "
                                 "image does not fill whole bytes, which is not supported")
            self._frame_bytes = pixels * bits // 8
            self.dtype = np.dtype(np.uint16)
            # The codes as stored: Phantom's 10-bit packing holds a companded (log-like)
            # code of the 12-bit sensor value. refflow measures the codes: one monotonic
            # curve for every frame maps a moving edge to a moving edge, so displacements do
            # not depend on it (the grey levels are then not linear in light).
            self.bit_depth = bits
        else:
            raise InputError(f"{name}: image compression (biCompression) {bi_compression} is not "
                             "supported, only uncompressed and 10 or 12-bit packed images are; "
                             "save the recording uncompressed (Cine RAW) from the Phantom software")
        if size_image and size_image != self._frame_bytes:
            raise InputError(f"{name}: the header gives {size_image} bytes per image, but a "
                             f"{self.width}x{self.height} image of this packing takes "
                             f"{self._frame_bytes}: the header is damaged or the layout unknown")

    def _read_image_offsets(self, name: str, off_offsets: int, count: int, size: int) -> None:
        """The images' file positions; refuses a file whose last images are cut off."""
        self._offsets = np.frombuffer(self._read_bytes(off_offsets, 8 * count), "<i8").copy()
        first = int(self._offsets[0])
        annotation = 8  # the smallest annotation block: its size and the image size
        if 0 <= first <= size - 4:
            annotation = max(annotation, struct.unpack("<I", self._read_bytes(first, 4))[0])
        ends = self._offsets + annotation + self._frame_bytes
        complete = int(np.count_nonzero((self._offsets >= 0) & (ends <= size)))
        if complete < count:
            raise InputError(f"{name} is truncated: {complete} of its {count} images are "
                             f"complete in its {size} bytes; copy the file again")

    def _read_time_block(self, start: int, stop: int, count: int) -> np.ndarray | None:
        """Seconds after the first image from the TIME64 tagged block.

        None where the file has no such block, or where its stamps do not
        increase steadily (a step that is not positive, or over ten times the
        median step; :attr:`timestamps_note` then says where).
        """
        pos = start
        while pos + 8 <= stop:
            block_size, block_type = struct.unpack("<IH", self._read_bytes(pos, 6))
            if block_size < 8 or pos + block_size > stop:
                self.timestamps_note = (f"tagged block at byte {pos} claims {block_size} bytes, "
                                        "past the image offsets: times are index / fps")
                return None
            if block_type == _TAG_TIME64 and block_size >= 8 + 8 * count:
                stamps = np.frombuffer(self._read_bytes(pos + 8, 8 * count), "<u4").reshape(-1, 2)
                # TIME64: fractions of a second in units of 2**-32 s (the two lowest bits are
                # IRIG and event flags), then whole seconds since 1970
                fractions = (stamps[:, 0] & ~np.uint32(3)).astype(np.float64) / 2.0**32
                seconds = stamps[:, 1].astype(np.float64)
                times = (seconds - seconds[0]) + (fractions - fractions[0])
                steps = np.diff(times)
                limit = 10 * np.median(steps) if len(steps) else 0.0
                bad = np.flatnonzero((steps <= 0) | (steps > limit))
                if len(bad):
                    k = int(bad[0]) + 1
                    self.timestamps_note = (
                        f"TIME64 stamp of image {k} is {times[k] - times[k - 1]:+.6g} s after "
                        f"image {k - 1}'s, where 1/fps = {1 / self.fps:.6g} s: the block is "
                        "inconsistent, times are index / fps")
                    return None
                return times
            pos += block_size
        return None

    def _read_frame(self, index: int) -> np.ndarray:
        name = self.path.name
        at = int(self._offsets[index])
        if not 0 <= at <= self._size - 8:
            raise InputError(f"{name}: image {index} is placed at byte {at}, outside the file's "
                             f"{self._size} bytes: the file is truncated or damaged")
        annotation = struct.unpack("<I", self._read_bytes(at, 4))[0]
        if annotation < 8 or at + annotation + self._frame_bytes > self._size:
            raise InputError(f"{name}: image {index} (annotation of {annotation} bytes at byte "
                             f"{at}) runs past the file's {self._size} bytes: the file is "
                             "truncated or damaged; copy it again")
        raw = self._read_bytes(at + annotation - 4, 4 + self._frame_bytes)
        declared = struct.unpack_from("<I", raw)[0]
        if declared != self._frame_bytes:
            raise InputError(f"{name}: image {index} declares {declared} bytes where its header "
                             f"layout needs {self._frame_bytes}; this image layout is not "
                             "supported")
        data = raw[4:]
        shape = (self.height, self.width)
        if self._packing in (_BI_PACKED10, _BI_PACKED12):
            return unpack_bits(data, self.bit_depth, self.width * self.height).reshape(shape)
        stored = np.frombuffer(data, "<u2" if self.dtype == np.uint16 else np.uint8)
        item = self.dtype.itemsize
        image = stored.reshape(self.height, self._stride // item)[:, :self.width]
        if self._bottom_up:
            image = image[::-1]
        return image.astype(self.dtype)  # a native-order, writable copy


def unpack_bits(data: bytes, bits: Literal[10, 12], count: int) -> np.ndarray:
    """Unpack pixels packed back to back, most significant bit first.

    Parameters
    ----------
    data : bytes
        The packed bytes: for 12 bits, two pixels in three bytes; for 10
        bits, four pixels in five bytes.
    bits : {10, 12}
        Bits per pixel.
    count : int
        Pixels to unpack; a multiple of the pixels per group (2 or 4).

    Returns
    -------
    numpy.ndarray
        ``(count,)`` uint16 values in ``[0, 2**bits - 1]``.
    """
    per_group = {10: 4, 12: 2}[bits]
    group_bytes = per_group * bits // 8
    if count % per_group:
        raise ValueError(f"{count} pixels do not fill whole {bits}-bit groups of {per_group}")
    groups = np.frombuffer(data, np.uint8, count // per_group * group_bytes)
    groups = groups.reshape(-1, group_bytes).astype(np.uint64)
    word = np.zeros(len(groups), np.uint64)
    for column in range(group_bytes):  # the group as one big-endian integer
        word = (word << np.uint64(8)) | groups[:, column]
    shifts = np.arange(per_group - 1, -1, -1, dtype=np.uint64) * np.uint64(bits)
    pixels = (word[:, None] >> shifts[None, :]) & np.uint64((1 << bits) - 1)
    return pixels.astype(np.uint16).reshape(-1)
