"""CLI of analysis on synthetic stage files in the documented formats."""

from __future__ import annotations

import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from analysis.__main__ import main
from analysis.synthetic import make_scenario

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def scenario(tmp_path_factory):
    root = tmp_path_factory.mktemp("scenario")
    return make_scenario(root, duration_s=16.0, occlusion_s=(8.0, 9.0))


def _evaluate(paths, method, out, scenario_name="occlusion"):
    return main(["evaluate", "--sensor", str(paths["sensor"]), "--sim-json", str(paths["sim_json"]),
                 "--truth", str(paths["truth"]), "--render-json", str(paths["render_json"]),
                 "--track", str(paths[method]), "--method", method, "--scenario", scenario_name,
                 "--out", str(out)])


@pytest.fixture(scope="module")
def metrics(scenario, tmp_path_factory):
    out_dir = tmp_path_factory.mktemp("metrics")
    files = {}
    for method in ("proposed", "klt"):
        files[method] = out_dir / f"{method}.json"
        assert _evaluate(scenario, method, files[method]) == 0
    return files


def test_evaluate_writes_documented_keys(metrics):
    data = json.loads(metrics["proposed"].read_text())
    for key in ("rmse_mm", "rmse_px", "max_error_mm", "bias_mm", "drift_mm_per_s", "max_disp_meas_mm",
                "max_disp_ref_mm", "max_disp_error_pct", "rmse_pct_of_max_ref", "lowfreq_power_ratio",
                "mode1_amplitude_ratio", "mode3_expected_hz", "sync_lag_s", "occlusion_rmse_mm",
                "post_occlusion_offset_mm", "post_occlusion_error_mm", "recovery_time_s", "occluded_flagged_invalid_frac",
                "method", "scenario", "versions"):
        assert key in data, key
    assert data["method"] == "proposed" and data["scenario"] == "occlusion"
    # planted: 0.03 mm white noise outside the occlusion, clock offset 12.3 ms
    assert data["rmse_unoccluded_mm"] == pytest.approx(0.03, rel=0.15)
    assert abs(data["sync_lag_s"] - 0.0123) < 1e-3
    assert abs(data["sync_lag_error_ms"]) < 0.5
    assert data["rmse_px"] == pytest.approx(data["rmse_mm"] * 2.8, rel=1e-3)
    assert data["mode3_expected_hz"] == pytest.approx(11.5)
    assert data["mode1_amplitude_ratio"] == pytest.approx(1.0, abs=0.05)


def test_evaluate_sees_planted_klt_errors(metrics, scenario):
    data = json.loads(metrics["klt"].read_text())
    first = csv.DictReader(Path(scenario["truth"]).open()).__next__()
    x0 = float(first["dx_mm"])  # the beam's deflection at frame 0, the tracker's datum
    assert data["mode1_amplitude_ratio"] == pytest.approx(0.83, abs=0.05)  # planted scale
    assert data["occlusion_rmse_mm"] > 2.0  # planted 3 mm garbage
    # planted 0.4 mm step + 0.01 mm/s drift (~0.095 mm at 9-10 s); the 0.83 scale
    # error on the frame-0 datum adds 0.17 x0 (the beam oscillates about 0 later)
    assert data["datum_offset_mm"] == pytest.approx(x0, abs=0.05)  # ref lacks mode 3 (30 Hz low-pass)
    assert data["post_occlusion_error_mm"] == pytest.approx(0.495 + 0.17 * data["datum_offset_mm"], abs=0.03)
    # the step itself: 0.4 mm plus the drift between the mean times before (~4 s) and after (9.5 s)
    assert data["post_occlusion_offset_mm"] == pytest.approx(0.4 + 0.01 * (9.5 - 4.0), abs=0.03)
    assert data["recovery_time_s"] is None  # never recovers
    assert data["lowfreq_power_ratio"] > 100


