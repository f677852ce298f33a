"""The typed options and run information of flow.pipeline (flow.options), without a video."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import pytest

from flow.io.errors import InputError
from flow.options import FramesInfo, InputInfo, OutputOptions, RunInfo, ScaleOptions
from flow.scale import MAX_MM_PER_PX, measurement_scale


def _run() -> RunInfo:
    return RunInfo(
        tool="refflow track",
        input=InputInfo(path="clip.mp4", frame_size=[480, 320], fps=60.0, rotation_deg=0, bit_depth=8,
                        measured_bits=8, header_frames=180, frames_decoded=60, frames_measured=60, truncated=False),
        frames=FramesInfo(first=0, stop=60, requested="0:60"),
        method="dis", method_kind="dense", parameters={"preset": "medium"}, reference_frame=0,
        reference_average=1, jobs=1, roi={"x": 0, "y": 0, "width": 480, "height": 320}, calibration=None,
        poi={"count": 10, "centroid_px": [1.0, 2.0]}, background=None, reference_digest="abc",
        timings={"setup_s": 0.1, "frames_s": 1.0})


def test_a_part_round_trips_through_its_stored_meta() -> None:
    run = _run()
    meta = json.loads(json.dumps(run.part_meta(["a note"]), sort_keys=True))  # as save_raw_tracks stores it
    assert meta["identity"]["reference_digest"] == "abc" and meta["identity"]["frame_size"] == [480, 320]
    assert meta["notes"] == ["a note"] and "versions" in meta and "parts" not in meta
    assert RunInfo.from_part(meta) == run


def test_the_sidecar_record_holds_neither_identity_nor_timings() -> None:
    run = _run()
    record = run.record()
    assert not {"identity", "timings", "reference_digest", "parts"} & set(record)
    assert record["input"]["frame_size"] == [480, 320] and record["frames"]["requested"] == "0:60"
    merged = replace(run, tool="refflow merge", parts=[{"file": "p.npz", "frames": [0, 60]}])
    assert merged.record()["parts"] == [{"file": "p.npz", "frames": [0, 60]}]


def test_outputs_are_written_in_order_with_the_csv_last() -> None:
    outputs = OutputOptions(csv="out/m.csv", raw_tracks="r.npz", poi_tracks="p.npz")
    assert outputs.paths() == [Path("r.npz"), Path("p.npz"), Path("out/m.json"), Path("out/m.csv")]
    assert OutputOptions(raw_tracks="r.npz").paths() == [Path("r.npz")]


def test_scale_without_a_calibration_and_its_limit() -> None:
    scale = measurement_scale(ScaleOptions(known_length=10.0, between="0,0,20,0"), None, (100, 100))
    assert scale.mm_per_px == pytest.approx(0.5) and scale.given and "undistorted" not in scale.source
    nothing = measurement_scale(ScaleOptions(), None, None)
    assert not nothing.given and nothing.mm_per_px != nothing.mm_per_px  # NaN
    with pytest.raises(InputError, match="kilometre"):
        measurement_scale(ScaleOptions(mm_per_px=MAX_MM_PER_PX), None, None)
