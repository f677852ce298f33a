"""Frame input, ROI and POI masks."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flow.io.errors import InputError
from flow.io.frames import (
    HISTORY_SHARE,
    Roi,
    as_uint8,
    copied_share,
    deep_image_gain,
    significant_bits,
)
from flow.io.source import open_source
from flow.measure.poi import load_mask, poi_coordinates, polygon_mask, rect_mask


def test_roi_parse_and_bounds() -> None:
    roi = Roi.parse("10,20,30,40")
    assert roi == Roi(10, 20, 30, 40)
    roi.check(40, 60)
    with pytest.raises(InputError, match="outside the 39x60 frame"):
        roi.check(39, 60)
    with pytest.raises(InputError, match="X,Y,W,H"):
        Roi.parse("1,2,3")


def test_image_folder_streams_grey_roi_with_fps_timestamps(tmp_path) -> None:
    for i in range(3):
        image = np.full((30, 40, 3), 10 * i, np.uint8)
        image[5, 7] = (255, 255, 255)
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), image)
    source = open_source(tmp_path, roi=Roi(7, 5, 10, 8), fps=25.0)
    frames = list(source)
    assert [f[0] for f in frames] == [0, 1, 2]
    assert [f[1] for f in frames] == pytest.approx([0, 0.04, 0.08])
    assert frames[1][2].shape == (8, 10) and frames[1][2].dtype == np.uint8
    assert frames[1][2][0, 0] == 255 and frames[1][2][1, 1] == 10
    assert source.frames_read == 3 and not source.truncated


def test_a_mask_drawn_on_a_transparent_layer_is_what_is_opaque(tmp_path) -> None:
    """Masks saved from an image editor's transparent layer: the transparent pixels are not the
    mask whatever their colour (white under them selected the whole frame before), labels keep
    their grey values, and a mask without transparency reads as before. Black paint on a
    transparent layer selects nothing (is the paint the member, or the rest?): refused as an
    empty mask, as before."""
    roi = Roi(0, 0, 50, 40)
    drawn = np.zeros((40, 50), bool)
    drawn[12:15, 11:16] = True
    cases = {
        "white_under": (np.dstack([np.full((40, 50), 255, np.uint8)] * 3 + [drawn.astype(np.uint8) * 255]), drawn),
        "opaque": (np.dstack([drawn.astype(np.uint8) * 255] * 3 + [np.full((40, 50), 255, np.uint8)]), drawn),
    }
    for name, (image, expected) in cases.items():
        cv2.imwrite(str(tmp_path / f"{name}.png"), image)
        notes: list[str] = []
        mask = load_mask(tmp_path / f"{name}.png", frame_size=(50, 40), roi=roi, notes=notes)
        assert np.array_equal(mask, expected), name
        assert any("transparent pixels" in note for note in notes) == (name != "opaque"), (name, notes)
    labels = np.zeros((40, 50), np.uint8)
    labels[2:6, 2:6], labels[20:25, 30:40] = 1, 2
    alpha = np.full((40, 50), 255, np.uint8)
    alpha[20:25, 30:35] = 0
    cv2.imwrite(str(tmp_path / "labels.png"), np.dstack([labels] * 3 + [alpha]))
    read = load_mask(tmp_path / "labels.png", frame_size=(50, 40), roi=roi, labels=True)
    assert (read == 1).sum() == 16 and (read == 2).sum() == 25 and not read[20:25, 30:35].any()
    cv2.imwrite(str(tmp_path / "black.png"), np.dstack([np.zeros((40, 50), np.uint8)] * 3 + [drawn.astype(np.uint8) * 255]))
    assert not load_mask(tmp_path / "black.png", frame_size=(50, 40), roi=roi).any()
    from PIL import Image

    turned = Image.Exif()
    turned[0x0112] = 3  # EXIF orientation: turned by 180 degrees
    Image.fromarray(cases["white_under"][0][..., [2, 1, 0, 3]], "RGBA").save(tmp_path / "turned.png", exif=turned.tobytes())
    with pytest.raises(InputError, match="mask turned.png has an EXIF orientation tag as well as transparent pixels"):
        load_mask(tmp_path / "turned.png", frame_size=(50, 40), roi=roi)



def test_a_sixteen_bit_mask_of_labels_is_read_by_its_values(tmp_path) -> None:
    """Labelling tools save labels 1, 2, ... as 16-bit PNGs; OpenCV's grey read keeps their
    high byte (0), and such a mask was refused as selecting nothing. 0/1 and 0/255 masks read
    as one region; a full-range 16-bit mask (0/65535) as before."""
    roi = Roi(0, 0, 50, 40)
    labels = np.zeros((40, 50), np.uint16)
    labels[2:6, 2:6], labels[20:25, 30:40] = 1, 2
    cv2.imwrite(str(tmp_path / "labels16.png"), labels)
    read = load_mask(tmp_path / "labels16.png", frame_size=(50, 40), roi=roi, labels=True)
    assert (read == 1).sum() == 16 and (read == 2).sum() == 50
    for top in (1, 255, 65535):
        cv2.imwrite(str(tmp_path / f"binary{top}.png"), (labels > 0).astype(np.uint16) * top)
        assert (load_mask(tmp_path / f"binary{top}.png", frame_size=(50, 40), roi=roi, labels=True) == 1).sum() == 66, top


def test_masks_full_size_roi_size_rect_polygon_and_grid(tmp_path) -> None:
    roi = Roi(10, 10, 20, 10)
    full = np.zeros((40, 50), np.uint8)
    full[12:15, 11:16] = 255
    cv2.imwrite(str(tmp_path / "full.png"), full)
    cv2.imwrite(str(tmp_path / "roi.png"), full[10:20, 10:30])
    cv2.imwrite(str(tmp_path / "bad.png"), full[:7, :9])
    a = load_mask(tmp_path / "full.png", frame_size=(50, 40), roi=roi)
    b = load_mask(tmp_path / "roi.png", frame_size=(50, 40), roi=roi)
    assert a.shape == (10, 20) and (a == b).all() and a.sum() == 15
    with pytest.raises(InputError, match="mask is 9x7 but frames are 50x40"):
        load_mask(tmp_path / "bad.png", frame_size=(50, 40), roi=roi)
    assert (rect_mask("11,12,5,3", roi=roi) == a).all()
    assert polygon_mask("10,10,29,10,29,19", roi=roi).sum() > 50
    assert len(poi_coordinates(a)) == 15
    assert len(poi_coordinates(a, grid_step=2)) == 4  # rows 2, 4 x cols 2, 4 of the ROI
    with pytest.raises(InputError, match="selects no pixel"):
        poi_coordinates(np.zeros((4, 4), bool))


def test_frame_ranges_and_fps_checks(tmp_path) -> None:
    for i in range(5):
        cv2.imwrite(str(tmp_path / f"{i:02d}.png"), np.full((6, 8), 40 * i, np.uint8))
    source = open_source(tmp_path, fps=10.0)
    picked = list(source.frames(1, 4))
    assert [f[0] for f in picked] == [1, 2, 3]
    assert [f[1] for f in picked] == pytest.approx([0.1, 0.2, 0.3])
    assert [int(f[2][0, 0]) for f in picked] == [40, 80, 120]
    assert [f[0] for f in source.frames(3)] == [3, 4]
    with pytest.raises(InputError, match="pass --fps"):
        open_source(tmp_path)
    assert [f[1] for f in open_source(tmp_path, require_fps=False)] == [0, 1, 2, 3, 4]
    for bad in (0.0, -5.0, float("nan")):
        with pytest.raises(InputError, match="is not a finite positive number"):
            open_source(tmp_path, fps=bad)


def test_video_fps_is_checked_too_and_ranges_skip_decoding(tmp_path) -> None:
    video = tmp_path / "v.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 25.0, (16, 12), True)
    for i in range(6):
        writer.write(np.full((12, 16, 3), 40 * i, np.uint8))
    writer.release()
    with pytest.raises(InputError, match="--fps -1.0 is not a finite positive number"):
        open_source(video, fps=-1.0)
    source = open_source(video)
    picked = list(source.frames(2, 5))
    assert [f[0] for f in picked] == [2, 3, 4]
    assert [f[1] for f in picked] == pytest.approx([0.08, 0.12, 0.16])
    assert abs(int(picked[0][2].mean()) - 80) <= 3
    assert not source.truncated  # stopped early: nothing to judge


def test_sixteen_bit_images_are_measured_at_full_depth(tmp_path) -> None:
    """12-bit data in 16-bit images comes out on the 8-bit grey scale but not rounded to it:
    value x gain exactly, as float32; 8-bit images stay uint8; the data's bits are recorded."""
    rng = np.random.default_rng(3)
    first = rng.integers(1000, 3000, (12, 16)).astype(np.uint16)
    first[0, 0] = 4000  # 12-bit data: 4000 < 4096
    cv2.imwrite(str(tmp_path / "a.png"), first)
    cv2.imwrite(str(tmp_path / "b.png"), first + np.uint16(1))  # one count brighter
    source = open_source(tmp_path, fps=10.0)
    frames = [grey for _, _, grey in source]
    gain = np.float32(deep_image_gain(first))
    assert source.bit_depth == 12
    assert frames[0].dtype == np.float32
    assert np.array_equal(frames[0], first.astype(np.float32) * gain)
    # One count of 12-bit data is 0.05 grey levels here: kept, where 8 bits would lose it.
    assert np.allclose(frames[1] - frames[0], gain, rtol=1e-3)
    eight = tmp_path / "eight"
    eight.mkdir()
    cv2.imwrite(str(eight / "a.png"), (first >> 4).astype(np.uint8))
    source = open_source(eight, fps=10.0)
    assert source.bit_depth == 8 and next(iter(source))[2].dtype == np.uint8