def test_summary_and_table1(metrics, tmp_path):
    out_csv, out_md = tmp_path / "summary.csv", tmp_path / "summary.md"
    assert main(["summary", str(metrics["proposed"]), str(metrics["klt"]), "--out", str(out_csv),
                 "--markdown", str(out_md)]) == 0
    rows = list(csv.DictReader(out_csv.open()))
    assert [(r["scenario"], r["method"]) for r in rows] == [("occlusion", "klt"), ("occlusion", "proposed")]
    assert float(rows[1]["rmse_mm"]) == pytest.approx(json.loads(metrics["proposed"].read_text())["rmse_mm"], rel=1e-5)
    assert "Reference displacement sensor" in out_md.read_text()
    t1_md, t1_csv = tmp_path / "table1.md", tmp_path / "table1.csv"
    assert main(["table1", str(metrics["proposed"]), str(metrics["klt"]), "--out-md", str(t1_md),
                 "--out-csv", str(t1_csv)]) == 0
    text = t1_md.read_text()
    assert "0.0753" in text and "0.2943" in text and "simulated" in text.lower()
    table = list(csv.DictReader(t1_csv.open()))
    assert table[3]["quantity"] == "RMSE, proposed" and float(table[3]["paper_experiment"]) == 0.0753


def test_figures_without_video(scenario, tmp_path):
    assert main(["figures", "--sensor", str(scenario["sensor"]), "--truth", str(scenario["truth"]),
                 "--sim-json", str(scenario["sim_json"]), "--render-json", str(scenario["render_json"]),
                 "--track", str(scenario["proposed"]), "--track", f"KLT={scenario['klt']}",
                 "--out-dir", str(tmp_path)]) == 0
    for name in ("fig8_time_histories", "fig9_psd", "fig10_occlusion"):
        for ext in ("png", "svg"):
            assert (tmp_path / f"{name}.{ext}").stat().st_size > 1000


