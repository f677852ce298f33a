"""High-speed camera files: Photron .cih/.cihx + .mraw and Phantom .cine (flow.io.camfiles)."""

from __future__ import annotations

import shutil
import struct
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

from flow.io.camera import open_camera_file
from flow.io.camfiles import unpack_bits
from flow.io.errors import InputError
from flow.io.phantom import PhantomCine
from flow.io.photron import PhotronMraw

ROOT = Path(__file__).resolve().parents[2]
DATA = ROOT / ".." / "shared" / "data"
CIH = DATA / "data_showcase.cih"
CINE = DATA / "data_small_cine.cine"
needs_data = pytest.mark.skipif(
    not (CIH.is_file() and CIH.with_suffix(".mraw").is_file() and CINE.is_file()),
    reason=f"shared camera samples absent from {DATA} (see shared/data/README.md)")


# -- writers the tests build their files with (independent of the readers) ------------------

def pack_msb(values: np.ndarray, bits: int) -> bytes:
    """Pixels back to back, most significant bit first, via a bit string."""
    text = "".join(format(int(v), f"0{bits}b") for v in np.ravel(values))
    assert len(text) % 8 == 0
    return int(text, 2).to_bytes(len(text) // 8, "big")


CIH_KEYS = {
    "Record Rate(fps)": "5000", "Shutter Speed(s)": "1/5000", "Trigger Mode": "Start",
    "Total Frame": "3", "Start Frame": "-2", "Save Step": "1", "Image Width": "6",
    "Image Height": "4", "Color Type": "Mono", "Color Bit": "8", "File Format": "MRaw",
    "EffectiveBit Depth": "12", "EffectiveBit Side": "Lower",
}


def write_mraw(tmp_path: Path, frames: np.ndarray, stored: bytes, **keys: str) -> Path:
    """A .cih (CIH_KEYS with ``keys`` over them; None drops a key) and its .mraw."""
    n, h, w = frames.shape
    fields = CIH_KEYS | {"Total Frame": str(n), "Image Width": str(w), "Image Height": str(h)}
    fields |= keys
    lines = ["#Camera Information Header"] + [f"{k} : {v}" for k, v in fields.items()
                                             if v is not None]
    cih = tmp_path / "rec.cih"
    cih.write_text("\n".join(lines + ["", "END", ""]))
    cih.with_suffix(".mraw").write_bytes(stored)
    return cih


def write_cine(path: Path, images: list[bytes], *, width: int, height: int, bit_count: int = 16,
               bi_compression: int = 0, real_bpp: int = 12, fps: int = 2000, compression: int = 0,
               cfa: int = 0, stamps: list[tuple[int, int]] | None = None) -> Path:
    """A cine: CINEFILEHEADER, BITMAPINFOHEADER, 1024-byte SETUP, TIME64 block, offsets, images."""
    n = len(images)
    setup = bytearray(1024)
    struct.pack_into("<H", setup, 0, min(fps, 65535))  # FrameRate16
    setup[140:142] = b"ST"
    struct.pack_into("<H", setup, 142, len(setup))  # Length
    struct.pack_into("<I", setup, 768, fps)  # FrameRate
    struct.pack_into("<I", setup, 808, cfa)  # CFA
    struct.pack_into("<I", setup, 896, real_bpp)  # RealBPP
    blocks = b""
    if stamps is not None:
        blocks = struct.pack("<IHH", 8 + 8 * n, 1002, 0) + b"".join(
            struct.pack("<II", frac, sec) for frac, sec in stamps)
    off_offsets = 44 + 40 + len(setup) + len(blocks)
    first = off_offsets + 8 * n
    pointers, body = [], b""
    for image in images:
        pointers.append(first + len(body))
        body += struct.pack("<II", 8, len(image)) + image  # annotation: its size, image size
    header = struct.pack("<2sHHHiIiIIIIII", b"CI", 44, compression, 1, -5, n, -5, n, 44, 84,
                         off_offsets, 1 << 31, 1_700_000_000)
    bitmap = struct.pack("<IiiHHIIiiII", 40, width, height, 1, bit_count, bi_compression,
                         len(images[0]), 0, 0, 0, 0)
    path.write_bytes(header + bitmap + bytes(setup) + blocks
                     + struct.pack(f"<{n}q", *pointers) + body)
    return path


def correlation(a: np.ndarray, b: np.ndarray) -> float:
    return float(np.corrcoef(a.ravel().astype(float), b.ravel().astype(float))[0, 1])


# -- the real samples ----------------------------------------------------------------------

@needs_data
def test_photron_sample_header_and_frames() -> None:
    cam = open_camera_file(CIH)
    assert isinstance(cam, PhotronMraw)
    assert (cam.frame_count, cam.width, cam.height) == (75, 640, 40) and len(cam) == 75
    assert cam.fps == 15000.0 and cam.frame_step == 100  # saved every 100th recorded frame
    assert cam.bit_depth == 8 and cam.dtype == np.uint8
    assert cam.first_frame_number == 0 and cam.trigger_mode == "Start"
    assert cam.header["Camera Type"].startswith("FASTCAM SA-Z")
    assert cam.time_s(3) == pytest.approx(3 * 100 / 15000) and cam.frame_interval_s == 100 / 15000
    assert cam.timestamps_s()[-1] == pytest.approx(74 * 100 / 15000)
    frames = [cam.read(i) for i in range(cam.frame_count)]
    assert all(f.shape == (40, 640) and f.dtype == np.uint8 for f in frames)
    stack = np.stack(frames)
    assert stack.std() > 30 and stack.min() < 10 and stack.max() > 200  # a real scene
    assert min(correlation(a, b) for a, b in zip(frames, frames[1:], strict=False)) > 0.95
    assert np.array_equal(cam.read(-1), frames[-1])


@needs_data
def test_phantom_sample_header_and_frames() -> None:
    cam = open_camera_file(CINE)
    assert isinstance(cam, PhantomCine)
    assert (cam.frame_count, cam.width, cam.height) == (235, 256, 32)
    assert cam.fps == 100.0 and cam.frame_step == 1
    assert cam.bit_depth == 10 and cam.dtype == np.uint16
    assert cam.header["biCompression"] == 256 and cam.header["RealBPP"] == 10  # 10-bit packed
    assert cam.first_frame_number == 0
    assert cam.trigger_time_posix == pytest.approx(1784894704.8256, abs=1e-3)
    frames = [cam.read(i) for i in range(cam.frame_count)]
    assert all(f.shape == (32, 256) and f.dtype == np.uint16 for f in frames)
    good = np.stack(frames[:234])
    # 10-bit codes (companded 12-bit data, up to about 2460 once linearised by Phantom's table)
    assert good.max() <= 1023 and 700 < np.percentile(good.reshape(234, -1).max(1), 50) < 1000
    assert good.std() > 50
    assert min(correlation(a, b) for a, b in zip(good, good[1:], strict=False)) > 0.99
    # The sample's last image is blank (every pixel code 1012) and its TIME64 stamp and
    # exposure are garbage: the stamps are set aside for index / fps.
    assert np.all(frames[234] == frames[234][0, 0])
    assert not cam.has_timestamps and "image 234" in cam.timestamps_note
    assert cam.time_s(234) == pytest.approx(2.34) and cam.timestamps_s()[10] == pytest.approx(0.1)


@needs_data
@pytest.mark.parametrize("sample", [CIH, CINE])
def test_reading_a_frame_touches_only_its_bytes(sample: Path, monkeypatch) -> None:
    cam = open_camera_file(sample)
    calls: list[tuple[int, int]] = []
    original = cam._read_bytes

    def spy(offset: int, size: int) -> bytes:
        calls.append((offset, size))
        return original(offset, size)

    monkeypatch.setattr(cam, "_read_bytes", spy)
    k = 17
    frame = cam.read(k)
    if isinstance(cam, PhotronMraw):
        nbytes = frame.size  # 8 bit
        assert calls == [(k * nbytes, nbytes)]
    else:
        start = int(cam._offsets[k])
        stop = start + 8 + cam.width * cam.height * 10 // 8  # annotation + 10-bit packed image
        assert all(start <= off and off + size <= stop for off, size in calls)
        assert sum(size for _, size in calls) <= stop - start + 4


def test_memory_stays_constant_on_a_large_mraw(tmp_path) -> None:
    n, h, w = 256, 128, 128  # an 8 MiB recording, 32 KiB a frame
    frames = np.zeros((n, h, w), np.uint16)
    frames[:, 0, 0] = np.arange(n)
    cih = write_mraw(tmp_path, frames, frames.astype("<u2").tobytes(), **{"Color Bit": "16"})
    cam = open_camera_file(cih)
    tracemalloc.start()
    try:
        for k in (0, 100, 255):
            assert cam.read(k)[0, 0] == k
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 4 * h * w * 2  # a few frames' worth, not the 8 MiB file


# -- synthetic Photron files -----------------------------------------------------------------

def test_unpack_bits_against_hand_packed_bytes() -> None:
    assert unpack_bits(bytes([0xAB, 0xC1, 0x23]), 12, 2).tolist() == [0xABC, 0x123]
    # 10 bit: 1111111111 0000000000 0101010101 1010101010 -> FF C0 05 56 AA
    assert unpack_bits(bytes([0xFF, 0xC0, 0x05, 0x56, 0xAA]), 10, 4).tolist() == [
        0x3FF, 0, 0x155, 0x2AA]


def test_mraw_12bit_packed_reads_back_exactly(tmp_path) -> None:
    rng = np.random.default_rng(3)
    frames = rng.integers(0, 4096, (3, 4, 6)).astype(np.uint16)
    frames[0, 0, :2] = (4095, 0)
    cih = write_mraw(tmp_path, frames, pack_msb(frames, 12), **{"Color Bit": "12"})
    cam = open_camera_file(cih)
    assert cam.bit_depth == 12 and cam.dtype == np.uint16
    assert cam.first_frame_number == -2 and cam.fps == 5000.0 and cam.frame_step == 1
    for i in range(3):
        assert np.array_equal(cam.read(i), frames[i])
    assert cam.timestamps_s() == pytest.approx([0, 2e-4, 4e-4])


@pytest.mark.parametrize(("order", "side", "depth"), [("<", "Lower", 12), (">", "Lower", 12),
                                                      ("<", "Higher", 16)])
def test_mraw_16bit_reads_back_exactly(tmp_path, order: str, side: str, depth: int) -> None:
    rng = np.random.default_rng(4)
    frames = rng.integers(0, 4096, (2, 5, 7)).astype(np.uint16)
    if side == "Higher":
        frames <<= 4  # the 12 effective bits sit at the top of the 16-bit word
    cih = write_mraw(tmp_path, frames, frames.astype(order + "u2").tobytes(),
                     **{"Color Bit": "16", "EffectiveBit Side": side})
    cam = PhotronMraw(cih, byteorder=order)
    assert cam.bit_depth == depth and cam.dtype == np.uint16
    assert np.array_equal(cam.read(1), frames[1]) and cam.read(1).dtype.isnative


def test_mraw_8bit_reads_back_exactly(tmp_path) -> None:
    frames = np.arange(3 * 4 * 6, dtype=np.uint8).reshape(3, 4, 6)
    cam = open_camera_file(write_mraw(tmp_path, frames, frames.tobytes()))
    assert cam.bit_depth == 8 and cam.dtype == np.uint8  # EffectiveBit 12 > 8 stored bits
    assert np.array_equal(cam.read(2), frames[2])
    with pytest.raises(IndexError, match="outside rec.cih's 3 frames"):
        cam.read(3)
    with pytest.raises(IndexError):
        cam.read(-4)


def test_cihx_xml_header_after_binary_preamble(tmp_path) -> None:
    frames = np.arange(2 * 4 * 6, dtype=np.uint16).reshape(2, 4, 6) * 50
    xml = ("<cih><fileInfo><date>2024/01/02</date></fileInfo>"
           "<recordInfo><recordRate>20000</recordRate></recordInfo>"
           "<frameInfo><totalFrame>2</totalFrame><startFrame>7</startFrame></frameInfo>"
           "<imageDataInfo><resolution><width>6</width><height>4</height></resolution>"
           "<colorInfo><type>Mono</type><bit>16</bit></colorInfo>"
           "<effectiveBit><depth>12</depth><side>Lower</side></effectiveBit></imageDataInfo>"
           "<imageFileInfo><fileFormat>MRaw</fileFormat></imageFileInfo></cih>")
    cihx = tmp_path / "rec.cihx"
    cihx.write_bytes(b"\x00\x01\xfe\xffbinary preamble\x00" + xml.encode())
    cihx.with_suffix(".mraw").write_bytes(frames.astype("<u2").tobytes())
    cam = open_camera_file(cihx)
    assert (cam.fps, cam.frame_count, cam.width, cam.height) == (20000.0, 2, 6, 4)
    assert cam.bit_depth == 12 and cam.first_frame_number == 7
    assert np.array_equal(cam.read(1), frames[1])
    (tmp_path / "bad.cihx").write_bytes(b"\x00\x01 no xml here")
    with pytest.raises(InputError, match="no <cih>"):
        open_camera_file(tmp_path / "bad.cihx")


# -- Photron errors ----------------------------------------------------------------------------

@needs_data
def test_truncated_mraw_says_how_many_frames_are_complete(tmp_path) -> None:
    shutil.copy(CIH, tmp_path / "cut.cih")
    data = CIH.with_suffix(".mraw").read_bytes()
    (tmp_path / "cut.mraw").write_bytes(data[:12 * 640 * 40 + 100])
    with pytest.raises(InputError, match=r"cut.mraw is truncated: .* hold 12 complete frames "
                                         r"of the 75 that cut.cih declares"):
        open_camera_file(tmp_path / "cut.cih")


@needs_data
def test_missing_mraw_beside_the_cih(tmp_path) -> None:
    shutil.copy(CIH, tmp_path / "alone.cih")
    with pytest.raises(InputError, match="alone.mraw is missing beside alone.cih"):
        open_camera_file(tmp_path / "alone.cih")


@pytest.mark.parametrize(("keys", "message"), [
    ({"Image Width": None, "Record Rate(fps)": None},
     "lacks the header keys 'Record Rate\\(fps\\)', 'Image Width'"),
    ({"Color Bit": "10"}, "Color Bit 10 is not supported"),
    ({"Color Type": "Color"}, "colour recordings are not supported"),
    ({"File Format": "TIFF"}, "File Format 'TIFF' is not supported"),
    ({"Record Rate(fps)": "fast"}, "'Record Rate\\(fps\\)' is 'fast', not a number"),
    ({"Total Frame": "2.5"}, "not a whole number"),
    ({"Save Step": "0"}, "Save Step is 0"),
])
def test_bad_cih_headers(tmp_path, keys: dict, message: str) -> None:
    frames = np.zeros((3, 4, 6), np.uint8)
    with pytest.raises(InputError, match=message):
        open_camera_file(write_mraw(tmp_path, frames, frames.tobytes(), **keys))


def test_suffixes(tmp_path) -> None:
    assert open_camera_file(tmp_path / "clip.mp4") is None
    assert open_camera_file(tmp_path / "frames") is None
    with pytest.raises(InputError, match="does not exist"):
        open_camera_file(tmp_path / "gone.CINE")
    with pytest.raises(InputError, match="does not exist"):
        open_camera_file(tmp_path / "gone.cih")


# -- synthetic Phantom files -------------------------------------------------------------------

def test_cine_uncompressed_16bit_is_stored_bottom_up(tmp_path) -> None:
    rng = np.random.default_rng(5)
    frames = rng.integers(0, 16384, (3, 4, 6)).astype(np.uint16)
    images = [f[::-1].astype("<u2").tobytes() for f in frames]  # DIB order: bottom row first
    stamps = [(int(i * 2**32 / 2000) & ~3, 1_700_000_000) for i in range(3)]
    cam = open_camera_file(write_cine(tmp_path / "a.cine", images, width=6, height=4,
                                      real_bpp=14, stamps=stamps))
    assert (cam.width, cam.height, cam.frame_count, cam.fps) == (6, 4, 3, 2000.0)
    assert cam.bit_depth == 14 and cam.dtype == np.uint16 and cam.first_frame_number == -5
    assert cam.has_timestamps and cam.timestamps_s() == pytest.approx([0, 5e-4, 1e-3], abs=1e-9)
    assert cam.trigger_time_posix == pytest.approx(1_700_000_000.5)
    for i in range(3):
        assert np.array_equal(cam.read(i), frames[i])


def test_cine_8bit_top_down_and_packed_12bit(tmp_path) -> None:
    frames8 = np.arange(2 * 4 * 8, dtype=np.uint8).reshape(2, 4, 8)
    cam = open_camera_file(write_cine(tmp_path / "b.cine", [f.tobytes() for f in frames8],
                                      width=8, height=-4, bit_count=8))
    assert cam.bit_depth == 8 and cam.dtype == np.uint8 and not cam.has_timestamps
    assert np.array_equal(cam.read(1), frames8[1]) and cam.time_s(1) == pytest.approx(5e-4)
    frames12 = np.random.default_rng(6).integers(0, 4096, (2, 4, 6)).astype(np.uint16)
    cam = open_camera_file(write_cine(tmp_path / "c.cine", [pack_msb(f, 12) for f in frames12],
                                      width=6, height=4, bi_compression=1024))
    assert cam.bit_depth == 12 and np.array_equal(cam.read(1), frames12[1])


def test_cine_packed_10bit_codes_read_back_as_stored(tmp_path) -> None:
    codes = np.array([[0, 1, 15, 511], [512, 1008, 1014, 1023]], np.uint16)
    cam = open_camera_file(write_cine(tmp_path / "d.cine", [pack_msb(codes, 10)], width=4,
                                      height=2, bi_compression=256, real_bpp=10))
    assert cam.bit_depth == 10 and cam.dtype == np.uint16
    assert cam.read(0).tolist() == codes.tolist()


# -- Phantom errors ----------------------------------------------------------------------------

def small_cine(tmp_path: Path, **kwargs) -> Path:
    frames = np.zeros((2, 4, 6), np.uint16)
    return write_cine(tmp_path / "e.cine", [f.tobytes() for f in frames], width=6, height=4,
                      **kwargs)


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"compression": 1}, "compressed \\(JPEG\\) cine, which is not supported"),
    ({"bi_compression": 2}, "biCompression\\) 2 is not supported"),
    ({"cfa": 3}, "colour recording"),
    ({"bit_count": 24}, "colour recording"),
    ({"bit_count": 12}, "12 bits per pixel is not supported"),
    ({"fps": 0}, "no frame rate"),
])
def test_unsupported_cines(tmp_path, kwargs: dict, message: str) -> None:
    with pytest.raises(InputError, match=message):
        open_camera_file(small_cine(tmp_path, **kwargs))