@pytest.mark.parametrize("dtype, scale", [(np.float32, 1 / 255), (np.float64, 3.7), (np.int32, 1000)])
def test_floating_point_and_32_bit_images_are_measured_at_full_depth(tmp_path, dtype, scale) -> None:
    """Floating-point TIFFs (0-1 from most DIC tools, any unit from others) and 32-bit integer
    ones get one gain to the 8-bit grey scale, like 16-bit data, and stay float32. Before, they
    were clipped to 0-255: 0-1 data read as a uniform grey 0 and the run was refused."""
    rng = np.random.default_rng(4)
    first = (rng.uniform(40, 200, (12, 16)) * scale).astype(dtype)
    second = (first * dtype(1.01)).astype(dtype) if dtype != np.int32 else first + 7
    cv2.imwrite(str(tmp_path / "a.tif"), first)
    cv2.imwrite(str(tmp_path / "b.tif"), second)
    source = open_source(tmp_path, fps=10.0)
    frames = [grey for _, _, grey in source]
    gain = deep_image_gain(first)
    assert source.bit_depth == 24 and frames[0].dtype == np.float32
    assert np.allclose(frames[0], first * gain, rtol=1e-6) and np.allclose(frames[1], second * gain, rtol=1e-6)
    assert 180 < np.percentile(frames[0], 99.9) < 230
    assert any(note.startswith(f"{8 * np.dtype(dtype).itemsize}-bit") for note in source.notes)


