"""`refflow modal` on a planted measurement: four points of a cantilever, two decaying modes, each
point its own `refflow track` CSV. The frequencies, damping ratios and shapes come back; a
measurement scaled by 0.95 gives the same modes; swapping two points' files swaps their shape
values (and the MAC against the true shapes then fails); CSVs of different frames are refused
and a failed run leaves nothing behind."""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np
import pytest

from flow.io.errors import InputError
from flow.modal import add_parser, run_modal
from refflow.modal import mac

COLUMNS = ["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid"]
FPS = 60.0
DURATION_S = 30.0
MM_PER_PX = 0.357
HEIGHTS = np.array([0.25, 0.5, 0.75, 1.0])  # z / L of the four points, root to tip
MODES = ((3.1, 0.015, 3.0), (19.4, 0.01, 0.6))  # Hz, damping ratio, tip amplitude (px)
# The beam is filmed a little askew: it moves along this image direction (x right, y down).
ANGLE = np.deg2rad(12.0)


def cantilever(z_over_l: np.ndarray, mode: int) -> np.ndarray:
    """Clamped-free Euler-Bernoulli shape, tip = 1 (written out here, apart from analysis)."""
    bl = (1.875104068711961, 4.694091132974175)[mode - 1]
    x = bl * z_over_l
    sigma = (np.cosh(bl) + np.cos(bl)) / (np.sinh(bl) + np.sin(bl))
    phi = np.cosh(x) - np.cos(x) - sigma * (np.sinh(x) - np.sin(x))
    return phi / (np.cosh(bl) - np.cos(bl) - sigma * (np.sinh(bl) - np.sin(bl)))


TRUE_SHAPES = [cantilever(HEIGHTS, 1), cantilever(HEIGHTS, 2)]


