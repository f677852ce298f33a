"""A clip the images cannot resolve to a fraction of a pixel has every frame flagged.

A painted bar over a textured wall, x264 at CRF 30 (the paint's texture gone, the outlines
smeared): dis reads it about 0.7 px RMS off the truth and its own uncertainty says so (0.7 px
typical, a large part of the bar's swing), so `refflow track` flags every frame, says why on
stderr and in the sidecar, and keeps each frame's reading beside its flag; deepflow reads the
same clip to about a quarter of a pixel (typical uncertainty 0.21 px) and keeps its frames
valid. ``--max-typical-sigma 0`` vouches for dis's readings.
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
from flow.measure.quality import MAX_SIGMA_TO_RANGE

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402


@pytest.fixture(scope="module")
def clip(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("precision")
    made = make_clip(seed=0, frames=60)
    mask = folder / "mask.png"
    cv2.imwrite(str(mask), made.mask.astype(np.uint8) * 255)
    return {"video": encode(made, folder / "crf30.mp4", crf=30), "mask": mask,
            "truth": made.truth_px - made.truth_px[0]}


def _track(clip: dict, out: Path, *extra: str) -> tuple[list[dict[str, str]], dict]:
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--mm-per-px", "1", "--out", str(out),
                 "--no-progress", *extra]) == 0
    with out.open() as handle:
        return list(csv.DictReader(handle)), json.loads(out.with_suffix(".json").read_text())


def _rmse(rows: list[dict[str, str]], truth: np.ndarray) -> float:
    dx = np.array([float(r["dx_px"]) for r in rows])
    return float(np.sqrt(np.mean((dx - truth) ** 2)))


def test_an_unresolved_clip_is_flagged_and_a_resolved_one_is_not(clip, tmp_path, capsys) -> None:
    rows, meta = _track(clip, tmp_path / "dis.csv", "--method", "dis")
    err = capsys.readouterr().err
    assert meta["quality"]["unresolved"] is True and meta["quality"]["typical_sigma_px"] > 0.35
    assert meta["quality"]["frames_valid"] == 0 and meta["filter"]["max_typical_sigma_px"] == 0.35
    motion = meta["quality"]["motion"]
    assert motion["sigma_to_range"] > motion["max_sigma_to_range"] == MAX_SIGMA_TO_RANGE
    assert motion["sigma_to_range"] == pytest.approx(motion["sigma_px"] / motion["range_px"])
    assert all(r["valid"] == "0" for r in rows)
    assert "every frame is flagged valid=0, its reading kept" in err and "--max-typical-sigma 0" in err
    assert "of the motion's 5-95 % range" in err
    assert any("typical frame's standard uncertainty" in note for note in meta["notes"])
    # the flagged readings are in the file, and indeed not sub-pixel ones
    assert _rmse(rows, clip["truth"]) > 0.5
    kept, meta = _track(clip, tmp_path / "dis_kept.csv", "--method", "dis", "--max-typical-sigma", "0")
    assert meta["quality"]["unresolved"] is False and all(r["valid"] == "1" for r in kept)
    assert [r["dx_px"] for r in kept] == [r["dx_px"] for r in rows]
    # deepflow resolves the same clip and keeps every frame
    rows, meta = _track(clip, tmp_path / "deepflow.csv")
    assert meta["quality"]["unresolved"] is False and meta["quality"]["typical_sigma_px"] < 0.3
    assert all(r["valid"] == "1" for r in rows) and _rmse(rows, clip["truth"]) < 0.35


@pytest.mark.parametrize("value", ["-0.1", "nan", "inf"])
def test_a_bad_limit_is_refused_in_one_line(clip, tmp_path, capsys, value) -> None:
    out = tmp_path / "x.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--mm-per-px", "1", "--out", str(out),
                 "--no-progress", "--max-typical-sigma", value]) == 2
    err = capsys.readouterr().err.strip()
    assert "--max-typical-sigma" in err and len(err.splitlines()) == 1 and not out.exists()


def test_merge_measures_again_and_plot_says_what_it_lacks(clip, tmp_path, capsys) -> None:
    """The verdict is the measurement's own: a part's raw tracks carry no "flagged" note, so a
    merge with another limit is not contradicted by its part; `refflow plot` of a flagged CSV
    beside a measured one says so and takes the spectra's axis from the one that has values."""
    part, flagged = tmp_path / "part.npz", tmp_path / "flagged.csv"
    assert main(["track", str(clip["video"]), "--mask", str(clip["mask"]), "--mm-per-px", "1", "--method", "dis",
                 "--out", str(flagged), "--raw-tracks", str(part), "--no-progress"]) == 0
    for limit, unresolved in (("0", False), ("0.35", True)):
        merged = tmp_path / f"merged{limit}.csv"
        assert main(["merge", str(part), "--mm-per-px", "1", "--max-typical-sigma", limit, "--out", str(merged)]) == 0
        meta = json.loads(merged.with_suffix(".json").read_text())
        notes = [n for n in meta["notes"] if "every frame is flagged" in n]
        assert meta["quality"]["unresolved"] is unresolved and len(notes) == int(unresolved)
    assert "refflow merge: warning: the typical frame's" in capsys.readouterr().err
    measured = tmp_path / "measured.csv"
    _track(clip, measured)
    capsys.readouterr()
    assert main(["plot", str(flagged), str(measured), "--units", "px", "--out", str(tmp_path / "p.png")]) == 0
    out = capsys.readouterr()
    assert "has no valid frame: its flagged readings are drawn grey" in out.err and "spectra plotted: dx" in out.out