def test_not_a_number_in_an_image_stops_the_run_naming_the_image(tmp_path) -> None:
    image = np.random.default_rng(5).uniform(0.2, 0.8, (12, 16)).astype(np.float32)
    cv2.imwrite(str(tmp_path / "a.tif"), image)
    image[3, 4] = np.nan
    image[5, 6] = np.inf
    cv2.imwrite(str(tmp_path / "b.tif"), image)
    source = open_source(tmp_path, fps=10.0)
    with pytest.raises(InputError, match=r"image b\.tif holds 2 NaN or infinite pixel\(s\) in the area read "
                                         r"\(the first at x=4, y=3\): pass an --roi that leaves them out"):
        list(source)
    assert len(list(open_source(tmp_path, fps=10.0, roi=Roi(8, 0, 8, 12)))) == 2  # an ROI without them


def test_an_image_of_another_pixel_type_than_the_first_stops_the_run(tmp_path) -> None:
    """One gain from the first image serves every frame only if all share its pixel type: a
    0-1 float frame after 16-bit ones came out as grey 0.03."""
    cv2.imwrite(str(tmp_path / "a.png"), np.full((6, 8), 3000, np.uint16))
    cv2.imwrite(str(tmp_path / "b.tif"), np.full((6, 8), 0.5, np.float32))
    with pytest.raises(InputError, match="image b.tif holds float32 pixels but the first holds uint16"):
        list(open_source(tmp_path, fps=10.0))


def test_numbered_images_are_read_in_their_numbers_order(tmp_path) -> None:
    """Names numbered without zero padding (frame1 ... frame12): frame10 comes after frame9, not
    after frame1 (a plain name sort scrambled the time series and said nothing); padded names
    keep their order. Hidden files (macOS's "._" companions) are not frames."""
    for i in range(1, 13):
        cv2.imwrite(str(tmp_path / f"frame{i}.png"), np.full((6, 8), 10 * i, np.uint8))
    (tmp_path / "._frame1.png").write_bytes(b"\0\5\26\7" + bytes(100))  # macOS's resource fork: hidden
    source = open_source(tmp_path, fps=10.0)
    assert [int(grey.mean()) for _, _, grey in source] == [10 * i for i in range(1, 13)]
    assert not any("numbers" in note for note in source.notes)


@pytest.mark.parametrize("numbers, said", [((0, 2, 4, 6), "go up by 2"), ((1, 2, 4, 5), "skip 1 value(s) (first after f2.png"),
                                           ((1, 2, 3, 4), None)])
def test_images_whose_numbers_do_not_go_up_by_one_are_noted(tmp_path, numbers, said) -> None:
    for n in numbers:
        cv2.imwrite(str(tmp_path / f"f{n}.png"), np.full((6, 8), 80, np.uint8))
    notes = [note for note in open_source(tmp_path, fps=10.0).notes if "numbers" in note]
    assert (notes == []) if said is None else (len(notes) == 1 and said in notes[0]), notes


_STACKS = {  # name: (dtype, top value, colour, how it is written)
    "opencv-8-bit": (np.uint8, 255, False, "opencv"),  # OpenCV writes LZW: decoded by Pillow
    "opencv-16-bit": (np.uint16, 4000, False, "opencv"),
    "opencv-colour": (np.uint8, 255, True, "opencv"),
    "float32": (np.float32, 1, False, "tifffile"),
    "float64": (np.float64, 1, False, "tifffile"),
    "uint32": (np.uint32, 4_000_000_000, False, "tifffile"),
    "16-bit-colour": (np.uint16, 60000, True, "tifffile"),
    "big-endian-bigtiff": (np.uint16, 4000, False, "bigtiff"),
    "imagej-over-4-GB": (np.uint16, 4000, False, "imagej-truncate"),  # one page listed, images=N
    "zlib": (np.uint16, 4000, False, "zlib"),
}


