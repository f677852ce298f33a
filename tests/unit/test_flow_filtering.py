"""Paper eq. (10)-(12): background and outlier POIs are removed, good ones kept."""

from __future__ import annotations

import numpy as np
import pytest

from flow.filtering import filter_and_average, mean_cross_correlation, remove_offset
from flow.track import flag_invalid


def planted(seed: int = 0):
    rng = np.random.default_rng(seed)
    t = np.arange(200) / 30.0
    truth = 2.0 * np.sin(2 * np.pi * 1.3 * t)
    good = truth[:, None] + rng.normal(0, 0.05, (200, 40)) + 0.7  # offset removed by the filter
    background = rng.normal(0, 0.05, (200, 10))  # stationary: eq. 10 removes
    outliers = 3.0 * np.cumsum(rng.normal(0, 0.3, (200, 5)), axis=0)  # large, uncorrelated: eq. 11
    dx = np.hstack([good, background, outliers])
    dy = 0.1 * dx + rng.normal(0, 0.05, dx.shape)
    return truth, dx, dy


def test_filters_remove_background_and_outliers_and_keep_good_pois() -> None:
    truth, dx, dy = planted()
    result = filter_and_average(dx, dy)
    assert result.kept[:40].all()
    assert not result.kept[40:50].any(), "stationary background must fail eq. (10)"
    assert not result.kept_threshold[40:50].any()
    assert not result.kept[50:].any(), "uncorrelated outliers must fail eq. (11)"
    assert np.abs(result.dx - (truth - truth[0])).max() < 0.1


def test_unfiltered_average_is_biased_by_background() -> None:
    truth, dx, dy = planted()
    plain = filter_and_average(dx, dy, enabled=False)
    assert plain.kept.all()
    assert np.abs(plain.dx - (truth - truth[0])).max() > 0.5


def test_invalid_frames_do_not_poison_the_correlation() -> None:
    truth, dx, dy = planted()
    dx, dy = dx[:, :40].copy(), dy[:, :40].copy()
    rng = np.random.default_rng(3)
    dx[100:130] = rng.normal(0, 30, (30, 40))  # occluded view: garbage flow
    valid = np.ones(200, bool)
    valid[100:130] = False
    result = filter_and_average(dx, dy, valid=valid)
    assert result.kept.all()
    ok = valid.copy()
    assert np.abs(result.dx[ok] - (truth - truth[0])[ok]).max() < 0.1


def test_median_average_and_nan_tracks() -> None:
    truth, dx, dy = planted()
    dx[50:, 3] = np.nan  # a lost feature
    result = filter_and_average(dx, dy, average="median")
    assert np.isfinite(result.dx).all()
    assert np.abs(result.dx - (truth - truth[0])).max() < 0.1
    with pytest.raises(ValueError, match="average"):
        filter_and_average(dx, dy, average="mode")


def test_mean_cross_correlation_matches_the_full_matrix() -> None:
    rng = np.random.default_rng(1)
    tracks = rng.normal(size=(50, 8)) + np.linspace(0, 3, 50)[:, None]
    full = np.corrcoef(tracks.T)
    expected = (full.sum(axis=1) - 1) / 7
    assert np.allclose(mean_cross_correlation(tracks), expected)


def test_remove_offset_uses_reference_row() -> None:
    d = np.array([[1.0, np.nan], [2.0, 5.0], [3.0, 6.0]])
    out = remove_offset(d, 0)
    assert np.allclose(out[:, 0], [0, 1, 2]) and np.allclose(out[1:, 1], [0, 1])


def test_flag_invalid_catches_a_blocked_view() -> None:
    residual = np.full(100, 1.5) + np.random.default_rng(0).normal(0, 0.2, 100)
    residual[40:45] = 25.0
    valid, threshold = flag_invalid(residual)
    assert not valid[40:45].any() and valid[:40].all() and valid[45:].all()
    assert 3.0 <= threshold < 25.0


def test_incoherent_frames_are_flagged_even_with_a_low_residual():
    """An occluder as bright as the structure: residual stays low, the POIs scatter."""
    from flow.track import flag_incoherent, poi_spread

    rng = np.random.default_rng(3)
    frames, points = 40, 200
    motion = np.sin(np.linspace(0, 6, frames))[:, None] * 3.0
    dx = motion + rng.normal(0, 0.05, (frames, points)) + np.linspace(-0.3, 0.3, points)[None, :]
    dy = rng.normal(0, 0.05, (frames, points))
    blocked = np.arange(15, 22)
    dx[blocked] = rng.normal(0, 8.0, (blocked.size, points))
    dy[blocked] = rng.normal(0, 8.0, (blocked.size, points))
    flagged = flag_incoherent(poi_spread(dx, dy))
    assert np.flatnonzero(flagged).tolist() == blocked.tolist()
