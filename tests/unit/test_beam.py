"""Beam physics: frequencies, convergence, statics, damping, shapes, files, config errors."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from sim import beam as B
from sim.__main__ import main as cli_main

NO_GRAVITY = {"beam": {"gravity": False}}


def _free_decay(n_segments: int = 20, gravity: bool = True, duration_s: float = 4.0,
                engine: str = "mujoco", zeta: float = 0.005):
    cfg = B.SimConfig.from_dict({
        "duration_s": duration_s,
        "beam": {"n_segments": n_segments, "gravity": gravity},
        "damping": {"ratios": [zeta]},
        "excitation": [{"type": "pluck", "peak_mm": 1.8},
                       {"type": "impulse", "start_s": 0.0, "height_mm": 400.0, "impulse_ns": 0.02}],
        "simulation": {"engine": engine},
    })
    return cfg, B.run_simulation(cfg)


def _modal_coordinates(cfg, result):
    modal = B._dof_modal(cfg)
    return result.qpos @ (modal["mass"] @ modal["modes"]), modal["omega"]


def _fit_damped(time_s, signal, omega_guess):
    """Least-squares damped cosine: returns (omega_d, zeta)."""
    from scipy.optimize import curve_fit

    def model(t, amp, phase, omega, decay):
        return amp * np.exp(-decay * t) * np.cos(omega * t + phase)

    amp0 = np.abs(signal).max()
    phase0 = 0.0 if signal[0] > 0 else np.pi
    best = None
    for phase in (phase0, phase0 + np.pi / 2, phase0 - np.pi / 2):
        try:
            p, _ = curve_fit(model, time_s, signal, p0=[amp0, phase, omega_guess, 0.005 * omega_guess],
                             maxfev=20000)
        except RuntimeError:
            continue
        cost = np.sum((model(time_s, *p) - signal) ** 2)
        if best is None or cost < best[0]:
            best = (cost, p)
    _, p = best
    omega_d, decay = abs(p[2]), p[3]
    omega_n = math.hypot(omega_d, decay)
    return omega_d, decay / omega_n


def _log_decrement_zeta(time_s, signal, period_s):
    """Damping ratio from the logarithmic decrement of successive positive peaks."""
    from scipy.signal import find_peaks

    peaks, _ = find_peaks(signal, distance=max(1, int(0.7 * period_s / (time_s[1] - time_s[0]))))
    peaks = peaks[signal[peaks] > 0]
    cycles = len(peaks) - 1
    assert cycles >= 4, "record too short for a log decrement"
    delta = np.log(signal[peaks[0]] / signal[peaks[-1]]) / cycles
    return delta / math.sqrt(4 * math.pi**2 + delta**2)


# --- frequencies ------------------------------------------------------------

def test_default_frequencies_match_euler_bernoulli_within_half_percent():
    result = B.modal_analysis(NO_GRAVITY, n_modes=3)
    model, theory = np.array(result["model_hz"]), np.array(result["euler_bernoulli_hz"])
    np.testing.assert_allclose(theory, [4.0769, 25.5495, 71.5394], rtol=1e-4)
    assert np.all(np.abs(model / theory - 1) < 0.005), model / theory - 1


def test_convergence_is_second_order():
    errors = []
    for n in (10, 20, 40):
        result = B.modal_analysis({"beam": {"gravity": False, "n_segments": n}}, n_modes=3)
        errors.append(np.abs(np.array(result["model_hz"]) / result["euler_bernoulli_hz"] - 1))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 1.85), orders


def test_gravity_lowers_frequencies_slightly():
    with_g = B.modal_analysis({}, 3)
    assert with_g["gravity"] is True
    ratio = np.array(with_g["model_hz"]) / with_g["model_hz_no_gravity"]
    assert np.all(ratio < 1) and np.all(ratio > 0.98), ratio
    # Self-weight lowers f1^2 by ~ 0.0235 * (L / L_buckle)^3 ... about 1.2 % in f1.
    assert 0.985 < ratio[0] < 0.992


def test_tip_mass_matches_euler_bernoulli_with_end_mass():
    cfg = {"beam": {"gravity": False, "tip_mass_kg": 0.3}}
    result = B.modal_analysis(cfg, 3)
    assert np.all(np.abs(np.array(result["model_hz"]) / result["euler_bernoulli_hz"] - 1) < 0.005)
    assert result["euler_bernoulli_hz"][0] < B.euler_bernoulli_hz(NO_GRAVITY, 1)[0]


def test_tune_to_hz_hits_target():
    tuned, change = B.tune_to_hz({}, 4.8)
    assert change["parameter"] == "beam.youngs_modulus_gpa" and change["after"] > 200
    assert B.modal_analysis(tuned, 1)["model_hz"][0] == pytest.approx(4.8, rel=1e-8)
    tuned_m, change_m = B.tune_to_hz({}, 3.5, parameter="tip_mass_kg")
    assert change_m["after"] > 0
    assert B.modal_analysis(tuned_m, 1)["model_hz"][0] == pytest.approx(3.5, rel=1e-8)
    with pytest.raises(ValueError, match="tip mass"):
        B.tune_to_hz({}, 4.8, parameter="tip_mass_kg")


def test_mode_shapes_match_analytic_mac():
    result = B.modal_analysis(NO_GRAVITY, 3)
    assert min(result["mac_vs_euler_bernoulli"]) > 0.999
    z = np.array(result["mode_shapes"]["z_mm"])
    assert z[0] == 0 and z[-1] == pytest.approx(1000.0)


# --- statics ------------------------------------------------------------------

def test_static_tip_deflection_matches_beam_theory():
    cfg = B.SimConfig.from_dict(NO_GRAVITY)
    modal = B._dof_modal(cfg)
    load_n = 1.0
    qpos = np.linalg.solve(modal["spring"] + modal["geometric"],
                           B._lever(cfg.beam, cfg.beam.length_mm) * load_n)
    x, _, _ = B._node_displacements(cfg.beam, qpos)
    expected = load_n * cfg.beam.length_m**3 / (3 * cfg.beam.bending_stiffness_n_m2)
    assert x[-1] == pytest.approx(expected, rel=0.005)
    # MuJoCo agrees the deflected chain is in equilibrium under the tip load.
    model = modal["model"]
    import mujoco
    data = mujoco.MjData(model)
    data.qpos[:] = qpos
    mujoco.mj_forward(model, data)
    residual = data.qfrc_passive - data.qfrc_bias + B._lever(cfg.beam, 1000.0) * load_n
    assert np.abs(residual).max() < 1e-3 * np.abs(data.qfrc_passive).max()


def test_point_between_nodes_lies_on_its_rigid_segment():
    cfg = B.SimConfig.from_dict({"beam": {"n_segments": 8}})
    qpos = np.linspace(0.01, 0.02, 8)
    x, _, _ = B._node_displacements(cfg.beam, qpos)
    assert B._point_x(cfg.beam, x, 250.0) == pytest.approx(x[2])  # a node
    mid = B._point_x(cfg.beam, x, 250.0 + 125.0 / 2)
    assert mid == pytest.approx(0.5 * (x[2] + x[3]))
    assert B._point_x(cfg.beam, x, 1000.0) == pytest.approx(x[-1])


# --- time simulation -------------------------------------------------------

@pytest.fixture(scope="module")
def mujoco_decay():
    cfg, result = _free_decay()
    eta, omega = _modal_coordinates(cfg, result)
    return cfg, result, eta, omega


def test_mujoco_free_decay_frequencies_match_eigenvalues(mujoco_decay):
    cfg, result, eta, omega = mujoco_decay
    for k in range(3):
        omega_d, zeta = _fit_damped(result.time_s, eta[:, k], omega[k])
        omega_n = omega_d / math.sqrt(1 - zeta**2)
        assert omega_n / omega[k] == pytest.approx(1.0, abs=0.002), (k, omega_n / omega[k])


def test_sensor_spectrum_peak_at_mode_one(mujoco_decay):
    cfg, result, _, omega = mujoco_decay
    _, table = B.sensor_table(cfg, result)
    signal = table[:, 1] - table[:, 1].mean()
    n_fft = 1 << 18  # zero padding: sub-bin peak location
    spectrum = np.abs(np.fft.rfft(signal * np.hanning(signal.size), n_fft))
    freqs = np.fft.rfftfreq(n_fft, 1 / cfg.sensor.rate_hz)
    band = (freqs > 2) & (freqs < 10)
    peak = freqs[band][np.argmax(spectrum[band])]
    assert peak == pytest.approx(omega[0] / (2 * math.pi), rel=0.002)


def test_log_decrement_matches_target_damping(mujoco_decay):
    cfg, result, eta, omega = mujoco_decay
    for k in range(2):
        zeta = _log_decrement_zeta(result.time_s, eta[:, k], 2 * math.pi / omega[k])
        assert zeta == pytest.approx(cfg.damping.ratio(k), rel=0.10), (k, zeta)


def test_modal_engine_agrees_with_mujoco(mujoco_decay):
    cfg, result, _, _ = mujoco_decay
    modal_result = B.run_simulation(cfg, engine="modal")
    a = B.sensor_table(cfg, result)[1][:, 1]
    b = B.sensor_table(cfg, modal_result)[1][:, 1]
    assert np.abs(a - b).max() < 0.01 * np.abs(a).max()


def test_pluck_peak_at_sensor_is_peak_mm():
    cfg, result = _free_decay(duration_s=0.2, engine="modal")
    _, table = B.sensor_table(cfg, result)
    assert table[0, 1] == pytest.approx(1.8, rel=1e-5)  # linear static shape, exact kinematics
    assert np.abs(table[:, 1]).max() < 1.9


# --- files -----------------------------------------------------------------

SCENARIO = {
    "seed": 7, "duration_s": 0.5,
    "beam": {"n_segments": 12},
    "excitation": [{"type": "ambient", "rms_m_s2": 0.1},
                   {"type": "harmonic", "height_mm": 900, "freq_hz": 5.0, "amplitude_n": 0.1},
                   {"type": "impulse", "start_s": 0.1, "height_mm": 1000, "impulse_ns": 0.01}],
    "sensor": {"extra_heights_mm": [500, 1000]},
    "camera": {"ignored_by_sim": True},
}


def test_simulate_writes_documented_files(tmp_path):
    sidecar = B.simulate(SCENARIO, tmp_path, progress=False)
    lines = (tmp_path / "sensor.csv").read_text().splitlines()
    assert lines[0] == "time_s,dx_mm,dx_mm_z0500,dx_mm_z1000"
    assert len(lines) == 1 + 501
    with np.load(tmp_path / "shapes.npz") as shapes:
        assert set(shapes.files) == {"time_s", "z_mm", "x_mm", "z_def_mm", "theta_rad"}
        assert shapes["x_mm"].shape == (501, 13) and shapes["z_mm"].shape == (13,)
        assert np.all(shapes["x_mm"][:, 0] == 0)
        assert np.all(shapes["z_def_mm"][:, -1] <= 1000.0 + 1e-9)
        table = np.loadtxt(tmp_path / "sensor.csv", delimiter=",", skiprows=1)
        np.testing.assert_allclose(table[:, 3], shapes["x_mm"][:, -1], atol=1e-8)
    written = json.loads((tmp_path / "sim.json").read_text())
    for key in ("model_hz", "euler_bernoulli_hz", "damping_ratios", "config_hash", "versions"):
        assert key in written
    assert written["timings"]["simulated_s_per_wall_s"] > 0
    assert sidecar["seed"] == 7


def test_same_seed_gives_identical_bytes(tmp_path):
    for name in ("a", "b"):
        B.simulate(SCENARIO, tmp_path / name, progress=False)
    B.simulate({**SCENARIO, "seed": 8}, tmp_path / "c", progress=False)
    for file in ("sensor.csv", "shapes.npz"):
        assert (tmp_path / "a" / file).read_bytes() == (tmp_path / "b" / file).read_bytes()
    assert (tmp_path / "a" / "sensor.csv").read_bytes() != (tmp_path / "c" / "sensor.csv").read_bytes()
    first = json.loads((tmp_path / "a" / "sim.json").read_text())
    second = json.loads((tmp_path / "b" / "sim.json").read_text())
    first.pop("timings"), second.pop("timings")
    assert first == second


def test_cli_modes_json(capsys):
    assert cli_main(["modes", "--json", "--n-modes", "3", "--tune-to-hz", "4.8"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model_hz"][0] == pytest.approx(4.8, rel=1e-6)
    assert len(out["euler_bernoulli_hz"]) == 3 and "tuning" in out
    assert len(out["mode_shapes"]["x_normalized"]) == 3


# --- config errors -----------------------------------------------------------

@pytest.mark.parametrize(("config", "message"), [
    ({"beam": {"length_mm": -3}}, r"beam.length_mm must be > 0, got -3"),
    ({"beam": {"thickness_mm": 0}}, r"beam.thickness_mm must be > 0, got 0"),
    ({"beam": {"n_segments": 2}}, r"beam.n_segments must be an integer >= 4, got 2"),
    ({"beam": {"colour": "red"}}, r"unknown key\(s\) in beam: \['colour'\]"),
    ({"beam": {"gravity": "yes"}}, r"beam.gravity must be true or false"),
    ({"damping": {"ratios": [0.01, 1.0]}}, r"damping.ratios\[1\] must be in \[0, 1\), got 1.0"),
    ({"damping": {"ratios": [-0.1]}}, r"damping.ratios\[0\] must be in \[0, 1\)"),
    ({"sensor": {"height_mm": 1200}}, r"sensor.height_mm must be <= beam.length_mm \(1000.0\), got 1200"),
    ({"sensor": {"extra_heights_mm": [100, -5]}}, r"sensor.extra_heights_mm\[1\] must be > 0"),
    ({"sensor": {"rate_hz": 1000, "shape_rate_hz": 300}}, r"integer multiples"),
    ({"duration_s": 0}, r"duration_s must be > 0, got 0"),
    ({"seed": -1}, r"seed must be a non-negative integer, got -1"),
    ({"excitation": [{"type": "kick"}]}, r"excitation\[0\].type must be one of"),
    ({"excitation": [{"type": "pluck", "force": 1}]}, r"unknown key\(s\) in excitation\[0\]"),
    ({"excitation": [{"type": "harmonic", "freq_hz": -2}]}, r"excitation\[0\].freq_hz must be > 0"),
    ({"excitation": [{"type": "impulse", "height_mm": 2000}]}, r"excitation\[0\].height_mm must be <="),
    ({"excitation": [{"type": "ambient", "band_hz": [50, 10]}]}, r"low < high"),
    ({"excitation": [{"type": "pluck"}, {"type": "pluck"}]}, r"at most one pluck"),
    ({"simulation": {"engine": "euler"}}, r"simulation.engine must be"),
])
def test_bad_config_raises_value_error_naming_key(config, message):
    with pytest.raises(ValueError, match=message):
        B.SimConfig.from_dict(config)


def test_defaults_and_unknown_sections_ignored():
    cfg = B.SimConfig.from_dict({"camera": {"x": 1}, "beam": {"length_mm": 1000}})
    assert cfg.beam == B.BeamParams() and cfg.sensor.height_mm == 750.0
    assert cfg.excitation[0].type == "pluck" and cfg.excitation[0].get("peak_mm") == 1.8


@pytest.mark.parametrize("excitation", [
    {"type": "harmonic", "height_mm": 900, "freq_hz": 5.0, "amplitude_n": 0.1},
    {"type": "ambient", "rms_m_s2": 0.1},
])
def test_forced_response_agrees_between_engines(excitation):
    cfg = B.SimConfig.from_dict({"duration_s": 1.0, "beam": {"n_segments": 12},
                                 "excitation": [excitation]})
    tip = [B.shape_arrays(cfg, B.run_simulation(cfg, engine=e))["x_mm"][:, -1]
           for e in ("modal", "mujoco")]
    assert np.abs(tip[0]).max() > 0.05
    assert np.abs(tip[0] - tip[1]).max() < 0.02 * np.abs(tip[0]).max()


def test_cli_modes_writes_out_file(tmp_path, capsys):
    out = tmp_path / "sim" / "modes.json"
    assert cli_main(["modes", "--json", "--out", str(out)]) == 0
    written = json.loads(out.read_text())
    assert written["model_hz"] == json.loads(capsys.readouterr().out)["model_hz"]


def test_cli_bad_config_exits_2(tmp_path, capsys):
    bad = tmp_path / "bad.yaml"
    bad.write_text("beam: {length_mm: -3}\n")
    assert cli_main(["modes", "--config", str(bad)]) == 2
    assert "beam.length_mm must be > 0, got -3" in capsys.readouterr().err