@pytest.mark.parametrize("kind", sorted(_STACKS))
def test_a_tiff_stack_is_read_frame_by_frame(tmp_path, kind) -> None:
    """A multi-page TIFF (ImageJ's, a scientific camera's) is one frame per page, read as the
    same frames saved as a folder of images read (OpenCV's video reader took its first page
    only: one frame, nothing said). Its frames carry no time stamps: --fps is asked for."""
    import tifffile

    dtype, top, colour, how = _STACKS[kind]
    rng = np.random.default_rng(6)
    pages = rng.uniform(0, top, (5, 12, 16, 3) if colour else (5, 12, 16)).astype(dtype)
    stack = tmp_path / "stack.tif"
    if how == "opencv":
        assert cv2.imwritemulti(str(stack), list(pages))
    else:
        extra = {"tifffile": {}, "bigtiff": {"bigtiff": True, "byteorder": ">"}, "zlib": {"compression": "zlib"},
                 "imagej-truncate": {"imagej": True, "truncate": True}}[how]
        rgb = pages[..., ::-1] if colour else pages  # stored RGB, as OpenCV's BGR turned
        tifffile.imwrite(stack, rgb, photometric="rgb" if colour else "minisblack", **extra)
    folder = tmp_path / "folder"
    folder.mkdir()
    for i, page in enumerate(pages):
        cv2.imwrite(str(folder / f"{i}.tif"), page)
    source = open_source(stack, fps=10.0)
    from PIL import Image

    opened = []
    with pytest.MonkeyPatch.context() as patch:  # pages read in turn: the file opened once, not per page
        patch.setattr(Image, "open", lambda *a, _open=Image.open, **k: opened.append(a) or _open(*a, **k))
        frames = [(t, grey) for _, t, grey in source]
    assert len(opened) <= 1
    twins = [grey for _, _, grey in open_source(folder, fps=10.0)]
    assert type(source).__name__ == "TiffStackSource" and source.header_frames == 5 and source.lossless
    assert np.allclose([t for t, _ in frames], [0.0, 0.1, 0.2, 0.3, 0.4])
    assert all(np.array_equal(grey, twin) for (_, grey), twin in zip(frames, twins, strict=True)), kind
    assert source.bit_depth == source.bit_depth and (source.bit_depth > 8) == (dtype != np.uint8)
    with pytest.raises(InputError, match="TIFF stack of images without timestamps: pass --fps"):
        open_source(stack)


def test_a_tiff_stack_cut_short_or_of_mixed_pages_is_refused_before_the_first_frame(tmp_path) -> None:
    pages = [np.full((12, 16), 40 * i, np.uint8) for i in range(4)]
    whole = tmp_path / "whole.tif"
    cv2.imwritemulti(str(whole), pages)
    for cut in (10, 200):
        (tmp_path / "cut.tif").write_bytes(whole.read_bytes()[:-cut])
        with pytest.raises(InputError, match="lies past the file's end"):
            open_source(tmp_path / "cut.tif", fps=10.0)
    cv2.imwritemulti(str(tmp_path / "mixed.tif"), [pages[0], np.zeros((10, 16), np.uint8)])
    with pytest.raises(InputError, match="page 1 of mixed.tif is 16x10 uint8 but the first is 16x12 uint8"):
        open_source(tmp_path / "mixed.tif", fps=10.0)
    cv2.imwrite(str(tmp_path / "one.tif"), pages[1])  # one page: an image, read as before
    assert type(open_source(tmp_path / "one.tif")).__name__ == "VideoSource"
    import tifffile

    tifffile.imwrite(tmp_path / "imagej.tif", np.zeros((5, 12, 16), np.uint16), imagej=True, truncate=True)
    (tmp_path / "imagej_cut.tif").write_bytes((tmp_path / "imagej.tif").read_bytes()[:-100])
    with pytest.raises(InputError, match="lists 5 ImageJ images but holds 1"):
        open_source(tmp_path / "imagej_cut.tif", fps=10.0)
    tifffile.imwrite(tmp_path / "hyper.tif", np.zeros((3, 2, 12, 16), np.uint8), imagej=True,
                     metadata={"axes": "TCYX"})
    with pytest.raises(InputError, match="hyper.tif is a hyperstack"):
        open_source(tmp_path / "hyper.tif", fps=10.0)


def test_images_are_measured_as_shown_under_their_exif_orientation(tmp_path) -> None:
    """A portrait photo is stored landscape with an EXIF orientation; a viewer shows it turned,
    and its mask and --rect are drawn on what is shown. The folder's frames are turned so
    (before, they were measured as stored, and a mask drawn on the shown image was refused as
    mis-sized); each orientation matches what OpenCV's and Pillow's readers show."""
    from PIL import Image, ImageOps

    rng = np.random.default_rng(7)
    stored = rng.integers(0, 255, (12, 20)).astype(np.uint8)
    for tag in range(1, 9):
        folder = tmp_path / str(tag)
        folder.mkdir()
        exif = Image.Exif()
        exif[0x0112] = tag
        for i in range(2):
            Image.fromarray(stored).save(folder / f"f{i}.png", exif=exif.tobytes())
        source = open_source(folder, fps=10.0)
        with Image.open(folder / "f0.png") as image:
            shown = np.asarray(ImageOps.exif_transpose(image))
        assert np.array_equal(next(iter(source))[2], shown), tag
        assert (source.width, source.height) == (shown.shape[1], shown.shape[0])
        assert source.rotation_deg == {3: 180, 6: 90, 8: 270}.get(tag, 0)
        assert any("EXIF orientation" in note for note in source.notes) == (tag != 1)


