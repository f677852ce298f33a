"""The CI workbench end to end: `snakemake` on config/ci.yaml, then the accuracy gates.

Simulates, renders (short crop clips of the paper's ambient and occlusion
experiments), tracks with every CI method, evaluates, and fails with the
gate table when a gate of config/gates.yaml is missed.
"""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def workbench(tmp_path_factory) -> Path:
    results = tmp_path_factory.mktemp("results-ci")
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "MPLBACKEND": "Agg",
           "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    cmd = [str(BIN / "snakemake"), "--cores", "2", "--configfile", "config/ci.yaml",
           "--config", f"results_dir={results}", "--quiet", "rules"]
    run = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=1500)
    if run.returncode != 0:
        logs = "\n".join(f"--- {p}\n{p.read_text()[-2000:]}" for p in sorted(results.rglob("*.log")))
        pytest.fail(f"snakemake failed ({run.returncode}):\n{run.stderr[-4000:]}\n{logs}")
    return results


def test_dense_runs_were_split_into_frame_ranges_and_merged(workbench):
    # ci.yaml: 100-frame jobs; the 3 s ambient clip has 180 frames -> 2 parts
    sidecar = json.loads((workbench / "ambient/track/deepflow.json").read_text())
    assert [p["frames"] for p in sidecar["parts"]] == [[0, 100], [100, 180]]
    # the tool was given what a user has: a calibration, the video's place on the sensor,
    # and the beam's edges as the scale reference
    assert sidecar["calibration"]["video_origin"] != [0, 0]
    assert "known length 5.0 mm" in sidecar["scale"]["source"]


def test_summary_has_every_scenario_and_method(workbench):
    rows = list(csv.DictReader((workbench / "summary.csv").open()))
    assert {(r["scenario"], r["method"]) for r in rows} == {
        (s, m) for s in ("ambient", "occlusion") for m in ("deepflow", "dis", "klt")
    }
    assert all(float(r["rmse_mm"]) >= 0 for r in rows)
    assert (workbench / "table1.md").read_text().count("simulated") >= 1


