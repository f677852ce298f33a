"""Modal identification of a user's video, end to end: four painted bars side by side in one
H.264 video are four points of a structure that vibrates in two modes (free decay, known
frequencies, damping and shapes). One `refflow track` with a labelled mask measures the four
regions, `refflow modal` on its CSV identifies the modes: the frequencies come back within
0.5 %, the shapes with MAC > 0.99 (and not the other mode's), and the modes are drawn over the
reference frame and animated."""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from PIL import Image, ImageSequence

from flow.cli import main
from refflow.modal import mac

sys.path.insert(0, str(Path(__file__).parents[1] / "unit"))
from _lowtex_clip import encode, make_clip  # noqa: E402

FPS = 60.0
FRAMES = 480  # 8 s: 18 cycles of the first mode
MODES = ((2.3, 0.010, 2.5), (7.7, 0.008, 0.9))  # Hz, damping ratio, largest amplitude (px)
SHAPES = (np.array([0.18, 0.45, 0.75, 1.0]), np.array([0.75, 1.0, 0.2, -0.8]))


def history(seed: int = 5) -> np.ndarray:
    """(4, FRAMES) px: each bar's displacement, the two modes' free decays."""
    rng = np.random.default_rng(seed)
    t = np.arange(FRAMES) / FPS
    out = np.zeros((4, FRAMES))
    for shape, (f, zeta, amplitude) in zip(SHAPES, MODES, strict=True):
        wd = 2 * np.pi * f * np.sqrt(1 - zeta ** 2)
        q = amplitude * np.exp(-zeta * 2 * np.pi * f * t) * np.cos(wd * t + rng.uniform(0, 2 * np.pi))
        out += np.outer(shape, q)
    return out


@pytest.fixture(scope="module")
def identified(tmp_path_factory) -> dict:
    folder = tmp_path_factory.mktemp("modal_regions")
    bars = [make_clip(seed=50 + i, frames=FRAMES, fps=FPS, height=96, width=64, bar_width=20, mask_margin=5,
                      motion_px=motion) for i, motion in enumerate(history())]
    video = encode(dataclasses.replace(bars[0], frames=np.concatenate([b.frames for b in bars], axis=2)),
                   folder / "bars.mp4", crf=12)
    labels = np.concatenate([(i + 1) * b.mask.astype(np.uint8) for i, b in enumerate(bars)], axis=1)
    cv2.imwrite(str(folder / "labels.png"), labels)
    out = folder / "bars.csv"
    assert main(["track", str(video), "--mask", str(folder / "labels.png"), "--no-progress",
                 "--out", str(out)]) == 0
    modes_json = folder / "modes.json"
    assert main(["modal", str(out), "--out", str(modes_json), "--modes", "2"]) == 0
    return {"folder": folder, "result": json.loads(modes_json.read_text()), "truth": [b.truth_px for b in bars]}


def test_frequencies_and_shapes_of_a_video(identified) -> None:
    result = identified["result"]
    assert [p["region"] for p in result["points"]] == [1, 2, 3, 4]
    modes = sorted(result["modes"], key=lambda m: m["freq_hz"])
    assert len(modes) == 2
    for mode, shape, (f, zeta, _) in zip(modes, SHAPES, MODES, strict=True):
        error = mode["freq_hz"] / f - 1
        fit = mac(np.asarray(mode["shape"]), shape)
        print(f"{f} Hz: identified {mode['freq_hz']:.4f} Hz ({100 * error:+.3f} %), damping "
              f"{mode['damping_ratio']} (true {zeta}), MAC {fit:.5f}")
        assert abs(error) <= 0.005
        assert fit > 0.99
        assert mode["damping_ratio"] is not None and 0.3 * zeta < mode["damping_ratio"] < 3 * zeta
    # The MAC can fail: each identified shape is not the other mode's.
    assert mac(np.asarray(modes[0]["shape"]), SHAPES[1]) < 0.9
    assert mac(np.asarray(modes[1]["shape"]), SHAPES[0]) < 0.9


def test_modes_drawn_over_the_video_and_animated(identified) -> None:
    folder, result = identified["folder"], identified["result"]
    frame = cv2.imread(str(folder / "modes_shapes_frame.png"))
    assert frame is not None and frame.shape[0] > 200
    positions = np.array([p["position_px"] for p in result["points"]])
    np.testing.assert_allclose(positions[:, 0], 32 + 64 * np.arange(4), atol=2.0)  # each over its bar
    for mode in result["modes"]:
        with Image.open(folder / f"modes_mode{mode['mode']}.gif") as gif:
            frames = [np.asarray(f.convert("RGB"), np.int16) for f in ImageSequence.Iterator(gif)]
        assert len(frames) == 24 and frames[0].shape[:2] == (96, 256)
        # The points swing: a quarter cycle on, the picture has changed.
        assert np.abs(frames[6] - frames[0]).max() > 100
    assert not result["notes"] or all("not drawn" not in note for note in result["notes"])