def test_as_uint8_and_significant_bits() -> None:
    image = np.array([[-3.0, 0.4, 0.6], [254.5, 255.2, 900.0]], np.float32)
    assert as_uint8(image).tolist() == [[0, 0, 1], [254, 255, 255]]
    eight = np.zeros((2, 2), np.uint8)
    assert as_uint8(eight) is eight
    assert significant_bits(np.array([0, 255], np.uint16)) == 8
    assert significant_bits(np.array([0, 1023], np.uint16)) == 10
    assert significant_bits(np.array([0, 2460], np.uint16)) == 12
    assert significant_bits(np.array([0, 65535], np.uint16)) == 16


def _png_with_a_checksum_error(path) -> None:
    data = bytearray(cv2.imencode(".png", np.full((6, 8), 90, np.uint8))[1].tobytes())
    data[data.index(b"IDAT") + 6] ^= 0xFF  # a byte of the image data: its chunk's CRC no longer matches
    path.write_bytes(bytes(data))


def _png_with_undecodable_data(path) -> None:
    """A PNG whose chunks are sound (checksums match: Pillow's check passes) but whose image
    data is not zlib: only decoding finds it, and libpng prints its error on fd 2."""
    import zlib

    data = cv2.imencode(".png", np.full((6, 8), 90, np.uint8))[1].tobytes()
    start = data.index(b"IDAT") - 4
    length = int.from_bytes(data[start:start + 4], "big")
    garbage = bytes(range(7, 7 + length))
    chunk = b"IDAT" + garbage
    path.write_bytes(data[:start + 4] + chunk + zlib.crc32(chunk).to_bytes(4, "big") + data[start + 12 + length:])


def _cut(path, keep: float) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _tiff_with_a_broken_directory(path, samples: int | None = None, entries: int | None = None) -> None:
    """A TIFF from OpenCV (directory last) with one field of its directory overwritten."""
    data = bytearray(cv2.imencode(".tif", np.full((6, 8), 90, np.uint8))[1].tobytes())
    ifd = int.from_bytes(data[4:8], "little")
    count = int.from_bytes(data[ifd:ifd + 2], "little")
    if entries is not None:
        data[ifd:ifd + 2] = (count + entries).to_bytes(2, "little")  # Pillow: "Corrupt EXIF data"
    for i in range(count if samples is not None else 0):
        entry = ifd + 2 + 12 * i
        if int.from_bytes(data[entry:entry + 2], "little") == 277:  # SamplesPerPixel
            data[entry + 8:entry + 12] = samples.to_bytes(4, "little")  # Pillow logs an error
    path.write_bytes(bytes(data))


def _damage(folder, problem: str):
    """Damage the third of five 8x6 images in ``folder``; return (name, message expected)."""
    name = "f2.png"
    if problem == "png checksum error":  # Pillow raises SyntaxError
        _png_with_a_checksum_error(folder / name)
        return name, "bad header checksum in b'IDAT'"
    if problem == "png short of its last byte":  # Pillow's check stops before IEND's checksum
        cv2.imwrite(str(folder / name), np.full((6, 8), 90, np.uint8))
        (folder / name).write_bytes((folder / name).read_bytes()[:-1])
        return name, "the PNG's end chunk (IEND) is missing or broken"
    if problem == "truncated jpeg":  # decodes, grey-padded, with only a libjpeg warning
        name = "f2.jpg"
        noise = np.random.default_rng(0).integers(0, 255, (6, 8)).astype(np.uint8)
        cv2.imwrite(str(folder / name), noise, [cv2.IMWRITE_JPEG_QUALITY, 100])
        _cut(folder / name, 0.95)
        return name, "truncated: the JPEG data has no end marker"
    if problem == "jpeg with a bogus table":  # Pillow reads its header; libjpeg cannot decode it
        name = "f2.jpg"
        noise = np.random.default_rng(0).integers(0, 255, (6, 8)).astype(np.uint8)
        data = bytearray(cv2.imencode(".jpg", noise)[1].tobytes())
        at = data.index(b"\xff\xc4")  # the first Huffman table (DHT)
        data[at + 5:at + 21] = b"\xff" * 16  # its 16 code counts: far more codes than exist
        (folder / name).write_bytes(bytes(data))
        return name, "damaged: libjpeg cannot read it"
    if problem == "truncated tiff":  # directory first (Pillow's layout), strips cut off
        name = "f2.tif"
        from PIL import Image

        Image.fromarray(np.full((6, 8), 90, np.uint8)).save(folder / name)
        _cut(folder / name, 0.9)
        return name, "TIFF image data lies beyond the end of the file"
    if problem == "tiff Pillow cannot identify":  # Pillow logs, OpenCV cannot decode it either
        name = "f2.tif"
        _tiff_with_a_broken_directory(folder / name, samples=45825)
        return name, "cannot be read"
    if problem == "not an image":
        (folder / name).write_bytes(b"\x00\x05\x16\x07 AppleDouble")  # macOS's ._ files
        return name, "not an image Pillow or OpenCV can read"
    raise AssertionError(problem)


