"""An interrupted run stops within a frame, and a method's kernels are compiled before the
first frame with a notice where that takes long (issue 31: Ctrl-C took 11-24 s to act, while
the jobs finished their chains, and a first run sat at 0 % for 29 s compiling)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from flow.measure import driver


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
