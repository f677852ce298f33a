"""Frames that show nothing of the scene (flow.methods.deepflow.hidden) and what the default
reads there: a sheet over the whole view, a lens cap, and the visible frames that must not be
taken for them (moved, darkened to a sixth, defocused, half covered)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from flow.methods.deepflow.hidden import SceneCheck
from flow.methods.deepflow.method import DeepFlow

sys_rng = np.random.default_rng(5)


def _scene(height: int = 160, width: int = 240) -> np.ndarray:
    """A textured wall with a faint bar across it (the bench's kind of scene), float32 grey."""
    speckle = cv2.GaussianBlur(sys_rng.standard_normal((height, width)).astype(np.float32), (0, 0), 2.5)
    wall = 110 + 35 * speckle / speckle.std()
    wall[60:100, :] = 150 + 2.0 * cv2.GaussianBlur(
        sys_rng.standard_normal((40, width)).astype(np.float32), (0, 0), 2.0)
    return wall


REFERENCE = _scene()


def _noisy(image: np.ndarray, sigma: float = 1.2, seed: int = 0) -> np.ndarray:
    noise = np.random.default_rng(seed).normal(0, sigma, image.shape).astype(np.float32)
    return np.clip(image + noise, 0, 255).astype(np.float32)


def _shifted(image: np.ndarray, dx: float, dy: float) -> np.ndarray:
    matrix = np.float32([[1, 0, dx], [0, 1, dy]])
    return cv2.warpAffine(image, matrix, image.shape[::-1], borderMode=cv2.BORDER_REFLECT)


def _sheet(seed: int = 1) -> np.ndarray:
    return _noisy(np.full(REFERENCE.shape, 234.0, np.float32), sigma=3.0, seed=seed)


@pytest.mark.parametrize("name, frame", [
    ("the reference itself, noisy", _noisy(REFERENCE)),
    ("moved 20 px", _noisy(_shifted(REFERENCE, 20.0, -6.0))),
    ("darkened to a sixth", _noisy(REFERENCE / 6.0)),
    # texture gone too, so only the correlation tells: it must search the motion
    ("darkened to a sixth and moved 30 px", _noisy(_shifted(REFERENCE, 30.0, 4.0) / 6.0)),
    ("defocused", _noisy(cv2.GaussianBlur(REFERENCE, (0, 0), 4.0))),
    ("half covered by the sheet", np.where(np.arange(240)[None, :] < 120, _sheet(), _noisy(REFERENCE))),
])
def test_a_frame_that_shows_the_scene_is_not_hidden(name, frame) -> None:
    assert not SceneCheck(REFERENCE).hidden(frame.astype(np.float32)), name


@pytest.mark.parametrize("name, frame", [
    ("a white sheet over the view", _sheet()),
    ("a lens cap (one grey level)", np.zeros(REFERENCE.shape, np.float32)),
    ("a dark frame with sensor noise", _noisy(np.full(REFERENCE.shape, 8.0, np.float32), sigma=1.0)),
])
def test_a_frame_that_shows_nothing_of_the_scene_is_hidden(name, frame) -> None:
    assert SceneCheck(REFERENCE).hidden(frame), name


def test_the_check_reads_only_its_window() -> None:
    covered = _noisy(REFERENCE)
    covered[:, :120] = _sheet()[:, :120]
    window = (slice(0, 160), slice(0, 120))
    assert SceneCheck(REFERENCE, window).hidden(covered)
    assert not SceneCheck(REFERENCE, (slice(0, 160), slice(120, 240))).hidden(covered)


def test_the_default_reads_a_hidden_frame_coarsely_and_keeps_the_reading() -> None:
    """A hidden frame gets no full measurement (no refinement, a quarter-resolution dense
    flow) but a finite reading at the POIs, which the driver then flags; the frames before and
    after it are measured as without it."""
    reference = REFERENCE.astype(np.uint8)
    moved = _noisy(_shifted(REFERENCE, 0.3, 1.5), seed=3).astype(np.uint8)
    sheet = _sheet().astype(np.uint8)
    mask = np.zeros(reference.shape, bool)
    mask[62:98, 60:180] = True
    method = DeepFlow(warm=False)
    method.bind(reference, mask)
    before = method.calc(reference, moved)
    hidden = method.calc(reference, sheet)
    after = method.calc(reference, moved)
    assert method.counts["hidden_frames"] == 1 and method.counts["full_frames"] == 2
    assert np.isfinite(hidden[mask]).all(), "a hidden frame keeps a reading (flagged downstream)"
    assert np.abs(hidden[mask]).max() < 2.0, "the sheet stands still: no wild reading"
    assert np.array_equal(before, after, equal_nan=True)
    alone = DeepFlow(warm=False)
    alone.bind(reference, mask)
    assert np.array_equal(alone.calc(reference, moved), after, equal_nan=True)


def test_a_hidden_frame_of_a_narrow_window_is_glimpsed_at_a_finer_scale() -> None:
    """A window too narrow for a quarter-resolution matching (a 40-row frame: a Phantom
    recording's strip) is glimpsed at full resolution instead of failing."""
    reference = np.ascontiguousarray(REFERENCE[60:100]).astype(np.uint8)
    mask = np.zeros(reference.shape, bool)
    mask[8:32, 60:180] = True
    method = DeepFlow(warm=False)
    method.bind(reference, mask)
    flow = method.calc(reference, np.full(reference.shape, 234, np.uint8))
    assert method.last_hidden and method.counts["hidden_frames"] == 1
    assert np.isfinite(flow[mask]).all()


def test_hidden_frames_are_flagged_where_the_sheet_looks_like_the_member(tmp_path) -> None:
    """A sheet as grey as the member's paint leaves the POIs' photometric mismatch small (the
    workbench's A4 sheet over its grey beam): the frames are flagged all the same, their
    readings kept, and the sidecar counts them."""
    import csv
    import json
    import sys
    from pathlib import Path

    from flow.cli import main

    sys.path.insert(0, str(Path(__file__).parent))
    from _lowtex_clip import encode, make_clip

    clip = make_clip(seed=4, frames=30, fps=60.0, height=120, width=160, bar_width=28, amplitude=2.0,
                     member_grey=233.0, occlude_s=(0.2, 0.3))
    video = encode(clip, tmp_path / "bar.mp4", crf=12)
    mask = tmp_path / "mask.png"
    cv2.imwrite(str(mask), clip.mask.astype(np.uint8) * 255)
    out = tmp_path / "bar.csv"
    assert main(["track", str(video), "--mask", str(mask), "--no-progress", "--out", str(out)]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    valid = np.array([r["valid"] == "1" for r in rows])
    dx = np.array([float(r["dx_px"]) for r in rows])
    assert not valid[clip.occluded].any() and valid[~clip.occluded].all()
    assert np.isfinite(dx).all(), "a flag qualifies a reading, never deletes it"
    quality = json.loads(out.with_suffix(".json").read_text())["quality"]
    assert quality["frames_hidden"] == clip.occluded.sum() == 6
    # A method that does not tell says nothing (null), not "none hidden".
    for method in ("dis", "deepflow-dense"):
        other = tmp_path / f"{method}.csv"
        assert main(["track", str(video), "--mask", str(mask), "--method", method, "--no-progress",
                     "--out", str(other)]) == 0
        assert json.loads(other.with_suffix(".json").read_text())["quality"]["frames_hidden"] is None
    # Parts carry the flag; parts that do not record it (an older version) are not merged with
    # parts that do.
    parts = [tmp_path / "a.npz", tmp_path / "b.npz"]
    for part, frames in zip(parts, ("0:15", "15:"), strict=True):
        assert main(["track", str(video), "--mask", str(mask), "--no-progress", "--frames", frames,
                     "--raw-tracks", str(part)]) == 0
    merged = tmp_path / "merged.csv"
    assert main(["merge", *map(str, parts), "--out", str(merged)]) == 0
    assert json.loads(merged.with_suffix(".json").read_text())["quality"]["frames_hidden"] == 6
    with np.load(parts[1]) as data:
        older = {k: data[k] for k in data.files if k != "hidden"}
    np.savez(parts[1], **older)
    assert main(["merge", *map(str, parts), "--out", str(tmp_path / "mixed.csv")]) == 2
    assert not (tmp_path / "mixed.csv").exists()


def test_a_hidden_frame_is_glimpsed_at_a_scale_the_matching_can_take() -> None:
    """A coarse matching (downscale 8) on a 150-row window: the glimpse's quarter would be too
    small for its atoms; a finer one is taken instead of failing."""
    reference = np.ascontiguousarray(np.vstack([REFERENCE, REFERENCE])[:150]).astype(np.uint8)
    mask = np.zeros(reference.shape, bool)
    mask[40:110, 60:180] = True
    method = DeepFlow(warm=False, downscale=8)
    method.bind(reference, mask)
    flow = method.calc(reference, np.full(reference.shape, 234, np.uint8))
    assert method.last_hidden and np.isfinite(flow[mask]).all()
