"""The default method's chains: frames tracked from their predecessor, the same numbers however
the run is split, and full measurements where tracking cannot hold (a jump, an occlusion).

``deepflow`` measures the first frame of each chain of ``CHAIN_LENGTH`` frames in full and
tracks the member's edges through the rest (see :mod:`flow.methods.deepflow.method`). The chains are
fixed by the frame index, so a run split into --frames parts (starting inside a chain) or
measured with --jobs 2 gives the very numbers of one run; a frame where the member jumps or
the view is blocked gets the full measurement.
"""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main
from flow.methods.deepflow import method as method_module
from flow.methods.deepflow.method import CHAIN_LENGTH

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402

FPS = 60.0
FRAMES = 48
JUMP = (0.30, 0.45, 9.0)  # frames 18-26: 9 px further, inside the first chain (0-31)
OCCLUDED_S = (0.58, 0.63)  # frames 35-37


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("chains")
    clip = make_clip(seed=21, frames=FRAMES, fps=FPS, height=120, width=160, bar_width=28,
                     amplitude=2.5, jump=JUMP, occlude_s=OCCLUDED_S)
    video = encode(clip, folder / "bar.mp4", crf=12)
    mask = folder / "mask.png"
    cv2.imwrite(str(mask), clip.mask.astype(np.uint8) * 255)
    return {"clip": clip, "video": video, "mask": mask, "folder": folder}


def _numbers(path: Path) -> np.ndarray:
    with path.open() as handle:
        return np.array([[float(v) for v in row.values()] for row in csv.DictReader(handle)])


def _track(scene: dict, out: Path, *extra: str) -> Path:
    assert main(["track", str(scene["video"]), "--mask", str(scene["mask"]), "--no-progress",
                 *extra, "--out", str(out)]) == 0
    return out


@pytest.fixture(scope="module")
def whole(scene) -> Path:
    return _track(scene, scene["folder"] / "whole.csv", "--mm-per-px", "0.5")


