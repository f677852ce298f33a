"""The Photron reader: a ``.cih``/``.cihx`` header and its ``.mraw`` frames (clean-room, from
public descriptions of the format; no vendor SDK code).

The ``.cih`` header is text, one ``Key : Value`` per line; a ``.cihx`` holds the same
information as XML (``<cih>...</cih>``) after a binary preamble. The frames are in the
``.mraw`` file of the same name beside it, back to back, without headers: 8 bit, 16 bit
(little-endian unless told otherwise) or 12 bit packed (two pixels in three bytes, most
significant bits first).
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Literal

import numpy as np

from flow.io.camfiles import CameraFile, companion_files, unpack_bits
from flow.io.errors import InputError

__all__ = ["PhotronMraw"]

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


def _check_kind(fields: dict[str, str], name: str) -> None:
    """A complete header of monochrome MRaw frames, the only kind these readers read."""
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
        fields = _parse_cihx(self.path) if self.path.suffix.lower() == ".cihx" else _parse_cih(self.path)
        self.header = dict(fields)
        name = self.path.name
        _check_kind(fields, name)
        bits = self._read_numbers(fields, name)
        self._set_depth(fields, name, bits, byteorder)
        self.data_path = self._find_mraw()
        self._check_data(name)

    def _read_numbers(self, fields: dict[str, str], name: str) -> int:
        """Rate, frame count, size, save step, start frame and trigger from the header; returns
        its ``Color Bit`` (checked by :meth:`_set_depth`)."""
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
        return bits

    def _set_depth(self, fields: dict[str, str], name: str, bits: int, byteorder: Literal["<", ">"]) -> None:
        """The stored depth (8, 12 packed or 16 bit), the bytes of a frame and the bits its values use."""
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

    def _check_data(self, name: str) -> None:
        """The .mraw holds every frame the header declares."""
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
