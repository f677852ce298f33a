"""Several regions in one run: a labelled mask (grey values 1..N) or several --mask files.

Two painted bars over a static textured wall, side by side in one H.264 video, move with
different known histories (other amplitudes, frequencies and noise). One `refflow track`
with a labelled mask measures each bar on its own from one flow computation per frame and
writes one CSV with a ``region`` column; each region's history must be its bar's, the numbers
must be those of a run of that region alone, and the tools that read a CSV (plot, modal,
export) take each region as a measurement point.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402

FPS = 60.0
FRAMES = 40


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("regions")
    left = make_clip(seed=31, frames=FRAMES, fps=FPS, height=160, width=200, bar_width=32,
                     amplitude=2.5, frequency_hz=3.1)
    right = make_clip(seed=32, frames=FRAMES, fps=FPS, height=160, width=200, bar_width=32,
                      amplitude=1.2, frequency_hz=7.4)
    both = dataclasses.replace(left, frames=np.concatenate([left.frames, right.frames], axis=2))
    video = encode(both, folder / "bars.mp4", crf=12)
    labels = np.concatenate([left.mask.astype(np.uint8), 2 * right.mask.astype(np.uint8)], axis=1)
    paths = {"labels": folder / "labels.png", "left": folder / "left.png", "right": folder / "right.png"}
    cv2.imwrite(str(paths["labels"]), labels)
    cv2.imwrite(str(paths["left"]), (labels == 1).astype(np.uint8) * 255)
    cv2.imwrite(str(paths["right"]), (labels == 2).astype(np.uint8) * 255)
    truth = {1: left.truth_px - left.truth_px[0], 2: right.truth_px - right.truth_px[0]}
    return {"video": video, "truth": truth, "folder": folder, **paths}


def _track(scene: dict, out: Path, *masks: Path, extra: tuple[str, ...] = ()) -> Path:
    argv = ["track", str(scene["video"]), "--no-progress", "--mm-per-px", "0.5", "--out", str(out), *extra]
    for mask in masks:
        argv += ["--mask", str(mask)]
    assert main(argv) == 0
    return out


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def _region(rows: list[dict[str, str]], label: int | None) -> np.ndarray:
    """(frames, numeric columns) of one region's rows (all rows for None), region column left out."""
    chosen = [r for r in rows if label is None or r["region"] == str(label)]
    return np.array([[float(v) for k, v in r.items() if k != "region"] for r in chosen])


@pytest.fixture(scope="module")
def labelled(scene) -> Path:
    return _track(scene, scene["folder"] / "labelled.csv", scene["labels"])


def test_each_region_reads_its_own_history(scene, labelled) -> None:
    rows = _rows(labelled)
    assert list(rows[0])[:3] == ["frame", "time_s", "region"]
    assert [r["region"] for r in rows[:4]] == ["1", "2", "1", "2"], "frame by frame, regions in label order"
    assert len(rows) == 2 * FRAMES
    for label, true in scene["truth"].items():
        numbers = _region(rows, label)
        dx, valid = numbers[:, 2], numbers[:, 6] == 1
        assert valid.mean() >= 0.95
        error = dx[valid] - true[valid]
        rmse = float(np.sqrt(np.mean(error ** 2)))
        print(f"region {label}: RMSE {rmse:.4f} px, max {np.abs(error).max():.4f} px, "
              f"slope {np.polyfit(true[valid], dx[valid], 1)[0]:.4f}")
        assert rmse <= 0.05 and np.abs(error).max() <= 0.2
        # The other bar's history is not this one's: the regions are measured apart.
        other = scene["truth"][3 - label]
        assert np.sqrt(np.mean((dx[valid] - other[valid]) ** 2)) > 0.5
        assert np.all(np.isfinite(numbers[valid, 8])), "each region has its own sigma"
    sidecar = json.loads(labelled.with_suffix(".json").read_text())
    assert sidecar["columns"][:3] == ["frame", "time_s", "region"]
    regions = sidecar["regions"]
    assert [r["label"] for r in regions] == [1, 2]
    x_left, x_right = regions[0]["centroid_px"][0], regions[1]["centroid_px"][0]
    assert 85 < x_left < 115 and 285 < x_right < 315, "centroids in full-frame pixels, each over its bar"
    assert all(r["frames_valid"] >= 0.95 * FRAMES for r in regions)


