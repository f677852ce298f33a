"""The video reader: any file OpenCV's ffmpeg backend decodes, frame after frame, with the
frames' own time stamps.

A video that cannot be measured whole is an error, not a warning: a file that OpenCV cannot
open is diagnosed with the ffmpeg of ``imageio-ffmpeg`` (no frames at all, or not a video),
and a file that stops decoding well before its container's duration is truncated (see
:class:`VideoSource`).
"""

from __future__ import annotations

import math
import os
import re
import subprocess
import warnings
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np

from flow.io.errors import InputError
from flow.io.frames import FrameSource, Roi

__all__ = ["DISPLAY_ROTATIONS", "VideoSource", "diagnose_unreadable", "open_video",
           "quiet_decoder_logs"]

# Frame intervals that differ from their median by more than this share (and by more than
# VFR_SLACK_S, a container's time base rounding: Matroska keeps milliseconds) make a clip's
# frame rate variable.
VFR_SHARE = 0.1
VFR_SLACK_S = 0.0015
# x264 writes its settings (``x264 - core ... crf=18.0 ...``) into the first frame's SEI; a
# container holds it within its first megabytes (before or after the index).
X264_SEARCH_BYTES = 4 << 20


# OpenCV's display rotations (CAP_PROP_ORIENTATION_META) as cv2.rotate codes.
DISPLAY_ROTATIONS = {90: cv2.ROTATE_90_CLOCKWISE, 180: cv2.ROTATE_180, 270: cv2.ROTATE_90_COUNTERCLOCKWISE}


# OpenCV's ffmpeg backend reads its log level once, at the first VideoCapture or VideoWriter of
# the process, whoever makes it: hence here, on import, and not in quiet_decoder_logs.
os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")  # AV_LOG_QUIET


def quiet_decoder_logs() -> None:
    """Keep OpenCV and its ffmpeg backend from printing their own error lines on stderr.

    refflow diagnoses unreadable files itself and reports one line; the decoders' noise
    (``[ERROR:0@...] loadsave.cpp ... can't read header``, ffmpeg's ``moov atom not found``)
    would bury it. Called at the start of ``refflow``; ffmpeg's level is set when this module
    is imported. A level the user exported (``OPENCV_LOG_LEVEL``, ``OPENCV_FFMPEG_LOGLEVEL``,
    to debug a file) is kept.
    """
    if "OPENCV_LOG_LEVEL" not in os.environ:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


def open_video(path: Path) -> cv2.VideoCapture:
    """``path`` opened by OpenCV's ffmpeg backend only: not as an image sequence, nor by its own
    AVI parser (both print on stderr, and ffmpeg reads every container they do)."""
    return cv2.VideoCapture(str(path), cv2.CAP_FFMPEG)


def _ffmpeg_report(path: Path) -> tuple[str | None, int | None]:
    """What ffmpeg sees in ``path``: ``(stderr of opening it, video packets)``.

    ``(None, None)`` when the ffmpeg of imageio-ffmpeg is not available;
    packets is None when the file has no video stream or cannot be opened.
    """
    try:
        import imageio_ffmpeg

        exe = imageio_ffmpeg.get_ffmpeg_exe()
    except (ImportError, RuntimeError):
        return None, None
    try:
        opened = subprocess.run([exe, "-nostdin", "-hide_banner", "-i", str(path)],
                                capture_output=True, text=True, errors="replace", timeout=60)
        if not re.search(r"Stream #\S+: Video:", opened.stderr):
            return opened.stderr, None
        # Count the video packets without decoding: one framecrc line per packet.
        counted = subprocess.run([exe, "-nostdin", "-v", "error", "-i", str(path), "-map", "0:v:0",
                                  "-c", "copy", "-f", "framecrc", "-"],
                                 capture_output=True, text=True, errors="replace", timeout=300)
    except (OSError, subprocess.TimeoutExpired):
        return None, None
    packets = [ln for ln in counted.stdout.splitlines() if ln.strip() and not ln.startswith("#")]
    return opened.stderr, len(packets)


