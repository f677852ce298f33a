"""Stream frames into ffmpeg (imageio-ffmpeg's binary): H.264 like a phone, or FFV1.

A phone records 4K60 H.264 at about 48 Mbit/s, i.e. ~0.1 bit per pixel;
``codec.bits_per_pixel`` keeps that density for crops (a crop is a window of
the phone's stream, so it should be compressed as hard as the full frame).
"""

from __future__ import annotations

import os
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from sim.config import section_dataclass


@dataclass(frozen=True)
class CodecConfig:
    name: str = "h264"              # "h264" (video.mp4) or "ffv1" (lossless video.mkv)
    bits_per_pixel: float = 0.096   # 48 Mbit/s at 3840x2160x60
    bitrate_mbps: float | None = None  # overrides bits_per_pixel
    preset: str = "medium"
    gop_frames: int = 60            # phones: ~1 key frame per second
    profile: str = "high"

    @classmethod
    def from_config(cls, config: dict[str, Any]) -> CodecConfig:
        cfg = section_dataclass(cls, dict(config.get("codec") or {}), "codec")
        if cfg.name not in ("h264", "ffv1"):
            raise ValueError(f"codec.name must be 'h264' or 'ffv1', got {cfg.name!r}")
        if cfg.bits_per_pixel <= 0 or (cfg.bitrate_mbps is not None and cfg.bitrate_mbps <= 0):
            raise ValueError(f"codec bit rate must be > 0, got bits_per_pixel="
                             f"{cfg.bits_per_pixel!r}, bitrate_mbps={cfg.bitrate_mbps!r}")
        if cfg.gop_frames < 1:
            raise ValueError(f"codec.gop_frames must be >= 1, got {cfg.gop_frames!r}")
        return cfg

    @property
    def suffix(self) -> str:
        return ".mp4" if self.name == "h264" else ".mkv"

    def bitrate_bps(self, width: int, height: int, fps: float) -> int:
        if self.bitrate_mbps is not None:
            return int(self.bitrate_mbps * 1e6)
        return int(self.bits_per_pixel * width * height * fps)


def ffmpeg_exe() -> str:
    import imageio_ffmpeg
    return imageio_ffmpeg.get_ffmpeg_exe()


def ffmpeg_version() -> str:
    out = subprocess.run([ffmpeg_exe(), "-version"], capture_output=True, text=True, check=False)
    return out.stdout.splitlines()[0] if out.stdout else "unknown"


class StreamWriter:
    """An output written piece by piece: ``with`` it to ``close()`` on success and
    ``abort()`` (leave nothing half-done) on an exception."""

    def close(self) -> None:
        raise NotImplementedError

    def abort(self) -> None:
        raise NotImplementedError

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None:
            self.close()
        else:
            self.abort()


class VideoWriter(StreamWriter):
    """``with VideoWriter(path, w, h, fps, cfg) as vw: vw.write(rgb_uint8)``; constant memory."""

    def __init__(self, path: str | os.PathLike[str], width: int, height: int, fps: float,
                 cfg: CodecConfig):
        self.path = Path(path)
        self.width, self.height = width, height
        self.cfg = cfg
        self.frames = 0
        cmd = [ffmpeg_exe(), "-y", "-loglevel", "error", "-f", "rawvideo", "-pix_fmt", "rgb24",
               "-s", f"{width}x{height}", "-r", f"{fps:g}", "-i", "-", "-an"]
        if cfg.name == "h264":
            rate = cfg.bitrate_bps(width, height, fps)
            cmd += ["-c:v", "libx264", "-preset", cfg.preset, "-profile:v", cfg.profile,
                    "-pix_fmt", "yuv420p", "-b:v", str(rate), "-maxrate", str(int(rate * 1.5)),
                    "-bufsize", str(rate), "-g", str(cfg.gop_frames), "-bf", "0",
                    # One thread: x264's frame-threaded rate control makes the bytes (and
                    # from frame ~140 on, the pixels) differ from run to run.
                    "-threads", "1", "-x264-params", "log-level=error",
                    "-movflags", "+faststart", "-f", "mp4"]
        else:
            cmd += ["-c:v", "ffv1", "-level", "3", "-pix_fmt", "bgr0", "-g", "1", "-f", "matroska"]
        cmd.append(str(self.path))
        self.cmd = cmd
        self.proc = subprocess.Popen(cmd, stdin=subprocess.PIPE, stderr=subprocess.PIPE)

    def write(self, frame: np.ndarray) -> None:
        if frame.shape != (self.height, self.width, 3) or frame.dtype != np.uint8:
            raise ValueError(f"frame is {frame.shape} {frame.dtype}, expected "
                             f"({self.height}, {self.width}, 3) uint8")
        try:
            self.proc.stdin.write(np.ascontiguousarray(frame).tobytes())
        except BrokenPipeError:
            err = self.proc.stderr.read().decode(errors="replace")
            raise RuntimeError(f"ffmpeg stopped: {err.strip()} (command: {' '.join(self.cmd)})") \
                from None
        self.frames += 1

    def close(self) -> None:
        if self.proc.stdin and not self.proc.stdin.closed:
            self.proc.stdin.close()
        err = self.proc.stderr.read().decode(errors="replace")
        rc = self.proc.wait()
        if rc != 0:
            raise RuntimeError(f"ffmpeg failed (exit {rc}): {err.strip()}")

    def abort(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait()


def read_video_frames(path: str | os.PathLike[str]):
    """Decode a video to RGB uint8 frames (for tests and figures)."""
    import imageio_ffmpeg
    gen = imageio_ffmpeg.read_frames(str(path), pix_fmt="rgb24")
    meta = next(gen)
    w, h = meta["size"]
    for buf in gen:
        yield np.frombuffer(buf, np.uint8).reshape(h, w, 3)