def test_figures_6_7_from_video(tmp_path):
    cv2 = pytest.importorskip("cv2")
    from analysis.figures import fig_features
    h, w = 120, 160
    img = np.full((h, w), 90, np.uint8)
    img[:, 70:90] = 160  # the beam: flat inside, edges at x=70/90
    cv2.rectangle(img, (5, 5), (30, 30), 255, -1)  # background clutter with corners
    video = tmp_path / "clip.avi"
    writer = cv2.VideoWriter(str(video), cv2.VideoWriter_fourcc(*"MJPG"), 60.0, (w, h))
    assert writer.isOpened()
    for _ in range(3):
        writer.write(cv2.cvtColor(img, cv2.COLOR_GRAY2BGR))
    writer.release()
    mask = np.zeros((h, w), np.uint8)
    mask[20:100, 74:86] = 255
    cv2.imwrite(str(tmp_path / "mask.png"), mask)
    written = fig_features(video, tmp_path / "mask.png", tmp_path)
    assert {p.name for p in written} == {"fig6_poi_vs_corners.png",
                                         "fig7_gradient_magnitude.png", "fig7_gradient_magnitude.svg"}
    # Fig. 6's corners are those a KLT run tracked (its --raw-tracks file, ROI pixels), drawn
    # where they are in the frame: a red ring around (30, 30) = ROI (20, 30) + origin (10, 0).
    raw = tmp_path / "klt.npz"
    meta = json.dumps({"roi": {"x": 10, "y": 0, "width": 150, "height": h}})
    np.savez(raw, meta=np.array(meta), x_px=np.array([20.0], np.float32), y_px=np.array([30.0], np.float32))
    fig_features(video, tmp_path / "mask.png", tmp_path, klt_raw=raw)
    image = cv2.imread(str(tmp_path / "fig6_poi_vs_corners.png"))
    scale = round(600 / w)
    right = image[:, w * scale + 8:]
    assert image.shape == (h * scale, 2 * w * scale + 8, 3)
    radius = 3 * (scale // 2) + 2
    assert tuple(right[30 * scale, 30 * scale + radius]) == (0, 0, 255)
    assert tuple(right[30 * scale, 20 * scale + radius]) != (0, 0, 255)
    # and the mask's POIs in green on the left, every mask pixel
    centre = scale // 2
    assert tuple(image[50 * scale + centre, 80 * scale + centre]) == (0, 220, 0)
    assert tuple(image[50 * scale + centre, 60 * scale + centre]) != (0, 220, 0)


def test_modal_cli(scenario, tmp_path):
    out = tmp_path / "modal.json"
    assert main(["modal", "--sensor", str(scenario["sensor"]), "--sim-json", str(scenario["sim_json"]),
                 "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert abs(data["mode1_freq_error_pct"]) < 0.5 and abs(data["mode2_freq_error_pct"]) < 0.5
    assert data["mode1_mac"] > 0.99 and data["mode2_mac"] > 0.99
    assert data["heights_mm"] == [250.0, 500.0, 750.0, 800.0, 1000.0]


def test_missing_column_exits_2_naming_it(scenario, tmp_path, capsys):
    bad = tmp_path / "track.csv"
    lines = Path(scenario["proposed"]).read_text().splitlines()
    header = lines[0].split(",")
    drop = header.index("valid")
    bad.write_text("\n".join(",".join(c for j, c in enumerate(line.split(",")) if j != drop) for line in lines))
    paths = {**scenario, "proposed": bad}
    assert _evaluate(paths, "proposed", tmp_path / "m.json") == 2
    err = capsys.readouterr().err
    assert "valid" in err and "track.csv" in err
    assert not (tmp_path / "m.json").exists()


def test_nan_in_sensor_is_value_error(scenario, tmp_path):
    from analysis.readers import read_sensor
    lines = Path(scenario["sensor"]).read_text().splitlines()
    parts = lines[5].split(",")
    parts[1] = "nan"
    lines[5] = ",".join(parts)
    bad = tmp_path / "sensor.csv"
    bad.write_text("\n".join(lines))
    with pytest.raises(ValueError, match=r"sensor\.csv.*'dx_mm'.*NaN"):
        read_sensor(bad)


def test_module_entry_point_exit_code(tmp_path):
    proc = subprocess.run([sys.executable, "-m", "analysis", "summary", str(tmp_path / "none.json"),
                           "--out", str(tmp_path / "s.csv")], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 2
    assert "none.json" in proc.stderr


def test_calm_scenario_unitless_track_and_table1_choice(tmp_path):
    """No occlusion, a tracker run without a scale (dx_mm all NaN), a --config override."""
    paths = make_scenario(tmp_path / "calm", duration_s=12.0, occlusion_s=None, seed=4)
    track = Path(paths["proposed"])
    lines = track.read_text().splitlines()
    j = lines[0].split(",").index("dx_mm")
    rows = [lines[0]] + [",".join("nan" if k == j else c for k, c in enumerate(line.split(",")))
                         for line in lines[1:]]
    track.write_text("\n".join(rows) + "\n")
    config = tmp_path / "config.yaml"
    config.write_text("analysis:\n  lowpass_hz: 25.0\n  max_lag_s: 0.08\n")
    out = tmp_path / "calm_proposed.json"
    assert main(["evaluate", "--sensor", str(paths["sensor"]), "--sim-json", str(paths["sim_json"]),
                 "--truth", str(paths["truth"]), "--render-json", str(paths["render_json"]),
                 "--track", str(track), "--method", "proposed", "--scenario", "calm",
                 "--config", str(config), "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["mm_from_render_scale"] is True
    assert data["occlusion_spans"] == 0 and "recovery_time_s" not in data
    assert data["params"]["lowpass_hz"] == 25.0 and data["params"]["max_lag_s"] == 0.08
    assert data["rmse_mm"] == pytest.approx(0.03, rel=0.2)
    assert abs(data["sync_lag_s"] - 0.0123) < 1e-3
    t1_md = tmp_path / "t1.md"
    assert main(["table1", str(out), "--out-md", str(t1_md), "--out-csv", str(tmp_path / "t1.csv")]) == 0
    assert "`calm`" in t1_md.read_text()


@pytest.mark.parametrize("scale, shift_mm, expected_pct", [(1.0, 0.0, 0.0), (0.95, 0.0, -5.0), (1.0, 0.3, 0.0),
                                                          (1.05, -0.2, 5.0)])
def test_max_displacement_error_moves_with_scale_not_offset(tmp_path, scale, shift_mm, expected_pct):
    """Table 1's maximum-displacement error must see a scale error one for one and ignore a
    constant offset: it is read after the release, about each series' own rest position (the
    hold before the pluck, where every method is put into the laser's datum, is excluded).
    Mode 1 only: the 30 Hz low-pass of the reference would otherwise take part of mode 2."""
    scenario = make_scenario(tmp_path, duration_s=8.0, occlusion_s=None, amplitudes_mm=(2.2, 0.0, 0.0))
    rows = list(csv.DictReader(Path(scenario["truth"]).open()))
    truth_mm = np.array([float(r["dx_mm"]) for r in rows])
    measured = scale * (truth_mm - truth_mm[0]) + shift_mm  # a perfect tracker, scaled and shifted
    track = tmp_path / "track.csv"
    with track.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["frame", "time_s", "dx_px", "dy_px", "dx_mm", "dy_mm", "valid", "poi_kept_frac"])
        for r, value in zip(rows, measured, strict=True):
            writer.writerow([r["frame"], r["time_s"], f"{value * 2.8:.6f}", "0", f"{value:.6f}", "0", 1, 1])
    out = tmp_path / "m.json"
    assert _evaluate({**scenario, "custom": track}, "custom", out) == 0
    data = json.loads(out.read_text())
    assert data["release_s"] == 0.5
    assert data["max_disp_error_pct"] == pytest.approx(expected_pct, abs=0.2)
    assert data["p2p_first_cycles_error_pct"] == pytest.approx(expected_pct, abs=0.2)
    # the swing after the release, not the hold: the first cycles' peak-to-peak is about twice it
    assert data["p2p_first_cycles_ref_mm"] > 1.5 * data["max_disp_ref_mm"]


def test_klt_feature_gains_find_the_static_corners(scenario, tmp_path):
    """Fig. 11's gains: a feature on the beam reads gain ~1, a background corner 0, and the
    figure is written from a sparse run's --raw-tracks file."""
    from analysis.figures import fig_klt_features, klt_feature_gains
    from analysis.readers import read_truth

    truth = read_truth(scenario["truth"])
    true_px = truth["dx_px"] - truth["dx_px"][0]
    rng = np.random.default_rng(5)
    columns = [0.97 * true_px, 1.0 * true_px, np.zeros_like(true_px), 0.5 * true_px]
    dx = np.stack([c + 0.02 * rng.normal(size=c.size) for c in columns], 1).astype(np.float32)
    raw = tmp_path / "klt.npz"
    np.savez(raw, frame=truth["frame"].astype(np.int64), dx_px=dx, dy_px=np.zeros_like(dx),
             x_px=np.array([10, 20, 30, 40], np.float32), y_px=np.array([5, 5, 5, 5], np.float32))
    gains = klt_feature_gains(raw, truth)
    assert gains["gain"] == pytest.approx([0.97, 1.0, 0.0, 0.5], abs=0.01)
    written = fig_klt_features(raw, truth, None, None, 1 / 2.8, tmp_path)
    assert {p.name for p in written} == {"fig11_klt_features.png", "fig11_klt_features.svg"}
    assert all(p.stat().st_size > 1000 for p in written)


def test_a_method_that_flagged_every_frame_is_reported_unmeasured(scenario, metrics, tmp_path, capsys):
    """A run whose frames are all valid=0 (refflow's precision check on a video compressed past
    its detail) is a result, not a crash: its valid share, no error metrics, and the summary
    says so beside the methods that did measure; the figures leave it out."""
    rows = list(csv.DictReader(Path(scenario["proposed"]).open()))
    flagged = tmp_path / "flagged.csv"
    with flagged.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        for row in rows:
            writer.writerow({**row, "dx_px": "nan", "dy_px": "nan", "dx_mm": "nan", "dy_mm": "nan", "valid": 0})
    out = tmp_path / "flagged.json"
    assert _evaluate({**scenario, "flagged": flagged}, "flagged", out) == 0
    data = json.loads(out.read_text())
    assert data["valid_frac"] == 0 and data["compared_frames"] == 0 and "rmse_mm" not in data
    assert "at least 8" in data["unmeasured"]
    md = tmp_path / "summary.md"
    assert main(["summary", str(out), str(metrics["klt"]), "--out", str(tmp_path / "s.csv"),
                 "--markdown", str(md)]) == 0
    lines = md.read_text().splitlines()
    assert any(line.startswith("| flagged | ") and "every frame flagged" in line and "| 0 |" in line for line in lines)
    sensor = next(line for line in lines if line.startswith("| Reference displacement sensor"))
    assert sensor.split("|")[2].strip() == f"{json.loads(metrics['klt'].read_text())['max_disp_ref_mm']:.4g}"
    figs = tmp_path / "figs"
    assert main(["figures", "--sensor", str(scenario["sensor"]), "--sim-json", str(scenario["sim_json"]),
                 "--truth", str(scenario["truth"]), "--render-json", str(scenario["render_json"]),
                 "--track", str(flagged), "--track", str(scenario["klt"]), "--out-dir", str(figs)]) == 0
    assert (figs / "fig8_time_histories.png").is_file()
    assert "flagged: 0 valid frames outside occlusions, not plotted" in capsys.readouterr().err
