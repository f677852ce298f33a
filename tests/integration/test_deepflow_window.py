"""A small member in a large frame: ``deepflow``'s window and matching reach follow the member
and its motion, not the frame (issue 31).

The default's matching reach once grew with the frame (a tenth of its longer side), and the
window solved and the matching's memory with it: a 500x300 px member in a 4K frame took 23 GB.
Now a measurement searches :data:`BASE_REACH_PX` (or twice its chain's motion so far) and is
solved again with the reach doubled where the motion found comes past half of it, so that a
run without ``--roi`` gives the very numbers of a run with an ``--roi`` holding the window.
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
from flow.methods.base import CROP_MARGIN_PX
from flow.methods.deepflow.method import BASE_REACH_PX, MEMBER_CONTEXT_PX, WIDEN_SHARE, DeepFlow

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402

FRAMES = 40
WIDTH, HEIGHT = 1280, 800  # the frame: eight times the clip's width
AT = (560, 340)  # where the 160x120 clip lies in it (x, y)
# Frames 18-25 jump 20 px further: past half the base reach, so the reach is widened there.
JUMP = (0.30, 0.43, 20.0)


@pytest.fixture(scope="module")
def scene(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("window")
    clip = make_clip(seed=31, frames=FRAMES, height=120, width=160, bar_width=28, amplitude=2.5, jump=JUMP)
    frames = np.full((FRAMES, HEIGHT, WIDTH), 128, np.uint8)
    frames[:, AT[1]:AT[1] + 120, AT[0]:AT[0] + 160] = clip.frames
    mask = np.zeros((HEIGHT, WIDTH), np.uint8)
    mask[AT[1]:AT[1] + 120, AT[0]:AT[0] + 160] = clip.mask * 255
    big = type(clip)(frames, mask > 0, clip.truth_px, clip.axis, clip.fps, clip.occluded)
    video = encode(big, folder / "big.mp4", crf=12)
    cv2.imwrite(str(folder / "mask.png"), mask)
    rows, cols = np.nonzero(mask)
    # The widest window the method may take: the frames are measured cut to it.
    margin = DeepFlow().max_window_margin(mask.shape)
    window = (cols.min() - margin, rows.min() - margin, np.ptp(cols) + 1 + 2 * margin, np.ptp(rows) + 1 + 2 * margin)
    return {"video": video, "mask": folder / "mask.png", "folder": folder, "window": window}


def _run(scene: dict, name: str, *extra: str) -> tuple[list[dict], dict]:
    out = scene["folder"] / f"{name}.csv"
    assert main(["track", str(scene["video"]), "--mask", str(scene["mask"]), "--mm-per-px", "1",
                 "--no-progress", "--jobs", "2", *extra, "--out", str(out)]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    return rows, json.loads(out.with_suffix(".json").read_text())


def test_without_roi_the_numbers_of_an_roi_holding_the_window(scene):
    whole, whole_side = _run(scene, "whole")
    cropped, cropped_side = _run(scene, "roi", "--roi", ",".join(str(int(v)) for v in scene["window"]))
    assert len(whole) == len(cropped) == FRAMES
    assert whole == cropped
    # The jump took the reach past its base in both runs, the same number of times.
    assert whole_side["timings"]["reach_widened"] == cropped_side["timings"]["reach_widened"] >= 1
    assert whole_side["timings"]["full_frames"] == cropped_side["timings"]["full_frames"]
    jumped = [float(r["dx_px"]) for r in whole[19:25]]
    assert min(jumped) > 15.0, jumped
    # The POIs are where they were, in the frame's pixels, though the frames were measured cut.
    assert whole_side["poi"]["centroid_px"] == cropped_side["poi"]["centroid_px"]


def test_the_reach_and_window_follow_the_motion_not_the_frame():
    """Bound to a 60x40 px patch in a 1920x1080 frame, a still pair is solved at the base reach
    in the patch's box plus the crop margin; a 24 px motion (past half the base reach) widens
    the reach to twice the base, is found, and the window stays a patch's, not a frame's."""
    rng = np.random.default_rng(3)
    texture = cv2.GaussianBlur(rng.uniform(0, 255, (1080, 1920)).astype(np.float32), (0, 0), 2.0)
    reference = np.clip(texture, 0, 255).astype(np.uint8)
    mask = np.zeros(reference.shape, bool)
    mask[500:540, 900:960] = True
    method = DeepFlow(member=False, texture=False, preset="fast")
    method.bind(reference, mask)
    still = method.calc(reference, reference)
    assert method.last_reach_px == BASE_REACH_PX and method.counts["reach_widened"] == 0
    solved = np.isfinite(still[..., 0])
    rows, cols = np.nonzero(solved)
    margin = method.window_margin(reference.shape)
    assert margin == max(CROP_MARGIN_PX, int(BASE_REACH_PX))
    assert method.max_window_margin(reference.shape) >= MEMBER_CONTEXT_PX
    assert (rows.min(), rows.max() + 1, cols.min(), cols.max() + 1) == (500 - margin, 540 + margin,
                                                                        900 - margin, 960 + margin)
    moved = np.ascontiguousarray(np.roll(reference, 24, axis=1))
    assert 24 > WIDEN_SHARE * BASE_REACH_PX
    flow = method.calc(reference, moved)
    assert method.last_reach_px == 2 * BASE_REACH_PX and method.counts["reach_widened"] == 1
    assert abs(float(np.median(flow[mask][:, 0])) - 24.0) < 0.1
    assert np.isfinite(flow[..., 0]).sum() < 0.05 * reference.size


def test_a_long_reach_is_matched_coarser_to_stay_within_the_memory_budget():
    """The matching's response volumes grow with the window's area times the reach squared:
    a reach that would pass MATCH_BUDGET_BYTES is searched at a coarser downscale instead."""
    from flow.methods.deepflow.deepmatching import MatchParams, response_bytes
    from flow.methods.deepflow.method import MATCH_BUDGET_BYTES, MAX_REACH_PX, _match_at

    window = (300 + 2 * int(MAX_REACH_PX), 500 + 2 * int(MAX_REACH_PX))
    base = MatchParams()
    assert response_bytes(window, MatchParams(ngh_rad=MAX_REACH_PX)) > MATCH_BUDGET_BYTES
    wide = _match_at(base, MAX_REACH_PX, window, (2160, 3840))
    assert wide.ngh_rad == MAX_REACH_PX and wide.downscale > base.downscale
    assert response_bytes(window, wide) <= MATCH_BUDGET_BYTES
    near = _match_at(base, BASE_REACH_PX, (300 + 128, 500 + 128), (2160, 3840))
    assert near.downscale == base.downscale and near.ngh_rad == BASE_REACH_PX


def test_a_whole_image_search_is_matched_coarser_or_refused_within_the_memory_budget():
    """``ngh_rad=0`` (the whole image) keeps to MATCH_BUDGET_BYTES as any reach does: matched
    coarser where that fits (before 2026-12-05 it was exempt, and Middlebury's 741x500
    Motorcycle pair took 24 GB and was killed), refused with the longest radius that fits
    where even the coarsest matching would not (a 1080p frame)."""
    from flow.io.errors import InputError
    from flow.methods.deepflow.deepmatching import MatchParams, response_bytes
    from flow.methods.deepflow.method import MATCH_BUDGET_BYTES, _match_at

    whole = MatchParams(ngh_rad=0)
    assert response_bytes((500, 741), whole) > 10 * MATCH_BUDGET_BYTES
    coarse = _match_at(whole, None, (500, 741), (500, 741))
    assert coarse.ngh_rad == 0 and coarse.downscale > whole.downscale
    assert response_bytes((500, 741), coarse) <= MATCH_BUDGET_BYTES
    with pytest.raises(InputError, match=r"ngh_rad=0 searches the whole 1920x1080 px image .* at most (\d+) px") as err:
        _match_at(whole, None, (1080, 1920), (1080, 1920))
    radius = int(str(err.value).split("--param ngh_rad=")[1].split(")")[0])
    fits = _match_at(MatchParams(ngh_rad=radius), None, (1080, 1920), (1080, 1920))
    assert response_bytes((1080, 1920), fits) <= MATCH_BUDGET_BYTES
    with pytest.raises(InputError):
        _match_at(MatchParams(ngh_rad=2 * radius + 64), None, (1080, 1920), (1080, 1920))
    # The default's own reach is never refused (a 24 Mpx still's whole frame: as before).
    assert _match_at(MatchParams(), None, (4000, 6000), (4000, 6000)).downscale == 8


def test_the_field_of_frames_cut_to_the_work_area_sits_where_the_pixels_are(scene):
    """``--field`` with frames cut to the method's work area (issue 33 over issue 31): the mask
    pixels' field is read from the cut flow at their own place, so the mean over the kept
    pixels is the CSV's reading, frame by frame."""
    import h5py

    out = scene["folder"] / "field.csv"
    rows, _ = _run(scene, "field", "--field", str(out.with_suffix(".h5")))
    with h5py.File(out.with_suffix(".h5"), "r") as f:
        kept = f["kept"][()] == 1
        assert kept.any() and float(f["x_px"][0]) >= AT[0]
        for row in rows:
            index = int(row["frame"])
            mean = float(np.nanmean(f["u_px"][index][kept].astype(np.float64)))
            assert mean == pytest.approx(float(row["dx_px"]), abs=2e-6), index
