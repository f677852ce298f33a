"""``refflow track --field``: the whole displacement field as an HDF5 file (issue 33).

A clean-room synthetic clip (``tests/unit/_sine_field.py``) carries a known sine field; the
tests hold the file's layout, that xarray opens it, that a region's mean over its kept
pixels is the CSV's reading, that parts merged give the whole run's field, and that bad
input leaves no file behind.
"""

from __future__ import annotations

import csv
import sys
from pathlib import Path

import cv2
import h5py
import numpy as np
import pytest

from flow.cli import main

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "unit"))
import _sine_field as sine  # noqa: E402

RECT = "20,16,120,64"


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> Path:
    return sine.write_clip(tmp_path_factory.mktemp("sine") / "frames")


def _track(clip: Path, out: Path, *extra: str, method: str = "farneback") -> int:
    return main(["track", str(clip), "--fps", str(sine.FPS), "--method", method, "--no-progress", *extra,
                 "--out", str(out.with_suffix(".csv")), "--field", str(out.with_suffix(".h5"))])


def _csv(path: Path) -> list[dict[str, str]]:
    with path.open() as handle:
        return list(csv.DictReader(handle))


def test_layout_units_and_nan_outside_the_mask(clip, tmp_path) -> None:
    # A polygon (a triangle): the box holds pixels outside the mask, which must stay NaN.
    out = tmp_path / "tri"
    assert _track(clip, out, "--polygon", "20,16,139,16,20,79", "--mm-per-px", "0.5") == 0
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        assert f.attrs["format"] == "refflow-field/1" and f.attrs["complete"] == 1
        assert f.attrs["mm_per_px"] == 0.5
        n, height, width = f["u_px"].shape
        assert n == 20 and (height, width) == (f["y_px"].shape[0], f["x_px"].shape[0])
        assert f["x_px"][0] == 20 and f["y_px"][0] == 16
        for name in ("u_px", "v_px", "u_mm", "v_mm", "valid"):
            dataset = f[name]
            assert dataset.shape == (n, height, width)
            assert dataset.chunks[0] == 1 and dataset.compression == "gzip", name
        assert f["u_px"].dtype == np.float32 and f["valid"].dtype == np.uint8
        assert f["u_px"].attrs["units"] == "px" and f["u_mm"].attrs["units"] == "mm"
        inside = f["region_map"][()] > 0
        assert 0 < inside.sum() < inside.size
        u = f["u_px"][5]
        assert np.all(np.isnan(u[~inside])) and np.all(np.isfinite(u[inside]))
        np.testing.assert_allclose(f["u_mm"][5], u * 0.5, rtol=1e-6)
        assert np.all(f["valid"][5][~inside] == 0)
        np.testing.assert_allclose(f["time_s"][()], np.arange(n) / sine.FPS)
        assert f["frame"][()].tolist() == list(range(n))
        assert np.all(f["u_px"][0][inside] == 0)  # the reference frame against itself, offset removed


def test_the_known_sine_is_read(clip, tmp_path) -> None:
    out = tmp_path / "f"
    assert _track(clip, out, "--rect", RECT) == 0
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        x = f["x_px"][()]
        for frame in (3, 8):
            measured = np.nanmean(f["u_px"][frame], axis=0)
            truth = sine.u_true(x, frame / sine.FPS)
            rmse = float(np.sqrt(np.mean((measured - truth)[5:-5] ** 2)))
            assert rmse < 0.05 * sine.AMPLITUDE_PX, (frame, rmse)
            gain = float(np.dot(measured, truth) / np.dot(truth, truth))
            assert abs(gain - 1) < 0.05, (frame, gain)  # Farneback's smoothing: 0.97 here
            assert float(np.nanmax(np.abs(f["v_px"][frame]))) < 0.2


def test_xarray_opens_it(clip, tmp_path) -> None:
    xr = pytest.importorskip("xarray")
    pytest.importorskip("h5netcdf")
    out = tmp_path / "x"
    assert _track(clip, out, "--rect", RECT) == 0
    with xr.open_dataset(out.with_suffix(".h5"), engine="h5netcdf") as ds:
        assert ds["u_px"].dims == ("frame", "y_px", "x_px")
        assert ds["kept"].dims == ("y_px", "x_px")
        assert ds["sigma_px"].dims == ("frame", "region")
        column = ds["u_px"].isel(frame=3).mean("y_px")
        assert column.sizes["x_px"] == 120 and float(ds["x_px"][0]) == 20.0


