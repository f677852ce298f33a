"""What the user asked a measurement for (the options of ``refflow track`` and ``merge``) and
what the run records (its sidecar's run information), as typed objects.

The CLI turns its arguments into these; :mod:`flow.pipeline` reads only these. Option values
are kept as the user wrote them (``"X,Y,W,H"``, ``"START:END"``): the pipeline parses and
checks them, so its messages name the option and quote the text.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from flow.io.camfiles import companion_files
from flow.measure.quality import MAX_TYPICAL_SIGMA_PX
from refflow.io import versions


@dataclass(frozen=True)
class SourceOptions:
    """The video and how to read it: crop, frame rate, lens."""

    input: str
    roi: str | None = None  # X,Y,W,H in raw full-frame pixels
    fps: float | None = None
    calibration: str | None = None  # calibration JSON of `refflow calibrate`
    video_origin: str | None = None  # X,Y of the video on the calibrated sensor, or a JSON file
    allow_truncated: bool = False


@dataclass(frozen=True)
class RegionOptions:
    """Where the POIs are, drawn on the raw video frames: mask PNGs (labelled regions), or a
    rectangle, or a polygon; every ``grid_step``-th pixel of it."""

    masks: tuple[str, ...] = ()
    rect: str | None = None
    polygon: str | None = None
    grid_step: int = 1


@dataclass(frozen=True)
class BackgroundOptions:
    """The static scene whose image motion (the camera's) is removed from the POIs'."""

    mask: str | None = None
    rect: str | None = None
    model: str = "affine"


@dataclass(frozen=True)
class ScaleOptions:
    """At most one scale: mm per pixel, a known length between two raw points, or a file."""

    mm_per_px: float | None = None
    known_length: float | None = None
    between: str | None = None  # X1,Y1,X2,Y2 raw video pixels
    scale_file: str | None = None


@dataclass(frozen=True)
class FilterOptions:
    """The POI filter (paper eq. 10-12) and average; ``mode`` None: the method's default."""

    mode: str | None = None  # "paper", "median", "none"
    threshold_ratio: float = 0.5
    mcr_threshold: float = 0.5
    max_typical_sigma_px: float = MAX_TYPICAL_SIGMA_PX  # 0: never flag a clip for its precision


@dataclass(frozen=True)
class OutputOptions:
    """The files a run writes (none of them required alone; `track` needs csv or raw_tracks)."""

    csv: str | None = None  # the measurement; its sidecar is <csv>.json
    raw_tracks: str | None = None  # the unfiltered part, for `refflow merge`
    poi_tracks: str | None = None  # the per-POI displacement matrix (.npz)
    field: str | None = None  # the whole displacement field (.h5, flow/field/stream.py)

    def paths(self) -> list[Path]:
        """The files, in writing order (the CSV last: it is what other tools look for)."""
        return ([Path(self.raw_tracks)] if self.raw_tracks else []) \
            + ([Path(self.poi_tracks)] if self.poi_tracks else []) \
            + ([Path(self.field)] if self.field else []) \
            + ([Path(self.csv).with_suffix(".json"), Path(self.csv)] if self.csv else [])


@dataclass(frozen=True)
class TrackOptions:
    """Everything ``refflow track`` was asked."""

    source: SourceOptions
    region: RegionOptions = RegionOptions()
    method: str | None = None  # None: deepflow, else deepflow-opencv
    params: tuple[str, ...] = ()  # KEY=VALUE as given
    preset: str | None = None  # DIS preset
    reference_frame: int = 0
    reference_average: int = 1
    frames: str | None = None  # START:END
    max_frames: int | None = None
    background: BackgroundOptions = BackgroundOptions()
    scale: ScaleOptions = ScaleOptions()
    filter: FilterOptions = FilterOptions()
    outputs: OutputOptions = OutputOptions()
    jobs: int | None = None  # None: the cores this process may use
    progress: bool = True

    def input_paths(self) -> list[tuple[str, Path]]:
        """``(what, path)`` of every existing file the run reads (no output may be one)."""
        named = [("the video", self.source.input), *(("--mask", m) for m in self.region.masks),
                 ("--calibration", self.source.calibration), ("--scale-file", self.scale.scale_file),
                 ("--background-mask", self.background.mask), ("--video-origin", self.source.video_origin)]
        found = _existing(named)
        # A camera header's frames file (.mraw).
        return found + [("the recording's frames", path) for path in companion_files(self.source.input)]


@dataclass(frozen=True)
class MergeOptions:
    """Everything ``refflow merge`` was asked: the parts, then scale, filter and outputs as
    for ``track``."""

    parts: tuple[str, ...]
    scale: ScaleOptions = ScaleOptions()
    part_fields: tuple[str, ...] = ()  # each part's --field file, for --field
    filter: FilterOptions = FilterOptions()
    outputs: OutputOptions = OutputOptions()

    def input_paths(self) -> list[tuple[str, Path]]:
        return (_existing([("--scale-file", self.scale.scale_file)]) + [("a part", Path(p)) for p in self.parts]
                + [("a part's field", Path(p)) for p in self.part_fields])


def _existing(named: list[tuple[str, str | None]]) -> list[tuple[str, Path]]:
    return [(what, Path(value)) for what, value in named if value and Path(value).exists()]


@dataclass(frozen=True)
class InputInfo:
    """The video as read (sidecar ``input``)."""

    path: str
    frame_size: list[int]
    fps: float | None
    rotation_deg: int
    bit_depth: int
    measured_bits: int
    header_frames: int | None
    frames_decoded: int
    frames_measured: int
    truncated: bool


@dataclass(frozen=True)
class FramesInfo:
    """The frames measured, ``first`` to ``stop`` (exclusive), and ``--frames`` as given."""

    first: int
    stop: int
    requested: str | None


@dataclass(frozen=True)
class RunInfo:
    """What the sidecar records of a run (and a raw-tracks part of it, for `merge`).

    ``identity`` is what every part of one run shares; `refflow merge` refuses parts that
    differ in it. ``timings`` and the identity stay out of the measurement's sidecar (its
    timings are written with the total).
    """

    tool: str
    input: InputInfo
    frames: FramesInfo
    method: str
    method_kind: str  # "dense" or "sparse"
    parameters: dict[str, Any]
    reference_frame: int
    reference_average: int
    jobs: int
    roi: dict[str, int]
    calibration: dict[str, Any] | None  # pipeline.calibration_summary
    poi: dict[str, Any]
    background: dict[str, Any] | None
    reference_digest: str
    timings: dict[str, Any] = field(default_factory=dict)
    parts: list[dict[str, Any]] | None = None  # `merge`: each part's file and frames

    def identity(self) -> dict[str, Any]:
        return {"method": self.method, "parameters": self.parameters, "reference_frame": self.reference_frame,
                "reference_average": self.reference_average, "reference_digest": self.reference_digest,
                "roi": self.roi, "frame_size": self.input.frame_size, "header_frames": self.input.header_frames,
                "calibration": self.calibration, "poi": self.poi, "background": self.background}

    def record(self) -> dict[str, Any]:
        """The run as the measurement's sidecar records it (no identity, no timings)."""
        data = dataclasses.asdict(self)
        for key in ("timings", "reference_digest") + (("parts",) if self.parts is None else ()):
            data.pop(key)
        return data

    def part_meta(self, notes: list[str]) -> dict[str, Any]:
        """What a raw-tracks part stores (``track --raw-tracks``)."""
        return {**self.record(), "timings": self.timings, "identity": self.identity(), "notes": notes,
                "versions": versions()}

    @classmethod
    def from_part(cls, meta: dict[str, Any]) -> RunInfo:
        """The run of a part from its stored meta (:meth:`part_meta`)."""
        names = [f.name for f in dataclasses.fields(cls) if f.name not in ("input", "frames", "reference_digest")]
        return cls(input=InputInfo(**meta["input"]), frames=FramesInfo(**meta["frames"]),
                   reference_digest=meta["identity"]["reference_digest"],
                   **{name: meta[name] for name in names if name in meta})