@pytest.mark.parametrize("problem", ["png checksum error", "png short of its last byte", "truncated jpeg",
                                     "jpeg with a bogus table", "truncated tiff", "tiff Pillow cannot identify",
                                     "not an image"])
def test_a_damaged_image_anywhere_is_refused_when_the_folder_is_opened(tmp_path, capfd, caplog,
                                                                       problem) -> None:
    """Found by the folder scan, before any frame is read, in one line: no Pillow warning or log
    record, nothing the decoders print."""
    import warnings

    for i in range(5):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((6, 8), 90, np.uint8))
    (tmp_path / "f2.png").unlink()
    name, expected = _damage(tmp_path, problem)
    with warnings.catch_warnings(record=True) as shown, pytest.raises(InputError) as refused:
        warnings.simplefilter("always")
        open_source(tmp_path, fps=10.0)
    message = str(refused.value)
    assert name in message and expected in message and "\n" not in message, message
    assert not shown and not [r for r in caplog.records if r.name.startswith("PIL")]
    assert capfd.readouterr().err == ""


def test_the_folder_scan_keeps_sound_files_and_skips_subfolders(tmp_path, caplog) -> None:
    """A JPEG padded with zeros after its end marker (some cameras) is sound, and so is one whose
    EXIF holds a thumbnail (markers of its own); a folder named like an image is no frame."""
    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.jpg"), np.full((6, 8), 90, np.uint8))
    padded = tmp_path / "f1.jpg"
    padded.write_bytes(padded.read_bytes() + b"\0" * 300)
    exif = tmp_path / "f2.jpg"  # an EXIF segment holding a thumbnail: markers of its own, SOS included
    thumbnail = b"Exif\0\0" + b"\xff\xd8\xff\xdb\x00\x04\x00\x00\xff\xda\x00\x02\x12\x34\xff\xd9"
    segment = b"\xff\xe1" + (len(thumbnail) + 2).to_bytes(2, "big") + thumbnail
    exif.write_bytes(exif.read_bytes()[:2] + segment + exif.read_bytes()[2:])
    (tmp_path / "f3.jpg").mkdir()
    source = open_source(tmp_path, fps=10.0)
    assert [index for index, _, _ in source] == [0, 1, 2]
    assert not [r for r in caplog.records if r.name.startswith("PIL")]


def test_pillow_says_nothing_while_the_folder_is_scanned(tmp_path, caplog) -> None:
    """A TIFF whose directory claims more entries than it holds: Pillow warns ("Corrupt EXIF
    data"), which a user would see as a second line next to any message; the scan keeps quiet."""
    import warnings

    for i in range(3):
        cv2.imwrite(str(tmp_path / f"f{i}.png"), np.full((6, 8), 90, np.uint8))
    _tiff_with_a_broken_directory(tmp_path / "f1.tif", entries=40)
    with warnings.catch_warnings(record=True) as shown:
        warnings.simplefilter("always")
        open_source(tmp_path, fps=10.0)
    assert not shown and not [r for r in caplog.records if r.name.startswith("PIL")]


def test_read_image_holds_decoder_noise_back_for_the_message(tmp_path, capfd) -> None:
    """libpng prints its errors on file descriptor 2 itself: they become the complaint that goes
    into the one-line message (a mask, the first image of a folder), and nothing reaches stderr."""
    from flow.io.imagefiles import read_image

    good = tmp_path / "good.png"
    cv2.imwrite(str(good), np.full((6, 8), 90, np.uint8))
    bad = tmp_path / "bad.png"
    _png_with_undecodable_data(bad)
    image, complaint = read_image(good, cv2.IMREAD_GRAYSCALE)
    assert image.shape == (6, 8) and complaint == ""
    image, complaint = read_image(bad, cv2.IMREAD_GRAYSCALE)
    assert image is None and complaint.startswith("libpng error"), complaint
    assert capfd.readouterr().err == ""
    with pytest.raises(InputError, match=r"mask '.*bad.png' cannot be read \(libpng error: .*\): save it"):
        load_mask(bad, frame_size=(8, 6), roi=Roi(0, 0, 8, 6))
    first = tmp_path / "frames"
    first.mkdir()
    _png_with_undecodable_data(first / "f0.png")
    cv2.imwrite(str(first / "f1.png"), np.full((6, 8), 90, np.uint8))
    with pytest.raises(InputError, match=r"f0.png' cannot be read \(libpng error: .*\): remove or replace it"):
        open_source(first, fps=10.0)
    assert capfd.readouterr().err == ""