@pytest.mark.parametrize("method", ["farneback", "deepflow"])
def test_a_regions_mean_over_its_kept_pixels_is_its_csv_reading(clip, tmp_path, method) -> None:
    # Two regions (a labelled mask): each one's own filter verdicts and average.
    labels = np.zeros((sine.HEIGHT, sine.WIDTH), np.uint8)
    labels[16:80, 20:70] = 1
    labels[16:80, 90:140] = 2
    mask = tmp_path / "regions.png"
    cv2.imwrite(str(mask), labels)
    out = tmp_path / "r"
    assert _track(clip, out, "--mask", str(mask), method=method) == 0
    rows = _csv(out.with_suffix(".csv"))
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        kept, region_map = f["kept"][()] == 1, f["region_map"][()]
        assert f["region"][()].tolist() == [1, 2]
        for row in rows:
            index, label = int(row["frame"]), int(row["region"])
            where = kept & (region_map == label)
            assert where.any()
            for name, column in (("u_px", "dx_px"), ("v_px", "dy_px")):
                mean = float(np.nanmean(f[name][index][where].astype(np.float64)))
                assert mean == pytest.approx(float(row[column]), abs=2e-6), (method, index, label, name)
            assert f["frame_valid"][index, label - 1] == int(row["valid"])
            assert f["sigma_px"][index, label - 1] == pytest.approx(float(row["sigma_px"]), rel=1e-6)


def test_parts_merged_give_the_whole_runs_field(clip, tmp_path) -> None:
    whole = tmp_path / "whole"
    common = ["--rect", RECT, "--reference-frame", "4"]
    assert _track(clip, whole, *common) == 0
    parts, fields = [], []
    for k, frames in enumerate(("0:3", "3:9", "9:")):
        raw, field = tmp_path / f"p{k}.npz", tmp_path / f"p{k}.h5"
        assert main(["track", str(clip), "--fps", str(sine.FPS), "--method", "farneback", "--no-progress",
                     *common, "--frames", frames, "--raw-tracks", str(raw), "--field", str(field)]) == 0
        with h5py.File(field, "r") as f:
            assert f.attrs["complete"] == 0 and "valid" not in f
        parts.append(str(raw))
        fields.append(str(field))
    merged = tmp_path / "merged"
    assert main(["merge", *parts, *[a for f in fields for a in ("--part-field", f)],
                 "--out", str(merged.with_suffix(".csv")), "--field", str(merged.with_suffix(".h5"))]) == 0
    assert merged.with_suffix(".csv").read_text() == whole.with_suffix(".csv").read_text()
    with h5py.File(whole.with_suffix(".h5"), "r") as a, h5py.File(merged.with_suffix(".h5"), "r") as b:
        assert sorted(a) == sorted(b)
        for name in a:
            assert np.array_equal(a[name][()], b[name][()], equal_nan=True), name


def _leftovers(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.iterdir() if p.suffix in (".h5", ".csv", ".json") or ".part" in p.name
                  or ".stream" in p.name)


@pytest.mark.parametrize("extra, said", [
    (["--method", "klt"], "--field needs a dense method"),
    (["--field", "out.txt"], "the format is taken from the name"),
])
def test_bad_input_is_one_line_and_no_file(clip, tmp_path, capsys, monkeypatch, extra, said) -> None:
    monkeypatch.chdir(tmp_path)
    args = ["track", str(clip), "--fps", "20", "--rect", RECT, "--no-progress", "--out", "o.csv", "--field", "o.h5"]
    assert main(args + extra) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1
    assert _leftovers(tmp_path) == []


def test_merge_needs_every_parts_field(clip, tmp_path, capsys) -> None:
    raw = tmp_path / "p.npz"
    assert main(["track", str(clip), "--fps", "20", "--rect", RECT, "--method", "farneback", "--no-progress",
                 "--frames", "0:4", "--raw-tracks", str(raw)]) == 0
    assert main(["merge", str(raw), "--out", str(tmp_path / "m.csv"), "--field", str(tmp_path / "m.h5")]) == 2
    assert "--part-field" in capsys.readouterr().err
    assert not (tmp_path / "m.h5").exists() and not (tmp_path / "m.csv").exists()


