"""Real footage: the Tacoma Narrows clip (pyidi, MIT) runs end to end with a periodic signal."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from flow.cli import main

CLIP = Path(__file__).resolve().parents[2] / ".." / "shared" / "data" / "tacoma_bridge.mp4"
DECK = "0,160,140,125,190,120,190,215,0,215"  # polygon on the deck surface and curb, frame 0


@pytest.mark.skipif(not CLIP.is_file(), reason=f"shared test data absent: {CLIP} (see shared/data/README.md)")
def test_tacoma_deck_displacement_is_periodic(tmp_path) -> None:
    out = tmp_path / "tacoma.csv"
    frames = 120  # 4 s at 30 fps: more than one period of the deck's ~3.4 s twist
    rc = main(["track", str(CLIP), "--polygon", DECK, "--roi", "0,110,200,110", "--grid-step", "4",
               "--method", "dis", "--max-frames", str(frames), "--out", str(out), "--no-progress"])
    assert rc == 0
    with open(out, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert len(rows) == frames
    valid = np.array([int(r["valid"]) for r in rows])
    assert valid.mean() > 0.95
    dy = np.array([float(r["dy_px"]) for r in rows])
    dy = dy[np.isfinite(dy)]
    assert np.ptp(dy) > 5.0, "the deck twists by several pixels"
    centred = dy - np.median(dy)
    crossings = np.count_nonzero(np.diff(np.sign(centred[np.abs(centred) > 1.0])))
    assert crossings >= 2, "the deck must go up and down at least once"
    meta = json.loads(out.with_suffix(".json").read_text())
    assert meta["input"]["frames_measured"] == frames and not meta["input"]["truncated"]
