"""A chain whose key is too still to show its background: what its next frames cost.

A key that moved less than ``STATIC_MIN_MOTION_PX`` cannot tell from its dense flow whether the
background beyond the member's outline stands still (see ``_background_static``). The first
tracked frame that moved far enough used to be measured in full, dense flow and all, to ask it
(the bench's `jump` clip: frames 1, 33 and 92, a quarter of its full measurements). It is now
tracked where the frame's own pixels beyond the outline clearly show the background standing
still or moving with the member, side by side; measured in full as before where they do not.
And the reference frame itself (a clip's first frame) is not solved: its flow is nought.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

import flow.methods.deepflow.method as deepflow_module

sys.path.insert(0, str(Path(__file__).parent))
from _deepflow_synth import fourier_shift, grid, smooth_noise, textured, to_u8  # noqa: E402

HEIGHT, WIDTH, X0, X1 = 96, 160, 60, 100


def _scene(*, banded: bool = False):
    """A faintly painted vertical bar over a textured wall, running beyond the POIs at both ends;
    ``banded``: a strongly textured band across the bar just above the POIs (a bolted joint, a
    mark), so that beyond the top end of the member's outline lies the bar itself, moving with
    it, while beyond its long sides the wall stands still. ``render(across, behind)``: the bar
    moved ``across`` px along x, the wall ``behind`` px."""
    gx, gy = grid(HEIGHT, WIDTH)
    rng = np.random.default_rng(4)
    wall = textured(HEIGHT, WIDTH, seed=7).astype(np.float64)
    bar = 150 + 1.0 * smooth_noise(HEIGHT, WIDTH, 6.0, np.random.default_rng(11))
    if banded:
        band = 100 + 12.0 * smooth_noise(HEIGHT, WIDTH, 1.5, np.random.default_rng(12))
        bar = np.where((gy >= 6) & (gy < 20), band, bar)
    poi = np.zeros((HEIGHT, WIDTH), bool)
    poi[20:HEIGHT - 20, X0 + 6:X1 - 6] = True

    def render(across: float, behind: float = 0.0) -> np.ndarray:
        cover = np.clip(np.minimum(gx + 0.5 - (X0 + across), (X1 + across) - (gx - 0.5)), 0, 1)
        moved = fourier_shift(wall, behind, 0.0) * (1 - cover) + fourier_shift(bar, across, 0.0) * cover
        return to_u8(moved + rng.normal(0, 1.0, (HEIGHT, WIDTH)))

    return render, poi


@pytest.mark.parametrize("banded", [False, True])
def test_a_still_key_goes_on_tracking_where_the_frame_shows_the_wall_still(banded) -> None:
    """Key 0.2 px (too still to tell), then 0.8-2.6 px: one full measurement, not two, and the
    readings within 0.05 px of the truth. A wall moving half the bar's way is no such wall:
    its frames are measured in full (the dense flow's check then refuses the outline)."""
    render, poi = _scene(banded=banded)
    steps = (0.2, 0.8, 1.4, 2.0, 2.6)
    for wall_share, full in ((0.0, 1), (0.5, len(steps))):
        reference = render(0.0)
        method = deepflow_module.DeepFlow()
        method.bind(reference, poi)
        method.restart()
        read = [float(np.mean(method.calc(reference, render(a, wall_share * a))[..., 0][poi])) for a in steps]
        assert method.counts["full_frames"] == full, wall_share
        if wall_share == 0.0:
            assert method.counts["warm_frames"] == len(steps) - 1
            np.testing.assert_allclose(read, steps, atol=0.05)


def test_each_side_of_the_outline_shows_its_own_background() -> None:
    """Beyond the outline's long sides the wall stands still; beyond its top end (the mask's
    end, not the member's) the banded bar moves with itself. Judged as one side (left and top
    together) the samples fit neither and the frame would be measured in full; judged side by
    side each is clear. A wall moved half the way is not clear, and neither is a frame whose
    member's motion is misread (the outline fit's motion taken as 0.5 px short)."""
    render, poi = _scene(banded=True)
    reference = render(0.0)
    region = deepflow_module._Region.of(reference, poi, 1, member=True, texture=False)
    member = region.member
    assert member.vertical.sum() >= 10  # the top end's profiles, facing the band
    moved = np.tile([1.0, 0.0], (len(member.px), 1))
    assert deepflow_module._background_clear(region, reference, render(1.0), moved) is True
    assert deepflow_module._background_clear(region, reference, render(1.0, 0.5), moved) is False
    assert deepflow_module._background_clear(region, reference, render(1.5), moved) is False
    # The light 10 % brighter: the frame's gain scales the reference's predictions.
    brighter = np.clip(render(1.0).astype(np.float64) * 1.1, 0, 255).astype(np.uint8)
    assert deepflow_module._background_clear(region, reference, brighter, moved) is True
    # Too little motion at the outline to tell, as in a full measurement.
    assert deepflow_module._background_clear(region, reference, render(0.3), moved * 0.3) is False


def test_the_warm_up_compiles_the_solver_and_the_tracking(monkeypatch) -> None:
    """``compile_kernels`` (``make`` and every run's first step) must solve a dense flow and track
    a frame: with the reference itself first, its flow nought, the solver's kernels were left to
    a clip's first frame (a progress bar at 0 % while they compile, Ctrl-C waiting on them)."""
    calls = {"deep_matching": 0, "refine": 0}
    for name in calls:
        original = getattr(deepflow_module, name)

        def counted(*args, _name=name, _original=original, **kwargs):
            calls[_name] += 1
            return _original(*args, **kwargs)

        monkeypatch.setattr(deepflow_module, name, counted)
    tracked = []
    original_track = deepflow_module.DeepFlow._track

    def track(self, *args, **kwargs):
        found = original_track(self, *args, **kwargs)
        tracked.append(found is not None)
        return found

    monkeypatch.setattr(deepflow_module.DeepFlow, "_track", track)
    deepflow_module.compile_kernels()
    assert calls["deep_matching"] >= 1 and calls["refine"] >= 1
    assert any(tracked)


def test_the_reference_itself_is_not_solved(monkeypatch) -> None:
    """The reference frame against itself reads nought in the POIs' window without a solve (NaN
    outside it, as a solved frame); any other frame is solved."""
    render, poi = _scene()
    reference = render(0.0)
    method = deepflow_module.DeepFlow(member=False, texture=False)
    method.bind(reference, poi)
    solved = method.calc(reference, render(0.5))

    def refuse(*args, **kwargs):
        raise AssertionError("solved")

    monkeypatch.setattr(method, "_solve", refuse)
    flow = method.calc(reference, reference.copy())
    assert np.all(flow[poi] == 0.0)
    np.testing.assert_array_equal(np.isnan(flow), np.isnan(solved))
    changed = reference.copy()
    changed[HEIGHT // 2, WIDTH // 2] ^= 1
    with pytest.raises(AssertionError, match="solved"):
        method.calc(reference, changed)