def test_a_failed_run_leaves_no_field(clip, tmp_path, monkeypatch) -> None:
    from flow.field import stream as field

    def broken(self, index, *values):
        if index == 6:
            raise KeyboardInterrupt
        return original(self, index, *values)

    original = field.FieldStream.append
    monkeypatch.setattr(field.FieldStream, "append", broken)
    assert _track(clip, tmp_path / "k", "--rect", RECT) == 130
    assert _leftovers(tmp_path) == []


@pytest.fixture(scope="module")
def field_file(clip, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("plot") / "f"
    assert _track(clip, out, "--rect", RECT) == 0
    return out.with_suffix(".h5")


def test_field_plot_writes_map_movie_and_deflection_shape(field_file, tmp_path) -> None:
    prefix = tmp_path / "pic"
    assert main(["field-plot", str(field_file), "--out", str(prefix), "--hz", str(sine.HZ)]) == 0
    for suffix in ("_map.png", "_field.gif", "_ods.png"):
        assert (tmp_path / f"pic{suffix}").stat().st_size > 1000, suffix
    assert main(["field-plot", str(field_file), "--out", str(prefix), "--movie", "mp4", "--frame", "3"]) == 0
    assert (tmp_path / "pic_field.mp4").stat().st_size > 1000


def test_the_deflection_shape_is_the_known_sine(field_file) -> None:
    from flow.field.plot import deflection_shape
    from flow.field.stream import read_field

    with read_field(field_file) as field:
        amp_u, phase_u, amp_v, _ = deflection_shape(field, sine.HZ)
        x = field["x_px"][()]
    # Two whole cycles of the vibration: the amplitude is the sine's |shape|, the phase flips
    # by 180 degrees between its crests.
    shape = sine.AMPLITUDE_PX * np.sin(2 * np.pi * x / sine.PERIOD_PX)
    measured = np.nanmedian(amp_u, axis=0)
    crest = np.abs(shape) > 0.9 * sine.AMPLITUDE_PX
    assert np.median(measured[crest]) == pytest.approx(sine.AMPLITUDE_PX, rel=0.08)
    assert np.nanmedian(amp_v) < 0.1 * sine.AMPLITUDE_PX
    phase = np.nanmedian(phase_u, axis=0)
    up, down = crest & (shape > 0), crest & (shape < 0)
    gap = abs(((np.median(phase[up]) - np.median(phase[down])) + 180) % 360 - 180)
    assert gap == pytest.approx(180, abs=10)


@pytest.mark.parametrize("extra, said", [
    (["--hz", "15"], "Nyquist"),
    (["--hz", "-1"], "not a frequency"),
    (["--frame", "99"], "--frame 99 is not in the field"),
])
def test_field_plot_bad_input_is_one_line_and_no_file(field_file, tmp_path, capsys, extra, said) -> None:
    assert main(["field-plot", str(field_file), "--out", str(tmp_path / "bad"), *extra]) == 2
    err = capsys.readouterr().err
    assert said in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_field_plot_refuses_a_file_that_is_no_field(tmp_path, capsys) -> None:
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["x"] = np.zeros(3)
    assert main(["field-plot", str(other), "--out", str(tmp_path / "p")]) == 2
    assert "no refflow field file" in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["other.h5"]


def test_the_default_gives_a_deforming_regions_pixels_their_uncertainty(clip, tmp_path) -> None:
    """The sine deforms the speckle beyond any affine field: the default reads it pixel by pixel
    (a windowed step, flow.methods.deepflow.localfit) and writes each pixel's uncertainty,
    NaN outside the mask and in the reference frame (measured against itself); a method that
    has none (farneback) leaves the datasets NaN. Parts merged give the whole run's; field-plot
    maps it."""
    whole = tmp_path / "whole"
    common = ["--rect", RECT, "--reference-frame", "4"]
    assert _track(clip, whole, *common, method="deepflow") == 0
    with h5py.File(whole.with_suffix(".h5"), "r") as f:
        inside = f["region_map"][()] > 0
        assert f["sigma_u_px"].shape == f["u_px"].shape and f["sigma_u_px"].attrs["units"] == "px"
        for frame in (3, 8, 13):
            for name in ("sigma_u_px", "sigma_v_px"):
                sigma = f[name][frame]
                assert np.isfinite(sigma[inside]).mean() > 0.9, (frame, name)
                assert np.all(np.isnan(sigma[~inside]))
                assert 0 < np.nanmedian(sigma) < 0.05, (frame, name)
        assert np.all(np.isnan(f["sigma_u_px"][4]))
    parts, fields = [], []
    for k, frames in enumerate(("0:6", "6:")):
        raw, field = tmp_path / f"p{k}.npz", tmp_path / f"p{k}.h5"
        assert main(["track", str(clip), "--fps", str(sine.FPS), "--no-progress", *common, "--frames", frames,
                     "--raw-tracks", str(raw), "--field", str(field)]) == 0
        parts.append(str(raw))
        fields.append(str(field))
    merged = tmp_path / "merged"
    assert main(["merge", *parts, *[a for f in fields for a in ("--part-field", f)],
                 "--out", str(merged.with_suffix(".csv")), "--field", str(merged.with_suffix(".h5"))]) == 0
    with h5py.File(whole.with_suffix(".h5"), "r") as a, h5py.File(merged.with_suffix(".h5"), "r") as b:
        for name in ("sigma_u_px", "sigma_v_px", "u_px"):
            assert np.array_equal(a[name][()], b[name][()], equal_nan=True), name
    baseline = tmp_path / "farneback"
    assert _track(clip, baseline, *common) == 0
    with h5py.File(baseline.with_suffix(".h5"), "r") as f:
        assert np.all(np.isnan(f["sigma_u_px"][()])) and np.all(np.isnan(f["sigma_v_px"][()]))
    # field-plot maps the uncertainty where the file has it at the map's frame, only there.
    assert main(["field-plot", str(whole.with_suffix(".h5")), "--out", str(tmp_path / "pic"), "--frame", "8"]) == 0
    assert (tmp_path / "pic_sigma.png").stat().st_size > 1000
    assert main(["field-plot", str(baseline.with_suffix(".h5")), "--out", str(tmp_path / "base")]) == 0
    assert (tmp_path / "base_map.png").is_file() and not (tmp_path / "base_sigma.png").exists()


def test_the_pixels_uncertainty_lands_on_them_when_the_work_area_is_cut(tmp_path, monkeypatch) -> None:
    """A deforming speckle in a frame wider than the region's window (the default solves a
    window about the POIs, 256 px beyond them, whose corner is not the frame's): the uncertainty
    is written at the region's pixels, every one of them."""
    from scipy import ndimage

    height, width = 160, 1400
    rng = np.random.default_rng(5)
    texture = ndimage.gaussian_filter(rng.standard_normal((2 * height, 2 * width)), 3.0)
    texture = 128 + 70 * texture / texture.std()
    ys, xs = np.mgrid[0:2 * height, 0:2 * width] / 2.0
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(4):
        shift = 0.5 * k / 3 * np.sin(2 * np.pi * xs / 80.0)
        image = ndimage.map_coordinates(texture, [2 * ys, 2 * (xs - shift)], order=3, mode="mirror")
        image = image.reshape(height, 2, width, 2).mean(axis=(1, 3))
        cv2.imwrite(str(folder / f"frame_{k:03d}.png"), np.clip(np.rint(image), 0, 255).astype(np.uint8))
    out = tmp_path / "cut"
    from flow.field import stream

    origins = []
    append = stream.FieldStream.append
    monkeypatch.setattr(stream.FieldStream, "append",
                        lambda self, *a: (origins.append(self.flow_origin), append(self, *a))[1])
    mask = np.zeros((height, width), np.uint8)
    mask[90:138, 600:664] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    assert main(["track", str(folder), "--fps", "10", "--mask", str(tmp_path / "mask.png"), "--no-progress",
                 "--out", str(out.with_suffix(".csv")), "--field", str(out.with_suffix(".h5"))]) == 0
    assert origins and all(origin != (0, 0) for origin in origins)  # the window is cut out of the frame
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        assert f["x_px"][0] == 600 and f["y_px"][0] == 90
        for frame in (2, 3):
            sigma = f["sigma_u_px"][frame]
            assert np.isfinite(sigma).all() and 0 < np.median(sigma) < 0.05, frame