def test_chains_track_the_member_and_measure_in_full_where_it_jumps(scene, whole) -> None:
    clip = scene["clip"]
    rows = _numbers(whole)
    dx, valid = rows[:, 2], rows[:, 6] == 1
    true = clip.truth_px - clip.truth_px[0]
    occluded = clip.occluded
    assert not valid[occluded].any(), "the blocked view is flagged"
    seen = valid & ~occluded
    assert seen[~occluded].mean() >= 0.95
    error = np.abs(dx[seen] - true[seen])
    print(f"chains: max error {error.max():.4f} px, RMSE {np.sqrt(np.mean(error ** 2)):.4f} px")
    assert error.max() < 0.15 and np.sqrt(np.mean(error ** 2)) < 0.06
    t = np.arange(FRAMES) / FPS
    jumped = (t >= JUMP[0]) & (t < JUMP[1])
    assert np.abs(dx[jumped & seen] - true[jumped & seen]).max() < 0.15, "the jump is followed"
    timings = json.loads(whole.with_suffix(".json").read_text())["timings"]
    chains = -(-FRAMES // CHAIN_LENGTH)
    # Most frames are tracked; each chain's first frame and the jump's two ends are measured
    # in full; the sheet's frames, which show nothing of the scene, only glimpsed (see
    # flow.methods.deepflow.hidden), their readings kept and flagged.
    assert timings["full_frames"] + timings["warm_frames"] + timings["hidden_frames"] == FRAMES
    assert timings["hidden_frames"] == occluded.sum()
    assert np.isfinite(dx[occluded]).all()
    assert timings["warm_frames"] >= FRAMES // 2
    assert timings["full_frames"] >= chains + 2


def test_chains_give_one_run_s_numbers_in_parts_and_with_jobs(scene, whole, tmp_path) -> None:
    two = _track(scene, tmp_path / "two.csv", "--mm-per-px", "0.5", "--jobs", "2")
    assert np.array_equal(_numbers(whole), _numbers(two), equal_nan=True)
    parts = [tmp_path / f"{k}.npz" for k in range(3)]
    # Both cuts fall inside a chain (the first and the second): a part first solves its chain's
    # earlier frames.
    for part, frames in zip(parts, ["0:7", "7:40", "40:"], strict=True):
        assert 0 < int(frames.split(":")[0] or 0) % CHAIN_LENGTH or frames.startswith("0:")
        assert main(["track", str(scene["video"]), "--mask", str(scene["mask"]), "--no-progress",
                     "--frames", frames, "--raw-tracks", str(part)]) == 0
    merged = tmp_path / "merged.csv"
    assert main(["merge", *map(str, parts), "--mm-per-px", "0.5", "--out", str(merged)]) == 0
    assert np.array_equal(_numbers(whole), _numbers(merged), equal_nan=True)
    # The frames that showed nothing (the sheet's) travel through the parts too.
    hidden = [json.loads(p.with_suffix(".json").read_text())["quality"]["frames_hidden"] for p in (whole, merged)]
    assert hidden == [scene["clip"].occluded.sum()] * 2


def test_tracked_frames_read_like_frames_measured_in_full(scene, whole, tmp_path) -> None:
    full = _track(scene, tmp_path / "full.csv", "--mm-per-px", "0.5", "--param", "warm=false")
    timings = json.loads(full.with_suffix(".json").read_text())["timings"]
    assert timings["warm_frames"] == 0
    assert timings["full_frames"] == FRAMES - scene["clip"].occluded.sum() == FRAMES - timings["hidden_frames"]
    clip = scene["clip"]
    true = clip.truth_px - clip.truth_px[0]
    a, b = _numbers(whole), _numbers(full)
    both = (a[:, 6] == 1) & (b[:, 6] == 1)
    assert both.mean() > 0.85
    rmse = [float(np.sqrt(np.mean((r[both, 2] - true[both]) ** 2))) for r in (a, b)]
    difference = np.abs(a[both, 2] - b[both, 2])
    print(f"RMSE tracked {rmse[0]:.4f} px, full {rmse[1]:.4f} px; difference: max {difference.max():.4f} "
          f"px, mean {difference.mean():.4f} px")
    assert rmse[0] <= 1.1 * rmse[1] + 0.005
    assert difference.mean() < 0.02


def test_tracked_frames_fitted_by_their_key_s_outline_model_read_as_by_every_model(
        scene, whole, tmp_path, monkeypatch) -> None:
    """A tracked frame's outline is fitted by its key's outline model (with the sharp one and
    the whole-profile match) and by all five only where those agree worse than the key's
    (TRACKED_SPREAD_RATIO): the readings are those of every model on every frame."""
    monkeypatch.setattr(method_module, "TRACKED_SPREAD_RATIO", -np.inf)  # every model, every frame
    every = _track(scene, tmp_path / "every.csv", "--mm-per-px", "0.5")
    timings = [json.loads(p.with_suffix(".json").read_text())["timings"] for p in (whole, every)]
    tracked = timings[1]["warm_frames"]
    assert tracked >= FRAMES // 2 and timings[1]["outline_every_model"] == tracked
    assert timings[0]["outline_every_model"] < 0.5 * tracked  # the shortcut serves most frames
    a, b = _numbers(whole), _numbers(every)
    assert np.array_equal(a[:, 6], b[:, 6])
    clip = scene["clip"]
    seen = (a[:, 6] == 1) & ~clip.occluded
    true = clip.truth_px - clip.truth_px[0]
    rmse = [float(np.sqrt(np.mean((r[seen, 2] - true[seen]) ** 2))) for r in (a, b)]
    difference = np.abs(a[seen, 2] - b[seen, 2])
    print(f"key's model first vs every model: RMSE {rmse[0]:.4f} / {rmse[1]:.4f} px, difference max "
          f"{difference.max():.4f} px, mean {difference.mean():.5f} px")
    assert rmse[0] <= rmse[1] + 0.001
    assert difference.max() < 0.1 and difference.mean() < 0.003
    # The uncertainty keeps the key's models' disagreement: of the same size as each frame's own
    # (1.227 before 2026-12-06; 1.258 since the profiles a codec copied from the reference are left
    # out of each frame's fit, its own models then agreeing a little better than its key's; the
    # readings the same to the last digit either way; without the key's disagreement the ratio
    # would be that of the covariance alone, 4-10 times smaller on the bench).
    ratio = np.median(a[seen, 7] / b[seen, 7])
    print(f"sigma_dx_px, key's models first / every model: median ratio {ratio:.3f}")
    assert 0.8 < ratio < 1.3


def test_frames_stand_alone_where_there_is_nothing_to_track(scene) -> None:
    """Chains only where the member's edges can be tracked: not for the dense ablation, not
    with background points (their flow needs the dense solve), not with warm=false; and a
    NaN starting guess makes the edge fit fail, never the run."""
    from flow.methods.deepflow.method import DeepFlow, DeepFlowDense

    clip = scene["clip"]
    reference, mask = clip.frames[0], clip.mask
    wall = np.zeros_like(mask)
    wall[:10, :10] = True
    cases = [(DeepFlow(), None, CHAIN_LENGTH), (DeepFlow(), wall, 0), (DeepFlowDense(), None, 0),
             (DeepFlow(warm=False), None, 0)]
    for method, read, expected in cases:
        method.bind(reference, mask, read=read)
        assert method.chain_length == expected, (type(method).__name__, read is None)
    member = cases[0][0]._regions[0].member
    prior = np.zeros((member.n_profiles, 2))
    prior[0] = np.nan  # one outline without dense flow: the least-squares guess is all NaN
    assert not member.fit(clip.frames[5], prior).ok
    with pytest.raises(ValueError, match="crop must be true or false"):
        DeepFlow(crop=None)