def test_cine_bad_magic_and_offsets_beyond_the_file(tmp_path) -> None:
    path = small_cine(tmp_path)
    data = bytearray(path.read_bytes())
    (tmp_path / "magic.cine").write_bytes(b"XX" + data[2:])
    with pytest.raises(InputError, match="magic 'CI'"):
        open_camera_file(tmp_path / "magic.cine")
    struct.pack_into("<I", data, 32, len(data) + 100)  # OffImageOffsets
    (tmp_path / "offsets.cine").write_bytes(data)
    with pytest.raises(InputError, match="image offset array at bytes .* beyond the file"):
        open_camera_file(tmp_path / "offsets.cine")
    (tmp_path / "tiny.cine").write_bytes(data[:20])
    with pytest.raises(InputError, match="shorter than a cine header"):
        open_camera_file(tmp_path / "tiny.cine")


@needs_data
def test_truncated_cine_says_how_many_images_are_complete(tmp_path) -> None:
    data = CINE.read_bytes()
    first, step = 14144, 8 + 10240  # this sample: images back to back behind 8-byte annotations
    cut = first + 116 * step + 5000
    (tmp_path / "cut.cine").write_bytes(data[:cut])
    with pytest.raises(InputError, match="cut.cine is truncated: 116 of its 235 images"):
        open_camera_file(tmp_path / "cut.cine")
    (tmp_path / "head.cine").write_bytes(data[:5000])  # cut inside the SETUP
    with pytest.raises(InputError, match="beyond the file's 5000 bytes"):
        open_camera_file(tmp_path / "head.cine")