def test_accuracy_gates(workbench):
    metrics = sorted(str(p) for p in workbench.glob("*/metrics/*.json") if p.stem != "modal")
    run = subprocess.run([sys.executable, "-m", "analysis", "gates", *metrics,
                          "--gates", str(ROOT / "config/gates.yaml")],
                         cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, f"accuracy gates failed:\n{run.stdout}{run.stderr}"


def test_rerun_does_nothing(workbench):
    run = subprocess.run([str(BIN / "snakemake"), "--cores", "1", "--configfile", "config/ci.yaml",
                          "--config", f"results_dir={workbench}", "-n"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert "Nothing to be done" in run.stdout + run.stderr


def _dry_run(config_path: Path, results: Path) -> str:
    run = subprocess.run([str(BIN / "snakemake"), "--cores", "1", "--configfile", str(config_path),
                          "--config", f"results_dir={results}", "-n"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    return run.stdout + run.stderr


def _scheduled_scenarios(dry_run_output: str) -> set[str]:
    """The scenarios whose jobs a dry run lists."""
    return {line.split("scenario=")[1].split(",")[0].strip()
            for line in dry_run_output.splitlines() if "wildcards:" in line and "scenario=" in line}


def test_changing_one_scenario_reruns_only_that_scenario(workbench, tmp_path):
    import yaml

    config = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    config["scenarios"]["occlusion"]["occlusion"]["start_s"] += 0.25
    changed = tmp_path / "ci_occlusion_changed.yaml"
    changed.write_text(yaml.safe_dump(config))
    out = _dry_run(changed, workbench)
    scenarios = _scheduled_scenarios(out)
    assert scenarios == {"occlusion"}, out[-3000:]
    assert "rule render:" in out


def test_report_is_browsable(workbench, tmp_path):
    report = tmp_path / "report.html"
    run = subprocess.run([str(BIN / "snakemake"), "--configfile", "config/ci.yaml",
                          "--config", f"results_dir={workbench}", "--report", str(report)],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    html = report.read_text(errors="replace")
    # captions of the summary table and the figures, and the figures themselves
    assert "Accuracy of every method" in html and "fig8_time_histories" in html
    assert report.stat().st_size > 100_000


def test_changing_a_tracking_parameter_reruns_only_tracking(workbench, tmp_path):
    import yaml

    config = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    config["defaults"]["track"]["methods"]["dis"] = {"preset": "fast"}
    changed = tmp_path / "ci_changed.yaml"
    changed.write_text(yaml.safe_dump(config))
    run = subprocess.run([str(BIN / "snakemake"), "--cores", "1", "--configfile", str(changed),
                          "--config", f"results_dir={workbench}", "-n"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    jobs = {line.split()[0] for line in run.stdout.splitlines()
            if line[:1].isalpha() and len(line.split()) == 2 and line.split()[1].isdigit()}
    assert "track_part" in jobs and "merge_track" in jobs, run.stdout
    assert not jobs & {"simulate", "render", "modes", "calibrate"}, f"re-ran upstream stages: {sorted(jobs)}"


def test_seeds_add_replicates_without_rerunning_the_first(workbench, tmp_path):
    """`seeds: [a, b]` on a scenario runs it once more as NAME-seedb (fresh draws); NAME
    itself keeps seed a (here the defaults' seed), so nothing of it re-runs."""
    import yaml

    config = yaml.safe_load((ROOT / "config/ci.yaml").read_text())
    config["scenarios"]["ambient"]["seeds"] = [config["defaults"]["seed"], 12]
    changed = tmp_path / "ci_seeds.yaml"
    changed.write_text(yaml.safe_dump(config))
    out = _dry_run(changed, workbench)
    scenarios = _scheduled_scenarios(out)
    assert scenarios == {"ambient-seed12"}, out[-3000:]
    assert "rule simulate:" in out and "rule render:" in out and "rule summary:" in out
    # a replicate that would clash with a configured scenario is refused
    config["scenarios"]["ambient"]["seeds"] = [11, 4]
    config["scenarios"]["ambient-seed4"] = {}
    changed.write_text(yaml.safe_dump(config))
    run = subprocess.run([str(BIN / "snakemake"), "--cores", "1", "--configfile", str(changed),
                          "--config", f"results_dir={workbench}", "-n"],
                         cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert run.returncode != 0 and "seed replicate" in run.stdout + run.stderr


def test_interrupted_run_resumes(workbench, tmp_path):
    """Ctrl-C in the middle of a tracking job, then the same command again: it finishes
    what was left and nothing else, with no half-written file in between."""
    import signal
    import time

    # A tracking job of the CI workbench takes a few seconds: so that Ctrl-C surely lands
    # inside one, the first run's `refflow track` waits before it starts (a shim first on
    # its PATH). refflow's own clean-up on Ctrl-C is tested in tests/integration/test_cli_track.py.
    shim = tmp_path / "bin"
    shim.mkdir()
    waiting = tmp_path / "tracking-started"
    (shim / "refflow").write_text(f'#!/bin/sh\nif [ "$1" = track ]; then touch "{waiting}"; sleep 60; fi\n'
                                  f'exec "{BIN / "refflow"}" "$@"\n')
    (shim / "refflow").chmod(0o755)

    target = workbench / "occlusion/track/deepflow.csv"
    # as in a first run that was stopped: the measurement and everything after it are not there yet
    for name in ("occlusion/track/deepflow.csv", "occlusion/track/deepflow.json",
                 "occlusion/metrics/deepflow.json", "summary.csv", "summary.md", "table1.md",
                 "table1.csv", "timings.md"):
        (workbench / name).unlink()
    env = {**os.environ, "PYOPENGL_PLATFORM": "egl", "MPLBACKEND": "Agg",
           "PATH": f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}"}
    cmd = [str(BIN / "snakemake"), "--cores", "2", "--configfile", "config/ci.yaml",
           "--config", f"results_dir={workbench}", "--rerun-incomplete"]
    slowed = {**env, "PATH": f"{shim}{os.pathsep}{env['PATH']}"}
    # A terminal's Ctrl-C reaches processes that do not ignore SIGINT; a test run started in
    # the background of a script inherits SIGINT ignored, so the run gets the default back.
    run = subprocess.Popen(cmd, cwd=ROOT, env=slowed, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                           text=True, start_new_session=True,
                           preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline and run.poll() is None and not waiting.exists():
        time.sleep(0.2)
    time.sleep(0.5)
    assert run.poll() is None, "the run ended before it could be interrupted"
    os.killpg(run.pid, signal.SIGINT)  # what Ctrl-C at a terminal sends
    try:
        out, _ = run.communicate(timeout=120)
    except subprocess.TimeoutExpired:
        os.killpg(run.pid, signal.SIGKILL)
        out, _ = run.communicate()
        pytest.fail("the interrupted run did not stop within 120 s: " + out[-3000:])
    assert run.returncode != 0, out[-2000:]
    assert not target.exists()
    assert not list(workbench.glob("occlusion/track/parts/*.npz.*")), "a half-written part was left"
    again = subprocess.run(cmd, cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    assert target.exists()
    assert "Nothing to be done" in _dry_run(ROOT / "config/ci.yaml", workbench)