def x264_crf(path: Path) -> float | None:
    """The ``crf`` x264 wrote into the stream's settings (its SEI text), None where the stream
    holds no such text within :data:`X264_SEARCH_BYTES` (another encoder: a phone's hardware
    encoder does not say)."""
    with path.open("rb") as handle:
        head = handle.read(X264_SEARCH_BYTES)
    start = head.find(b"x264 - core")
    if start < 0:
        return None
    found = re.search(rb"\bcrf=([0-9]+(?:\.[0-9]+)?)", head[start:start + 4096])
    return float(found.group(1)) if found else None


def _starts_like_mp4(path: Path) -> bool:
    with path.open("rb") as handle:
        return handle.read(12)[4:8] in (b"ftyp", b"wide", b"mdat", b"free")


# Where an MP4/MOV keeps its index: after the file type box (``+faststart``, phones), or last.
MOOV_SEARCH_BYTES = 16 << 20


def _holds_moov(path: Path) -> bool:
    """Whether the first or last :data:`MOOV_SEARCH_BYTES` of ``path`` hold a complete ``moov``
    box (its declared size within the file), whether or not the boxes before it lead there."""
    length = path.stat().st_size
    with path.open("rb") as handle:
        for start in sorted({0, max(length - MOOV_SEARCH_BYTES, 0)}):
            handle.seek(start)
            data = handle.read(MOOV_SEARCH_BYTES)
            at = data.find(b"moov", 4)
            while at != -1:
                size = int.from_bytes(data[at - 4:at], "big")
                if size >= 8 and start + at - 4 + size <= length:
                    return True
                at = data.find(b"moov", at + 1)
    return False


def mp4_missing_bytes(path: Path) -> int:
    """Bytes an MP4/MOV file's top-level boxes declare beyond its end (0: complete, or not
    an MP4). A recording cut short after its index was written (``+faststart``, as phones
    write) keeps its frame count but loses the end of its ``mdat``: seen here at once,
    without decoding a frame."""
    if not _starts_like_mp4(path):
        return 0
    length = path.stat().st_size
    offset = 0
    with path.open("rb") as handle:
        while offset + 8 <= length:
            handle.seek(offset)
            header = handle.read(16)
            size = int.from_bytes(header[:4], "big")
            if size == 1 and len(header) >= 16:  # 64-bit size follows the type
                size = int.from_bytes(header[8:16], "big")
            elif size == 0:  # the box runs to the end of the file
                return 0
            if size < 8:
                return 0  # not a box structure we understand: leave it to the decoder
            if offset + size > length:
                return offset + size - length
            offset += size
    return 0


def diagnose_unreadable(path: Path) -> str:
    """One-line reason why OpenCV cannot open the video ``path``, and what to do."""
    name = str(path)
    if path.suffix.lower() == ".mraw":  # the frames alone: size, depth and rate are in the header
        header = next((h for h in (path.with_suffix(s) for s in (".cih", ".cihx", ".CIH", ".CIHX")) if h.is_file()),
                      None)
        return (f"{name!r} holds the frames of a Photron recording, without their size and rate: open the .cih "
                f"(the Photron header) {'beside it' if header is None else repr(str(header))} instead")
    if path.stat().st_size == 0:
        return f"video {name!r} is empty (0 bytes): copy it again from the camera"
    opened, packets = _ffmpeg_report(path)
    if opened is not None and "Input #0" in opened:
        if packets is None:
            return (f"video {name!r} has no frames: the container holds no video stream; "
                    "export or record the video again")
        if packets == 0:
            return (f"video {name!r} has no frames: the container has a video stream but no frame "
                    "in it; export or record the video again")
        return (f"video {name!r} holds {packets} frames that this OpenCV build cannot decode: "
                "convert it, e.g. `ffmpeg -i IN -c:v libx264 -crf 12 OUT.mp4`")
    if opened is not None and "moov atom not found" in opened and _starts_like_mp4(path):
        if _holds_moov(path):
            return (f"video {name!r} is damaged: it holds its MP4/MOV index (moov atom), but the boxes "
                    "leading to it are broken (a disk or copy error); copy it again from the camera, or "
                    "try a repair tool (e.g. untrunc) with a good file from the same camera")
        return (f"video {name!r} is truncated: the MP4/MOV index (moov atom) is missing, as when a "
                "recording is interrupted or a copy is incomplete; copy it again, or try to "
                "recover it with a repair tool (e.g. untrunc) and a good file from the same camera")
    if opened is not None and ("End of file" in opened or "ended prematurely" in opened):
        return (f"video {name!r} has no frames: the file ends within its header (an interrupted "
                "recording or an incomplete copy); copy or record it again")
    return (f"video {name!r} cannot be opened: it is not a video file OpenCV/ffmpeg can read "
            "(MP4/MOV/MKV/AVI, H.264/HEVC) or it is damaged; pass a video or a folder of images")


