"""The Phantom reader: a ``.cine`` file (clean-room, from public descriptions of the format; no
vendor SDK code).

A ``.cine`` starts with CINEFILEHEADER (magic ``"CI"``), whose offsets give the
BITMAPINFOHEADER (image geometry and packing), the SETUP (camera settings), the tagged
information blocks after SETUP (type 1002: one TIME64 time stamp per image) and the array of
64-bit file positions of the images; each image is preceded by an annotation block whose last
four bytes are the image's size. Images are 8 or 16 bit (stored bottom-up, as in a Windows
DIB), 10 bit packed (four pixels in five bytes: companded codes of the 12-bit sensor values,
returned as stored) or 12 bit packed (two pixels in three bytes). All integers are
little-endian.
"""

from __future__ import annotations

import os
import struct
from pathlib import Path

import numpy as np

from flow.io.camfiles import CameraFile, unpack_bits
from flow.io.errors import InputError

__all__ = ["PhantomCine"]

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
