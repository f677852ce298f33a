"""Simulation speed and accuracy of the beam physics, measured in one run.

Prints simulated seconds per wall second for both engines at the default
discretisation, and the frequency / damping errors each engine shows on a
free decay (modal coordinates fitted with a damped cosine).

Usage: python benchmarks/bench_simulate.py [--duration-s 60] [--mujoco-duration-s 3]
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np
from scipy.optimize import curve_fit

from sim import beam as B


def _fit(time_s: np.ndarray, signal: np.ndarray, omega: float) -> tuple[float, float]:
    def model(t, amp, phase, w, decay):
        return amp * np.exp(-decay * t) * np.cos(w * t + phase)

    best = None
    for phase in (0.0, np.pi / 2, np.pi, -np.pi / 2):
        try:
            p, _ = curve_fit(model, time_s, signal, p0=[np.abs(signal).max(), phase, omega, 0.005 * omega],
                             maxfev=20000)
        except RuntimeError:
            continue
        cost = np.sum((model(time_s, *p) - signal) ** 2)
        if best is None or cost < best[0]:
            best = (cost, p)
    w_d, decay = abs(best[1][2]), best[1][3]
    w_n = math.hypot(w_d, decay)
    return w_n, decay / w_n


def run(engine: str, duration_s: float, n_segments: int | None = None) -> None:
    beam = {} if n_segments is None else {"n_segments": n_segments}
    cfg = B.SimConfig.from_dict({
        "duration_s": duration_s, "beam": beam,
        "excitation": [{"type": "pluck"},
                       {"type": "impulse", "start_s": 0.0, "height_mm": 400.0, "impulse_ns": 0.02}],
        "simulation": {"engine": engine}})
    start = time.perf_counter()
    result = B.run_simulation(cfg)
    wall = time.perf_counter() - start
    modal = B._dof_modal(cfg)
    eta = result.qpos @ (modal["mass"] @ modal["modes"])
    print(f"{engine:6s} N={cfg.beam.n_segments:3d} duration {duration_s:6.1f} s  wall {wall:7.2f} s  "
          f"-> {duration_s / wall:8.2f} simulated s per wall s (dt {result.timestep_s:.3g} s, "
          f"{result.substeps} substeps/sample)")
    window = result.time_s < min(duration_s, 4.0)
    for k in range(3):
        w_n, zeta = _fit(result.time_s[window], eta[window, k], modal["omega"][k])
        print(f"    mode {k + 1}: {modal['omega'][k] / 2 / math.pi:8.4f} Hz  freq error "
              f"{(w_n / modal['omega'][k] - 1) * 100:+.4f} %  zeta {zeta:.5f} (target "
              f"{cfg.damping.ratio(k)})")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--duration-s", type=float, default=60.0)
    parser.add_argument("--mujoco-duration-s", type=float, default=3.0)
    args = parser.parse_args()
    run("modal", args.duration_s)
    run("mujoco", args.mujoco_duration_s)
    run("mujoco", args.mujoco_duration_s, n_segments=20)


if __name__ == "__main__":
    main()
