"""The default method on a painted member whose grey lies within the wall's: no under-read.

The clips are generated here (see ``tests/unit/_lowtex_clip.py``): a member with two grey
levels of paint texture over a textured wall of the same range of greys, exact sub-pixel
truth, H.264. What a user runs: ``refflow track VIDEO --mask MASK`` with no options.
"""

from __future__ import annotations

import csv
import json
import re
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from flow.cli import main

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402

SLOPE_TOLERANCE = 0.015


def _track(tmp_path: Path, clip, name: str, *, crf: int = 12, mask: np.ndarray | None = None,
           extra: tuple[str, ...] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    video = tmp_path / f"{clip.frames.shape[0]}_{crf}.mp4"
    if not video.exists():
        encode(clip, video, crf=crf)
    mask_png = tmp_path / f"{name}_mask.png"
    cv2.imwrite(str(mask_png), (clip.mask if mask is None else mask).astype(np.uint8) * 255)
    out = tmp_path / f"{name}.csv"
    assert main(["track", str(video), "--mask", str(mask_png), "--out", str(out), "--no-progress", *extra]) == 0
    with out.open() as handle:
        rows = list(csv.DictReader(handle))
    key = "dx_px" if clip.axis == "x" else "dy_px"
    measured = np.array([float(r[key]) for r in rows])
    sigma = np.array([float(r["sigma_" + key]) for r in rows])
    valid = np.array([r["valid"] == "1" for r in rows])
    return measured, sigma, valid


def _slope_rmse(measured: np.ndarray, truth: np.ndarray, use: np.ndarray) -> tuple[float, float]:
    true = truth - truth[0]
    slope = float(np.polyfit(true[use], measured[use], 1)[0])
    rmse = float(np.sqrt(np.mean((measured[use] - true[use]) ** 2)))
    return slope, rmse


@pytest.mark.parametrize("axis, bend", [("x", 0.0), ("y", 0.3)])
def test_default_method_reads_a_low_contrast_member_without_under_reading(tmp_path, axis, bend) -> None:
    clip = make_clip(seed=11 if axis == "x" else 12, frames=60, axis=axis, bend=bend)
    # The member's grey lies within the wall's range: its edges are weak where the wall matches it.
    wall = clip.frames[0][~(cv2.dilate(clip.mask.astype(np.uint8), np.ones((25, 25), np.uint8)) > 0)]
    member = float(np.median(clip.frames[0][clip.mask]))
    assert np.percentile(wall, 5) < member < np.percentile(wall, 95)

    measured, sigma, valid = _track(tmp_path, clip, f"member_{axis}")
    use = valid & np.isfinite(measured)
    slope, rmse = _slope_rmse(measured, clip.truth_px, use)
    true = clip.truth_px - clip.truth_px[0]
    covered = float(np.mean(np.abs(measured[use][1:] - true[use][1:]) < 2 * sigma[use][1:]))
    print(f"axis {axis} bend {bend}: slope {slope:.4f}, RMSE {rmse:.4f} px, 2-sigma coverage {covered:.2f}")
    assert use.mean() >= 0.95
    assert abs(slope - 1.0) <= SLOPE_TOLERANCE
    assert rmse <= 0.08
    assert covered >= 0.9
    # The slope check can fail: a 5 % under-read (what the dense flow alone gives) is caught.
    under, _ = _slope_rmse(0.95 * measured, clip.truth_px, use)
    assert abs(under - 1.0) > SLOPE_TOLERANCE


def _reads_the_member_through(tmp_path: Path, clip, loose: np.ndarray, name: str) -> str:
    """Track ``clip`` through the ``loose`` mask with the defaults and with DIS; assert the
    default reads the member (slope, RMSE well under DIS's, 2-sigma coverage); its note on the
    mask drawn past the member, which DIS has not."""
    measured, sigma, valid = _track(tmp_path, clip, name, crf=18, mask=loose)
    use = valid & np.isfinite(measured)
    slope, rmse = _slope_rmse(measured, clip.truth_px, use)
    dis, _, dis_valid = _track(tmp_path, clip, f"{name}_dis", crf=18, mask=loose, extra=("--method", "dis"))
    dis_slope, dis_rmse = _slope_rmse(dis, clip.truth_px, dis_valid)
    true = clip.truth_px - clip.truth_px[0]
    covered = float(np.mean(np.abs(measured[use][1:] - true[use][1:]) < 2 * sigma[use][1:]))
    print(f"{name} mask: slope {slope:.4f}, RMSE {rmse:.4f} px, coverage {covered:.2f}; "
          f"DIS {dis_slope:.4f}, {dis_rmse:.4f} px")
    assert use.mean() >= 0.95
    assert abs(slope - 1.0) <= 2 * SLOPE_TOLERANCE and rmse <= 0.1 and rmse < 0.5 * dis_rmse
    assert covered >= 0.9
    note = next(note for note in json.loads((tmp_path / f"{name}.json").read_text())["notes"]
                if "past a sharp step of its grey" in note)
    assert int(re.search(r"read (\d+) of 60 frames", note).group(1)) >= 55, note
    assert not any("past a sharp step of its grey" in note
                   for note in json.loads((tmp_path / f"{name}_dis.json").read_text())["notes"])
    return note


def test_a_mask_drawn_past_the_members_outlines_reads_the_member(tmp_path) -> None:
    # A user's loose mask: the bar and 6 px of the wall beyond each of its edges. Grown from it,
    # the member's grey held the wall's and its outline was refused; the dense flow over the
    # faint paint, with the wall's pixels averaged in, read 0.56 px RMSE, slope 0.67, its sigma
    # 0.04 px (DIS 0.23 px, slope 0.85). The outline found inside the mask reads what a mask
    # drawn inside does.
    clip = make_clip(seed=3, frames=60, amplitude=2.0, height=200)
    x0 = (clip.mask.shape[1] - 32) // 2
    loose = np.zeros(clip.mask.shape, bool)
    loose[clip.mask.any(axis=1), x0 - 6:x0 + 38] = True
    _reads_the_member_through(tmp_path, clip, loose, "loose")


def test_a_mask_drawn_past_the_members_free_end_reads_the_member(tmp_path) -> None:
    # A cantilever's tip with the still, textured wall below it, the mask drawn 12 px past the
    # tip and 6 px past each edge: the wall was averaged in (0.57 px RMSE, slope 0.79, 2-sigma
    # coverage 0.10; DIS 0.30 px, slope 0.82). Cut at the tip and at the outlines, it reads what
    # a mask ending at the tip reads (0.08 px).
    clip = make_clip(seed=3, frames=60, amplitude=2.0, height=200, tip_row=150)
    rows = np.nonzero(clip.mask.any(axis=1))[0]
    cols = np.nonzero(clip.mask.any(axis=0))[0]
    loose = np.zeros(clip.mask.shape, bool)
    loose[rows.min():162, cols.min() - 12:cols.max() + 13] = True
    note = _reads_the_member_through(tmp_path, clip, loose, "tip")
    assert re.search(r"up to 1[234] px", note), note