def test_a_region_reads_as_in_a_run_of_its_own(scene) -> None:
    """With the whole frame solved (no window: a run of one region would cut another), the
    regions' numbers are exactly those of one run per region, chains included."""
    whole = ("--param", "crop=false")
    both = _rows(_track(scene, scene["folder"] / "both.csv", scene["labels"], extra=whole))
    for label, mask in ((1, scene["left"]), (2, scene["right"])):
        alone = _rows(_track(scene, scene["folder"] / f"alone{label}.csv", mask, extra=whole))
        np.testing.assert_array_equal(_region(both, label), _region(alone, None))


def test_several_mask_files_are_a_labelled_mask(scene, labelled) -> None:
    files = _track(scene, scene["folder"] / "files.csv", scene["left"], scene["right"])
    assert files.read_text() == labelled.read_text()


def test_parts_and_jobs_give_the_numbers_of_one_run(scene, labelled) -> None:
    folder = scene["folder"]
    parts = []
    for i, frames in enumerate(("0:13", "13:")):
        part = folder / f"part{i}.npz"
        assert main(["track", str(scene["video"]), "--mask", str(scene["labels"]), "--no-progress",
                     "--frames", frames, "--raw-tracks", str(part), "--jobs", "1"]) == 0
        parts.append(str(part))
    merged = folder / "merged.csv"
    assert main(["merge", *parts, "--mm-per-px", "0.5", "--out", str(merged)]) == 0
    np.testing.assert_array_equal(_region(_rows(merged), None), _region(_rows(labelled), None))
    assert _rows(merged)[1]["region"] == "2"


def test_readers_take_each_region_as_a_point(scene, labelled, capsys) -> None:
    folder = scene["folder"]
    figure = folder / "spectra.png"
    assert main(["plot", str(labelled), "--out", str(figure)]) == 0
    printed = capsys.readouterr().out
    assert "region 1" in printed and "region 2" in printed and figure.stat().st_size > 0
    modes = folder / "modes.json"
    assert main(["modal", str(labelled), "--out", str(modes), "--modes", "1"]) == 0
    result = json.loads(modes.read_text())
    assert [p["region"] for p in result["points"]] == [1, 2]
    assert [p["name"] for p in result["points"]] == ["labelled region 1", "labelled region 2"]
    assert result["points"][1]["position_px"][0] > 200
    pyuff = pytest.importorskip("pyuff")
    uff = folder / "bars.uff"
    assert main(["export", str(labelled), "--out", str(uff)]) == 0
    records = pyuff.UFF(str(uff)).read_sets()
    nodes = sorted({(r["rsp_node"], r["rsp_dir"]) for r in records if r["type"] == 58})
    assert nodes == [(1, 1), (1, 2), (2, 1), (2, 2)]
    pois = folder / "pois.png"
    assert main(["pois", str(scene["video"]), "--mask", str(scene["labels"]), "--out", str(pois)]) == 0
    assert "in 2 regions" in capsys.readouterr().out
    image = cv2.imread(str(pois))
    assert image is not None and len(np.unique(image.reshape(-1, 3), axis=0)) > 2


@pytest.mark.parametrize("case, message", [
    ("overlap", "overlaps the masks before it"),
    ("klt", "picks its own features in one region"),
    ("grid", "hold no POI"),
])
def test_bad_regions_are_refused(scene, tmp_path, capsys, case, message) -> None:
    out = tmp_path / "out.csv"
    argv = ["track", str(scene["video"]), "--no-progress", "--out", str(out)]
    if case == "overlap":
        argv += ["--mask", str(scene["left"]), "--mask", str(scene["labels"])]
    elif case == "klt":
        argv += ["--mask", str(scene["labels"]), "--method", "klt"]
    else:
        tiny = np.zeros((160, 400), np.uint8)
        tiny[40:80, 60:90] = 1
        tiny[51, 201] = 2  # one pixel off the grid of --grid-step 4
        cv2.imwrite(str(tmp_path / "tiny.png"), tiny)
        argv += ["--mask", str(tmp_path / "tiny.png"), "--grid-step", "4"]
    assert main(argv) == 2
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and message in error[0]
    assert not out.exists() and not out.with_suffix(".json").exists()