def test_a_decoder_warning_on_an_image_that_decodes_goes_in_the_notes(tmp_path, capfd) -> None:
    """libpng warns about a broken colour profile and decodes: measured, the warning in the
    notes (on stderr it would be a second line next to any refusal that follows)."""
    from PIL import Image

    image = Image.fromarray(np.full((6, 8), 255, np.uint8))
    image.save(tmp_path / "mask.png", icc_profile=b"not a profile")
    notes: list[str] = []
    assert load_mask(tmp_path / "mask.png", frame_size=(8, 6), roi=Roi(0, 0, 8, 6), notes=notes).all()
    assert len(notes) == 1 and "mask mask.png decoded with a warning: libpng warning: iCCP" in notes[0], notes
    frames = tmp_path / "frames"
    frames.mkdir()
    image.save(frames / "f0.png", icc_profile=b"not a profile")
    image.save(frames / "f1.png")
    source = open_source(frames, fps=10.0)
    assert any("image f0.png (the first) decoded with a warning: libpng warning" in n for n in source.notes)
    assert capfd.readouterr().err == ""


def test_opencv_logs_nothing_once_refflow_quiets_it(tmp_path) -> None:
    """`refflow` silences OpenCV's own log (its `[ERROR:0@...]` lines) and ffmpeg's, unless the
    user asked for them, and opens videos with ffmpeg only (no image-sequence fallback, no AVI
    parser of its own). In a fresh process: ffmpeg reads its level once, at its first use."""
    import os
    import subprocess
    import sys

    clip = tmp_path / "clip.mp4"  # an MP4 whose first box header is damaged
    clip.write_bytes(b"\x01\x00\x00\x20ftypisom" + bytes(200))
    script = ("import cv2, sys; from flow.io.video import open_video, quiet_decoder_logs; quiet_decoder_logs(); "
              "print(cv2.utils.logging.getLogLevel()); "
              "assert not open_video(sys.argv[1]).isOpened() and cv2.imread(sys.argv[1]) is None")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENCV_LOG_LEVEL", "OPENCV_FFMPEG_LOGLEVEL")}
    quiet = subprocess.run([sys.executable, "-c", script, str(clip)], capture_output=True, text=True,
                           env=env, timeout=60)
    assert quiet.returncode == 0 and quiet.stderr == "", quiet.stderr
    assert int(quiet.stdout) == cv2.utils.logging.LOG_LEVEL_SILENT
    debugging = subprocess.run([sys.executable, "-c", script, str(clip)], capture_output=True, text=True,
                               env={**env, "OPENCV_LOG_LEVEL": "INFO"}, timeout=60)
    assert int(debugging.stdout.split()[0]) == cv2.utils.logging.LOG_LEVEL_INFO  # the user's own level is kept


def test_lossless_frames_are_told_from_a_lossy_codecs(tmp_path) -> None:
    """The default takes its texture fit's own sub-pixel bias off only where the frames are what
    the sensor recorded (see FrameSource.lossless and the pipeline's bias_correction)."""
    import subprocess

    import imageio_ffmpeg

    def encode(name: str, *codec: str):
        path = tmp_path / name
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", "-f", "lavfi", "-i",
                        "testsrc=size=64x48:rate=10", "-t", "0.5", *codec, str(path)], check=True)
        return open_source(path)

    assert encode("a.mkv", "-c:v", "ffv1").lossless
    assert encode("b.avi", "-c:v", "rawvideo", "-pix_fmt", "gray").lossless
    assert not encode("c.mp4", "-c:v", "libx264").lossless
    assert not encode("d.avi", "-c:v", "mjpeg").lossless
    folder = tmp_path / "frames"
    folder.mkdir()
    for i in range(3):
        cv2.imwrite(str(folder / f"{i:02d}.png"), np.full((12, 16), 40 * i, np.uint8))
    assert open_source(folder, fps=10).lossless
    cv2.imwrite(str(folder / "03.jpg"), np.full((12, 16), 200, np.uint8))
    assert not open_source(folder, fps=10).lossless  # one JPEG among them


def test_a_lossy_streams_quality_is_read_for_the_texture_sigmas_codec_floor(tmp_path) -> None:
    """x264 writes its crf into the stream; the pipeline hands it to the default's ``codec_crf``
    (the texture readings' codec floor), DEFAULT_CRF where a lossy stream does not say, and
    nothing for lossless frames."""
    import subprocess

    import imageio_ffmpeg

    from flow.methods import registry
    from flow.pipeline import DEFAULT_CRF, _for_source

    def encode(name: str, *codec: str):
        path = tmp_path / name
        subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", "-f", "lavfi", "-i",
                        "testsrc=size=64x48:rate=10", "-t", "0.5", *codec, str(path)], check=True)
        return open_source(path)

    x264, mjpeg, ffv1 = (encode("a.mp4", "-c:v", "libx264", "-crf", "21.5"), encode("b.avi", "-c:v", "mjpeg"),
                         encode("c.mkv", "-c:v", "ffv1"))
    assert (x264.codec_crf, mjpeg.codec_crf, ffv1.codec_crf) == (21.5, None, None)
    method = registry.get_method("deepflow")
    for source, crf in ((x264, 21.5), (mjpeg, DEFAULT_CRF), (ffv1, None)):
        params, built = _for_source("deepflow", {}, method, source, [])
        assert params.get("codec_crf") == crf and built._codec_crf == crf
    params, _ = _for_source("deepflow", {"codec_crf": 30.0}, method, x264, [])
    assert params["codec_crf"] == 30.0  # the user's value stands