# Video codecs that keep what the sensor recorded (FFV1, HuffYUV, PNG, grey raw; OpenCV's FourCC).
LOSSLESS_FOURCCS = (b"ffv1", b"FFV1", b"HFYU", b"FFVH", b"MPNG", b"png ", b"Y800", b"\0\0\0\0")


class VideoSource(FrameSource):
    """A video file, read by OpenCV's ffmpeg backend.

    Parameters
    ----------
    path : Path
        The video (it exists: :func:`flow.io.source.open_source` checked).
    roi : Roi, optional
        Crop window in full-frame pixels; the whole frame if omitted.
    fps : float, optional
        The capture rate where it differs from the file's (slow motion, high-speed export):
        the file's timeline is rescaled to it; also the rate of frames the decoder gives no
        time stamp.
    allow_truncated : bool
        A video that stops decoding well before its container's duration is truncated:
        iterating to its end raises :class:`InputError` unless this is True, in which case
        it warns and the decoded frames stand.

    Truncation is judged against the container's duration (its frame count over its frame
    rate, as OpenCV reports them), not against the frame count alone: a variable-frame-rate
    file's header count is an estimate, and its last frame still ends at the container's
    duration, whereas a cut file's last decoded frame ends well before it.
    """

    def __init__(self, path: Path, *, roi: Roi | None = None, fps: float | None = None,
                 allow_truncated: bool = False) -> None:
        super().__init__(path, allow_truncated=allow_truncated)
        self._unstamped = 0  # frames the decoder gave no time stamp (time_s = index / fps)
        self._time_scale = 1.0  # capture time per second of the file's timeline
        quiet_decoder_logs()
        cap = open_video(self.path)
        if not cap.isOpened():
            raise InputError(diagnose_unreadable(self.path))
        self._read_header(cap, fps)
        missing = mp4_missing_bytes(self.path)
        if missing and not allow_truncated:
            raise InputError(
                f"video {str(self.path)!r} is truncated: its header lists {self.header_frames} frames but "
                f"the file ends {missing} bytes before its data does (an interrupted recording or an "
                "incomplete copy); copy the file again, or pass --allow-truncated to measure the "
                "frames that decode")
        self.height, self.width = self._first_frame(cap).shape[:2]
        self._set_roi(roi)

    @property
    def lossless(self) -> bool:
        """A video in a lossless codec (:data:`LOSSLESS_FOURCCS`); False for H.264, H.265, MJPEG
        and every codec not known to be lossless."""
        return self.fourcc in LOSSLESS_FOURCCS

    @property
    def codec_crf(self) -> float | None:
        return None if self.lossless else x264_crf(self.path)

    def _read_header(self, cap: cv2.VideoCapture, fps: float | None) -> None:
        """Size, display rotation, rates and frame count from the container, as OpenCV reads them."""
        self.width = int(cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        self.fourcc = (int(cap.get(cv2.CAP_PROP_FOURCC)) & 0xFFFFFFFF).to_bytes(4, "little")  # the codec's tag
        header_fps = cap.get(cv2.CAP_PROP_FPS)
        self.header_fps = header_fps if header_fps and header_fps > 0 else float("nan")
        # Phones store portrait video as landscape frames plus a display rotation; OpenCV
        # applies it, so the frames are measured as any player shows them.
        self.rotation_deg = int(round(cap.get(cv2.CAP_PROP_ORIENTATION_META) or 0)) % 360
        if self.rotation_deg:
            self.notes.append(
                f"video {self.path.name} carries a {self.rotation_deg} degree display rotation: it is "
                "measured as displayed; masks, --rect, --roi and --between are read on the displayed "
                "frames (a mask drawn on the stored, unrotated frames is rotated to match)")
        self.fps = float(fps) if fps else self.header_fps
        # --fps on a video is the capture rate (a slow-motion or high-speed recording
        # played back at the file's rate): the file's timeline is rescaled to it.
        if fps and math.isfinite(self.header_fps) and abs(self.fps / self.header_fps - 1) > 1e-3:
            self._time_scale = self.header_fps / self.fps
            self.notes.append(f"--fps {self.fps:g} overrides the file's {self.header_fps:g} fps: time_s is "
                              f"the file's timeline x {self._time_scale:.6g} (capture rate, e.g. slow motion)")
        self.header_frames = max(int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0)

    def _first_frame(self, cap: cv2.VideoCapture) -> np.ndarray:
        """The first frame (its decoded size is the frames' size), or why there is none."""
        ok, first = cap.read()
        cap.release()
        if not ok or first is None:
            if self.header_frames == 0:
                raise InputError(f"video {str(self.path)!r} has no frames: export or record it again")
            raise InputError(
                f"video {str(self.path)!r} has no decodable frame although its header lists "
                f"{self.header_frames}: the file is truncated, damaged or in a codec this OpenCV "
                "build lacks; copy it again or convert it (e.g. to H.264 MP4 with ffmpeg)")
        return first

    def _time_s(self, cap: cv2.VideoCapture, index: int) -> float:
        msec = cap.get(cv2.CAP_PROP_POS_MSEC)
        # Decoders report the presentation time of the frame just read; some give 0
        # for every frame, so fall back to index/fps unless it advances.
        if index > 0 and msec <= 0 and math.isfinite(self.fps):
            self._unstamped += 1
            return index / self.fps
        if index == 0 and msec <= 0:
            return 0.0
        return self._time_scale * msec / 1000.0

    def _frames(self, start: int, stop: int | None) -> Iterator[tuple[int, float, np.ndarray]]:
        cap = open_video(self.path)
        times: list[float] = []  # one float per frame: small next to any frame
        try:
            index = 0
            while stop is None or index < stop:
                if index < start:
                    ok, image = cap.grab(), None
                else:
                    ok, image = cap.read()
                    ok = ok and image is not None
                if not ok:
                    break
                time_s = self._time_s(cap, index)
                times.append(time_s)
                self.frames_read = index + 1
                if image is not None:
                    yield index, time_s, self._crop(image)
                index += 1
            else:
                return  # stopped at ``stop``: what follows is not our concern
        finally:
            cap.release()
        self._check_complete(np.asarray(times))

    def clock(self, frame: np.ndarray, time_s: np.ndarray) -> tuple[np.ndarray, list[str]]:
        """The time stamps of the measured frames ``frame`` (read as ``time_s``), checked, and
        what the user should know of them (for the notes and the console).

        A video's own time stamps stand where they increase from frame to frame, a variable
        frame rate included (noted: its frames are not evenly spaced). Where one does not (a
        damaged file: a stamp equal to or before the one of the frame before it), none of them
        can be trusted, and every frame's time becomes its index over the frame rate (--fps,
        else the header's), noted: an approximation where the rate varied, never a clock that
        runs backwards.
        """
        times = np.asarray(time_s, np.float64)
        if times.size == 0:
            return times, []
        name = self.path.name
        order = np.argsort(frame, kind="stable")
        steps = np.diff(times[order])
        rate = "the header's rate" if self.fps == self.header_fps else "--fps"
        bad = np.flatnonzero(~(steps > 0))
        if bad.size or not np.isfinite(times).all():
            if not (math.isfinite(self.fps) and self.fps > 0):
                raise InputError(f"video {str(self.path)!r} has damaged time stamps and no frame rate: pass --fps "
                                 "(the camera frame rate) to time its frames")
            first = int(bad[0]) if bad.size else 0
            at, before = int(frame[order][first + 1]), int(frame[order][first])
            where = (f"frame {at}'s {times[order][first + 1]:.6g} s is not after frame {before}'s "
                     f"{times[order][first]:.6g} s" if bad.size else "a time stamp is not finite")
            return (np.asarray(frame, np.float64) / self.fps,
                    [f"video {name}: its time stamps are damaged ({where}; {bad.size} of {steps.size} steps do "
                     f"not advance): time_s = frame / {self.fps:.6g} fps ({rate}) for every frame; pass --fps "
                     "if the camera's rate differs"])
        notes = []
        if self._unstamped:
            notes.append(f"video {name}: the decoder gave {self._unstamped} frames no time stamp: their time_s is "
                         f"frame / {self.fps:.6g} fps ({rate})")
        if steps.size >= 2:
            typical = float(np.median(steps))
            uneven = np.abs(steps - typical) > max(VFR_SHARE * typical, VFR_SLACK_S * self._time_scale)
            if uneven.any():
                notes.append(f"video {name} has a variable frame rate: its frames are {steps.min():.6g} to "
                             f"{steps.max():.6g} s apart (median {typical:.6g} s); time_s is each frame's own time "
                             "stamp, not a constant rate (plot, modal and export put it on a uniform clock of "
                             "the median interval)")
        return times, notes

    def _check_complete(self, times: np.ndarray) -> None:
        """After the last decodable frame: truncated file, or only a header estimate?"""
        if not self.header_frames or self.frames_read >= self.header_frames:
            return
        times = times / self._time_scale  # back on the file's own timeline
        steps = np.diff(times)
        steps = steps[steps > 0]
        step = float(np.median(steps)) if steps.size else 1.0 / self.header_fps
        duration = self.header_frames / self.header_fps
        covered = float(times[-1]) + step if times.size else 0.0
        # A complete file's last frame ends at the container's duration, give or take a
        # frame; allow two, of the nominal rate or of the decoded one.
        slack = 2.0 * max(step, 1.0 / self.header_fps) if math.isfinite(self.header_fps) else math.inf
        if math.isfinite(duration) and covered >= duration - slack:
            self.notes.append(
                f"video {self.path.name}: header estimated {self.header_frames} frames, the file holds "
                f"{self.frames_read} covering its {duration:.3f} s (variable frame rate)")
            return
        self.truncated = True
        where = (f"decoding stopped at {covered:.3f} s of the container's {duration:.3f} s"
                 if math.isfinite(duration) else "the frame rate is unknown")
        if not self.allow_truncated:
            raise InputError(
                f"video {str(self.path)!r} is truncated: its header lists {self.header_frames} frames but "
                f"only {self.frames_read} decode ({where}); copy the file again, or pass "
                f"--allow-truncated to measure the {self.frames_read} frames that decode")
        warnings.warn(
            f"video {self.path.name}: truncated: header lists {self.header_frames} frames but only "
            f"{self.frames_read} decode ({where}); results cover the decoded frames "
            "(--allow-truncated)", stacklevel=2)
