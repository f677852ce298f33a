"""A video's clock (issue 32, case 3): a frame rate that gives finite times, time stamps that
never run backwards, and a variable frame rate that says so."""

from __future__ import annotations

import subprocess

import numpy as np
import pytest

from flow.io.errors import InputError
from flow.io.frames import FPS_RANGE, FrameSource, check_fps
from flow.io.source import open_source


def _ffmpeg(*args: str) -> None:
    import imageio_ffmpeg

    subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-nostdin", "-v", "error", "-y", *args],
                   check=True, capture_output=True, timeout=60)


def damaged_clip(folder) -> str:
    """12 frames at 30 fps whose fifth frame's time stamp lies before the fourth's (B-frames
    let the presentation times go anywhere; the setts filter rewrites one, as a broken muxer
    or editor does)."""
    base, damaged = folder / "base.mp4", folder / "damaged.mkv"
    _ffmpeg("-f", "lavfi", "-i", "testsrc=size=64x48:rate=30", "-frames:v", "12", "-c:v", "libx264", "-bf", "2",
            "-pix_fmt", "yuv420p", str(base))
    _ffmpeg("-i", str(base), "-c", "copy", "-bsf:v", "setts=pts=if(eq(N\\,5)\\,100\\,PTS)", str(damaged))
    return str(damaged)


def vfr_clip(folder) -> str:
    video = folder / "vfr.mkv"
    _ffmpeg("-f", "lavfi", "-i", "testsrc=size=64x48:rate=30", "-frames:v", "8",
            "-vf", "setpts='if(lt(N,5),N,5+(N-4)*(N-3))/30/TB'", "-fps_mode", "vfr", "-c:v", "ffv1", str(video))
    return str(video)


def _read(source: FrameSource) -> tuple[np.ndarray, np.ndarray]:
    frames, times = zip(*((index, time_s) for index, time_s, _ in source), strict=True)
    return np.array(frames), np.array(times)


@pytest.mark.parametrize("fps", [4e-320, 1e-300, 1e-7, 1e11, 1e300])
def test_a_frame_rate_no_camera_has_is_refused(fps) -> None:
    with pytest.raises(InputError, match=r"is no camera's frame rate \(1e-06 to 1e\+10"):
        check_fps(fps)


@pytest.mark.parametrize("fps", [FPS_RANGE[0], 1 / 86400 * 10, 30.0, 1e6, FPS_RANGE[1]])
def test_camera_frame_rates_give_finite_times(fps) -> None:
    check_fps(fps)
    assert np.isfinite(np.arange(10**6) / fps).all()


def test_time_stamps_that_run_backwards_become_index_over_the_rate_with_a_note(tmp_path) -> None:
    source = open_source(damaged_clip(tmp_path))
    frames, times = _read(source)
    assert (np.diff(times) <= 0).any(), "the clip must be damaged for this test to mean anything"
    fixed, notes = source.clock(frames, times)
    assert np.allclose(fixed, frames / 30.0) and (np.diff(fixed) > 0).all()
    assert len(notes) == 1 and "time stamps are damaged (frame 4's" in notes[0]
    assert "time_s = frame / 30 fps (the header's rate)" in notes[0]


def test_a_variable_frame_rate_keeps_its_stamps_and_says_so(tmp_path) -> None:
    source = open_source(vfr_clip(tmp_path))
    frames, times = _read(source)
    kept, notes = source.clock(frames, times)
    assert np.array_equal(kept, times)
    assert np.allclose(np.diff(kept), np.array([1, 1, 1, 1, 3, 4, 6]) / 30, atol=0.002)
    assert len(notes) == 1 and "has a variable frame rate" in notes[0] and "each frame's own time stamp" in notes[0]


def test_an_even_clock_has_nothing_to_say(tmp_path) -> None:
    video = tmp_path / "even.mkv"
    _ffmpeg("-f", "lavfi", "-i", "testsrc=size=64x48:rate=30", "-frames:v", "6", "-c:v", "ffv1", str(video))
    source = open_source(video)
    frames, times = _read(source)
    assert source.clock(frames, times) == (pytest.approx(frames / 30.0, abs=0.002), [])
