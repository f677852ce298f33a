"""CI gates fail loudly, with the gate named, when accuracy regresses."""

from __future__ import annotations

import json
import re

import pytest

from analysis.__main__ import main
from analysis.gates import check, format_table, load_metrics

GATES = [
    {"name": "deepflow accuracy", "scenario": "ambient", "method": "deepflow",
     "metric": "rmse_pct_of_max_ref", "max": 3.0},
    {"name": "klt worse", "scenario": "ambient", "better": "deepflow", "worse": "klt",
     "metric": "rmse_mm"},
    {"name": "recovery", "scenario": "occlusion", "method": "deepflow",
     "metric": "post_occlusion_offset_mm", "abs": True, "max": 0.05},
]


def _write(tmp_path, scenario, method, **values):
    path = tmp_path / f"{scenario}_{method}.json"
    path.write_text(json.dumps({"scenario": scenario, "method": method, **values}))
    return path


@pytest.fixture
def good(tmp_path):
    return [
        _write(tmp_path, "ambient", "deepflow", rmse_pct_of_max_ref=1.2, rmse_mm=0.02),
        _write(tmp_path, "ambient", "klt", rmse_pct_of_max_ref=9.0, rmse_mm=0.2),
        _write(tmp_path, "occlusion", "deepflow", post_occlusion_offset_mm=-0.01),
    ]


def test_all_gates_pass_on_good_metrics(good):
    rows = check(GATES, load_metrics(good))
    assert [r["passed"] for r in rows] == [True, True, True]
    assert format_table(rows).endswith("3 passed, 0 failed")


def test_regressions_fail_their_gates(tmp_path):
    paths = [
        _write(tmp_path, "ambient", "deepflow", rmse_pct_of_max_ref=3.5, rmse_mm=0.3),
        _write(tmp_path, "ambient", "klt", rmse_pct_of_max_ref=9.0, rmse_mm=0.2),
        _write(tmp_path, "occlusion", "deepflow", post_occlusion_offset_mm=-0.2),
    ]
    rows = check(GATES, load_metrics(paths))
    assert [r["passed"] for r in rows] == [False, False, False]
    table = format_table(rows)
    assert re.search(r"FAIL +deepflow accuracy", table) and "0 passed, 3 failed" in table


def test_missing_or_nan_metric_fails(tmp_path):
    paths = [_write(tmp_path, "ambient", "deepflow", rmse_pct_of_max_ref=None, rmse_mm=0.1)]
    rows = check(GATES, load_metrics(paths))
    assert not any(r["passed"] for r in rows)


def test_cli_exit_codes(good, tmp_path, capsys):
    import yaml

    spec = tmp_path / "gates.yaml"
    spec.write_text(yaml.safe_dump({"gates": GATES}))
    assert main(["gates", *map(str, good), "--gates", str(spec), "--out", str(tmp_path / "g.json")]) == 0
    assert json.loads((tmp_path / "g.json").read_text())["passed"] is True
    strict = [dict(GATES[0], max=1.0)]
    spec.write_text(yaml.safe_dump({"gates": strict}))
    assert main(["gates", *map(str, good), "--gates", str(spec)]) == 1
    assert "FAIL" in capsys.readouterr().out
    spec.write_text("gates: []\n")
    assert main(["gates", *map(str, good), "--gates", str(spec)]) == 2