def response(time_s: np.ndarray, seed: int = 7) -> np.ndarray:
    """Free decay of the two modes at the four points, px along the beam's motion; (4, frames)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((HEIGHTS.size, time_s.size))
    for shape, (f, zeta, amplitude) in zip(TRUE_SHAPES, MODES, strict=True):
        wd = 2 * np.pi * f * np.sqrt(1 - zeta ** 2)
        q = amplitude * np.exp(-zeta * 2 * np.pi * f * time_s) * np.cos(wd * time_s + rng.uniform(0, 2 * np.pi))
        out += np.outer(shape, q)
    return out + 0.01 * rng.normal(size=out.shape)  # 0.01 px measurement noise


def write_point(path: Path, time_s: np.ndarray, along_px: np.ndarray, valid: np.ndarray, *,
                centroid_px: tuple[float, float] | None, scale: float = MM_PER_PX) -> None:
    """A `refflow track` CSV (invalid frames empty, valid = 0) and its sidecar."""
    dx, dy = along_px * np.cos(ANGLE), along_px * np.sin(ANGLE)
    with path.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(COLUMNS)
        for i, (t, x, y, ok) in enumerate(zip(time_s, dx, dy, valid, strict=True)):
            values = [f"{v:.9g}" for v in (x, y, x * scale, y * scale)] if ok else ["nan"] * 4
            writer.writerow([i, f"{t:.9g}", *values, int(ok)])
    poi = {"count": 120, "source": "mask", "mask_pixels": 120, "grid_step": 1}
    if centroid_px is not None:
        poi["centroid_px"] = list(centroid_px)
    sidecar = {"method": "deepflow", "roi": {"x": 0, "y": 0, "width": 640, "height": 480}, "poi": poi}
    path.with_suffix(".json").write_text(json.dumps(sidecar))


def write_points(folder: Path, *, factor: float = 1.0, centroids: bool = True,
                 frames: int | None = None) -> list[Path]:
    folder.mkdir(parents=True, exist_ok=True)
    time_s = np.arange(int(DURATION_S * FPS)) / FPS
    if frames is not None:
        time_s = time_s[:frames]
    motion = factor * response(time_s)
    rng = np.random.default_rng(11)
    paths = []
    for i, (z, along) in enumerate(zip(HEIGHTS, motion, strict=True)):
        valid = rng.random(time_s.size) > 0.02  # a few frames lost per point, bridged
        if i == 1:
            valid[:5] = False  # one point starts late: the record starts where all measured
        path = folder / f"z{int(round(100 * z)):03d}.csv"
        write_point(path, time_s, along, valid, centroid_px=(320.0, 400.0 - 300.0 * z) if centroids else None)
        paths.append(path)
    return paths


@pytest.fixture(scope="module")
def measured(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("modal")
    paths = write_points(folder / "points")
    result = run_modal(paths, out_json=folder / "out" / "modes.json", n_modes=2)
    return {"folder": folder, "paths": paths, "result": result}


def test_two_modes_come_back_with_their_damping_and_shapes(measured) -> None:
    result = measured["result"]
    modes = result["modes"]
    assert len(modes) == 2
    for mode, (f, zeta, _), shape in zip(modes, MODES, TRUE_SHAPES, strict=True):
        assert mode["freq_hz"] == pytest.approx(f, rel=0.005)
        assert mode["damping_ratio"] == pytest.approx(zeta, rel=0.1)
        assert mac(mode["shape"], shape) > 0.99
        assert max(abs(v) for v in mode["shape"]) == pytest.approx(1.0)
    # The modes tell apart: each shape matches its own mode, not the other one.
    assert mac(modes[0]["shape"], TRUE_SHAPES[1]) < 0.5
    # The points in the order given, with their sidecars' positions and the beam's direction.
    assert [p["name"] for p in result["points"]] == ["z025", "z050", "z075", "z100"]
    assert [p["position_px"] for p in result["points"]] == [[320.0, 400.0 - 300.0 * z] for z in HEIGHTS]
    for point in result["points"]:
        assert point["direction_px"] == pytest.approx([np.cos(ANGLE), np.sin(ANGLE)], abs=0.01)
    assert result["units"]["displacement"] == "mm"
    assert result["record"]["frames_trimmed"] == 5 and result["record"]["rate_hz"] == pytest.approx(FPS)
    out = measured["folder"] / "out"
    written = json.loads((out / "modes.json").read_text())
    assert written["modes"] == result["modes"]
    assert sorted(p.name for p in out.iterdir()) == ["modes.json", "modes_shapes.png", "modes_stabilisation.png"]
    for name in ("modes_shapes.png", "modes_stabilisation.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_scaled_measurement_same_modes_and_swapped_points_swap_the_shape(measured, tmp_path) -> None:
    reference = measured["result"]["modes"]
    scaled = run_modal(write_points(tmp_path / "scaled", factor=0.95, centroids=False),
                       out_json=tmp_path / "scaled.json", out_prefix=tmp_path / "figs" / "scaled")
    for mode, ref in zip(scaled["modes"], reference, strict=True):
        assert mode["freq_hz"] == pytest.approx(ref["freq_hz"], rel=1e-6)
        assert mode["damping_ratio"] == pytest.approx(ref["damping_ratio"], rel=1e-4)
        assert mode["shape"] == pytest.approx(ref["shape"], abs=1e-5)
    assert all("position_px" not in p for p in scaled["points"])  # no centroid recorded: none given
    assert (tmp_path / "figs" / "scaled_shapes.png").is_file()

    # Points 2 and 3 given the other way round: their shape values trade places, so the
    # true shapes no longer match (the check above can fail).
    a, b, c, d = measured["paths"]
    swapped = run_modal([a, c, b, d], out_json=tmp_path / "swapped.json", direction="dx")
    assert [p["name"] for p in swapped["points"]] == ["z025", "z075", "z050", "z100"]
    assert all(p["direction_px"] == [1.0, 0.0] for p in swapped["points"])
    for mode, ref, shape in zip(swapped["modes"], reference, TRUE_SHAPES, strict=True):
        assert mode["shape"] == pytest.approx(np.asarray(ref["shape"])[[0, 2, 1, 3]], abs=0.02)
        assert mac(mode["shape"], shape) < 0.97
        assert mac(mode["shape"], shape[[0, 2, 1, 3]]) > 0.99


def _listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def test_points_of_different_frames_are_refused_and_nothing_is_written(measured, tmp_path) -> None:
    other = write_points(tmp_path / "short", frames=1500)[0]
    before = _listing(tmp_path)
    with pytest.raises(InputError, match=r"z025\.csv and .*z025\.csv do not share their frame times") as err:
        run_modal([measured["paths"][0], other], out_json=tmp_path / "modes.json")
    assert "\n" not in str(err.value)
    assert _listing(tmp_path) == before


def test_a_failure_while_writing_leaves_no_file(measured, tmp_path, monkeypatch) -> None:
    import flow.modal

    def broken(*args, **kwargs):
        raise RuntimeError("disk trouble")

    monkeypatch.setattr(flow.modal, "shapes_figure", broken)
    with pytest.raises(RuntimeError):
        run_modal(measured["paths"], out_json=tmp_path / "out" / "modes.json")
    assert list((tmp_path / "out").iterdir()) == []


def test_outputs_over_inputs_and_bad_options_are_refused(measured, tmp_path) -> None:
    paths = measured["paths"]
    with pytest.raises(InputError, match="never writes over an input"):
        run_modal(paths, out_json=paths[0].with_suffix(".json"))
    with pytest.raises(InputError, match="given twice"):
        run_modal([paths[0], paths[0]], out_json=tmp_path / "m.json")
    with pytest.raises(InputError, match="Nyquist"):
        run_modal(paths, out_json=tmp_path / "m.json", band_hz=(1.0, 40.0))
    with pytest.raises(InputError, match="--modes"):
        run_modal(paths, out_json=tmp_path / "m.json", n_modes=0)
    assert not (tmp_path / "m.json").exists()


def test_command_line(measured, tmp_path, capsys) -> None:
    parser = argparse.ArgumentParser(prog="refflow")
    add_parser(parser.add_subparsers(dest="command", required=True))
    out = tmp_path / "cli.json"
    args = parser.parse_args(["modal", *map(str, measured["paths"][:2]), "--out", str(out),
                              "--modes", "1", "--band", "1,10", "--direction", "dy"])
    assert args.func(args) == 0
    printed = capsys.readouterr().out
    assert "mode 1: 3.09" in printed or "mode 1: 3.10" in printed
    assert printed.rstrip().endswith(str(out))
    written = json.loads(out.read_text())
    assert written["band_hz"] == [1.0, 10.0] and written["direction"] == "dy"
    assert written["modes"][0]["freq_hz"] == pytest.approx(3.1, rel=0.005)
    args = parser.parse_args(["modal", str(measured["paths"][0]), "--out", str(out), "--band", "1:10"])
    with pytest.raises(InputError, match="not LO,HI"):
        args.func(args)