def _textured_frames(count: int, noise: float, seed: int = 0) -> list[np.ndarray]:
    """``count`` frames of one still texture (+-40 grey levels) with fresh sensor noise in each."""
    rng = np.random.default_rng(seed)
    scene = 120 + 40 * rng.standard_normal((64, 96))
    return [np.clip(np.rint(scene + noise * rng.standard_normal(scene.shape)), 0, 255).astype(np.uint8)
            for _ in range(count)]


def test_a_lossy_codecs_copied_blocks_are_found_and_a_cameras_frames_have_none() -> None:
    """copied_share: windows that are the frame before's bit for bit, though changed since the
    first frame (a codec's skipped blocks), and nothing in a camera's noisy frames, a scene
    without noise that stands still, a repeated frame or a saturated area."""
    camera = _textured_frames(5, noise=1.0)
    assert copied_share(iter(camera)) == 0.0
    # A codec skipped a 16x16 block of the third frame (and of the fourth): the second's there.
    coded = [f.copy() for f in camera]
    coded[2][16:32, 24:40] = coded[1][16:32, 24:40]
    coded[3][16:32, 24:40] = coded[1][16:32, 24:40]
    share = copied_share(iter(coded))
    assert HISTORY_SHARE < share < 0.1  # 9x9 window places of the 57x89 (the windows' anchors)
    # A block copied all the way from the first frame is not a copy of a changed scene.
    kept = [f.copy() for f in camera]
    for frame in kept[1:]:
        frame[16:32, 24:40] = kept[0][16:32, 24:40]
    assert copied_share(iter(kept)) == 0.0
    # A repeated frame (a camera's duplicate, a frame-rate conversion) tells nothing.
    assert copied_share(iter([camera[0], camera[1], camera[1], camera[2]])) == 0.0
    # A saturated area equal in every frame (an overexposed sky) is no texture.
    sky = [f.copy() for f in camera]
    for index, frame in enumerate(sky):
        frame[:32] = 255 if index else 254
    assert copied_share(iter(sky)) == 0.0
    # A scene without noise whose part moves every frame: its still part is the first frame's.
    still = _textured_frames(1, noise=0.0)[0]
    moving = [still.copy() for _ in range(5)]
    for index, frame in enumerate(moving):
        frame[:, :32] = np.roll(still[:, :32], 2 * index, axis=0)
    assert copied_share(iter(moving)) == 0.0


def test_lossless_files_of_a_lossy_codecs_frames_say_so(tmp_path) -> None:
    """FrameSource.copied_share reads the first frames of a folder: PNG images of noisy frames
    none; of the same frames with a codec's skipped block, above HISTORY_SHARE."""
    frames = _textured_frames(4, noise=1.5, seed=3)
    for name, images in (("camera", frames), ("exported", frames[:2] + [frames[2].copy(), frames[3].copy()])):
        if name == "exported":
            images[2][8:40, 8:40] = images[1][8:40, 8:40]
        folder = tmp_path / name
        folder.mkdir()
        for index, image in enumerate(images):
            cv2.imwrite(str(folder / f"{index:03d}.png"), image)
        source = open_source(folder, fps=30.0)
        assert source.lossless
        share = source.copied_share()
        assert (share > HISTORY_SHARE) == (name == "exported"), (name, share)


def test_a_user_who_turns_the_bias_correction_on_keeps_lossless_files_lossless(tmp_path, capsys) -> None:
    """The copied blocks' test can be wrong (a render without noise shows such blocks where it
    moves less than its grey levels' rounding in a frame), so the note names the way out:
    ``--param bias_correction=true`` keeps the frames lossless (no codec floor, nothing noted)."""
    from flow.methods import registry
    from flow.pipeline import DEFAULT_CRF, _for_source

    frames = _textured_frames(4, noise=1.5, seed=3)
    frames[2][8:40, 8:40] = frames[1][8:40, 8:40]
    for index, image in enumerate(frames):
        cv2.imwrite(str(tmp_path / f"{index:03d}.png"), image)
    source = open_source(tmp_path, fps=30.0)
    method = registry.get_method("deepflow")
    notes: list[str] = []
    params, _ = _for_source("deepflow", {}, method, source, notes)
    assert (params["codec_crf"], params["bias_correction"]) == (DEFAULT_CRF, False)
    assert len(notes) == 1 and "--param bias_correction=true" in notes[0] and notes[0] in capsys.readouterr().err
    notes = []
    params, built = _for_source("deepflow", {"bias_correction": True}, method, source, notes)
    assert params.get("codec_crf") is None and built._codec_crf is None and notes == []
