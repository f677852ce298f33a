"""An interrupted run stops within a frame (and within the stages of a frame, for a method that
checks its stop flag, issue 31: Ctrl-C within 2 s), and a method's kernels are compiled before the
first frame with a notice where that takes long (issue 31: Ctrl-C took 11-24 s to act, while
the jobs finished their chains, and a first run sat at 0 % for 29 s compiling)."""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np
import pytest

from flow.measure import driver
from flow.methods.base import DenseMethod, Stopped


class _Method:
    chain_length = 50

    def bind(self, reference, mask, read=None):
        pass

    def restart(self):
        pass


class _Readout:
    """Counts the frames measured, each taking a little while."""

    def __init__(self) -> None:
        self.frames: list[int] = []
        self._lock = threading.Lock()

    def measure(self, method, grey):
        time.sleep(0.01)
        with self._lock:
            self.frames.append(int(grey[0, 0]))
        return None


def test_an_interrupt_stops_every_job_after_its_current_frame():
    pool = driver._MethodPool(_Method, 2)
    pool.bind(np.zeros((2, 2), np.uint8), np.ones((2, 2), bool), None)
    readout = _Readout()
    frame = [np.full((2, 2), k, np.uint8) for k in range(3)]
    # Chain 0 is one frame; chains 1 and 2 are 50 frames each, still running when chain 0's
    # result comes in and the user's Ctrl-C arrives.
    chains = iter([[(0, 0.0, frame[0], True)]] + [[(i, 0.0, frame[k], True) for i in range(50)] for k in (1, 2)])

    def collect(results):
        raise KeyboardInterrupt

    measure = driver.functools.partial(driver._measure_chain, pool, readout)
    with pytest.raises(KeyboardInterrupt):
        driver._run_chains(chains, measure, collect, jobs=2, chain=50)
    later = [k for k in readout.frames if k > 0]
    assert readout.frames.count(0) == 1
    # Each job stopped after the frame it was measuring (a handful at most), not after its chain.
    assert len(later) < 10, len(later)


def test_kernels_are_warmed_up_before_binding_with_a_notice_when_slow(monkeypatch, capsys):
    monkeypatch.setattr(driver, "COMPILE_NOTICE_S", 0.05)
    calls = []

    class Slow:
        name = "slow"

        def warm_up(self):
            calls.append("warm")
            time.sleep(0.3)

    driver._warm_up(Slow(), progress=True)
    assert calls == ["warm"]
    assert "compiling the slow's kernels (first run only" in capsys.readouterr().err
    driver._warm_up(Slow(), progress=False)  # no progress bar, no notice
    assert capsys.readouterr().err == ""


class _LongFrames(DenseMethod):
    """A dense method whose frame ``k`` (its grey value) takes ``10 + 1000 k`` stages of 10 ms,
    checking the stop between them."""

    def __init__(self) -> None:
        super().__init__()
        self.stages: dict[int, int] = {}

    def _solve(self, reference, current, *, whole_shape):
        frame = int(current[0, 0])
        self.stages[frame] = 0
        for _ in range(10 + 1000 * frame):
            self.check_stop()
            time.sleep(0.01)
            self.stages[frame] += 1
        return np.zeros(reference.shape + (2,), np.float32)


def test_an_interrupt_abandons_the_frames_the_jobs_measure():
    pool = driver._MethodPool(_LongFrames, 2)
    assert all(method.stop is pool.stop for method in pool.methods)
    reference = np.zeros((4, 4), np.uint8)
    pool.bind(reference, np.ones((4, 4), bool), None)

    class Readout:
        def measure(self, method, grey):
            return method.calc(reference, grey)

    # Frame 0 is quick; frames 1-3 take 10-30 s. The user's Ctrl-C arrives with frame 0's
    # result, while the other job measures frame 1 (and maybe the first, frame 2).
    chains = iter([[(k, 0.0, np.full((4, 4), k, np.uint8), True)] for k in range(4)])
    measure = driver.functools.partial(driver._measure_chain, pool, Readout())

    def collect(results):
        raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        driver._run_chains(chains, measure, collect, jobs=2, chain=1, stop=pool.stop)
    assert pool.stop.is_set()
    stages: dict[int, int] = {}
    for method in pool.methods:
        stages.update(method.stages)
    assert stages[0] == 10
    # The frames begun were abandoned within a few stages, not finished.
    assert 1 in stages and all(stages[k] < 100 for k in stages if k > 0), stages


def test_the_stop_check_raises_only_once_the_run_stops():
    method = _LongFrames()
    method.check_stop()  # no driver: never stops
    method.stop = threading.Event()
    method.check_stop()
    method.stop.set()
    with pytest.raises(Stopped):
        method.calc(np.zeros((4, 4), np.uint8), np.full((4, 4), 3, np.uint8))
    assert method.stages == {3: 0}


def test_the_deepflow_solve_checks_between_its_stages():
    from flow.methods.deepflow.deepmatching import MatchParams, deep_matching
    from flow.methods.deepflow.variational import VariationalParams, _level_sizes, refine

    rng = np.random.default_rng(0)
    reference = (rng.random((64, 80)) * 255).astype(np.uint8)
    params = VariationalParams()
    checks = []
    refine(reference, reference, params, checkpoint=lambda: checks.append(1))
    levels = len(_level_sizes(64, 80, params.eta, params.min_size))
    # One before each pyramid level and one before each fixed-point iteration.
    assert len(checks) == levels * (1 + params.n_outer)
    matched = []
    deep_matching(reference, reference, MatchParams(), checkpoint=lambda: matched.append(1))
    assert len(matched) == 2

    def stop_at_third():
        checks.append(1)
        if len(checks) == 3:
            raise Stopped("the run is stopping")

    checks.clear()
    with pytest.raises(Stopped):
        refine(reference, reference, params, checkpoint=stop_at_third)
    assert len(checks) == 3


def test_the_stop_check_leaves_the_solve_unchanged():
    from flow.methods.deepflow.variational import VariationalParams, refine

    rng = np.random.default_rng(1)
    reference = cv2.GaussianBlur((rng.random((60, 90)) * 255).astype(np.float32), (0, 0), 1.5)
    current = np.roll(reference, 1, axis=1)
    params = VariationalParams()
    plain = refine(reference, current, params)
    checked = refine(reference, current, params, checkpoint=lambda: None)
    assert np.array_equal(plain, checked)
