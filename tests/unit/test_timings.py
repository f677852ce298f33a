"""Per-rule timings from Snakemake benchmark files (analysis.timings)."""

from __future__ import annotations

import pytest

from analysis.__main__ import main
from analysis.timings import find_benchmarks, read_benchmark, timings_markdown

HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"
RULES = ["track", "track_part", "render", "summary"]


def _bench(path, *walls, rss=100.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER + "".join(f"{w}\t0:00:00\t{rss}\t1\t1\t1\t0\t0\t50\t{w / 2}\n" for w in walls))
    return path


def test_rule_scenario_and_detail_from_the_path(tmp_path):
    job = read_benchmark(_bench(tmp_path / "ambient/benchmarks/track_part_deepflow_0.tsv", 4.0), RULES,
                         "ambient")
    assert (job.rule, job.scenario, job.detail) == ("track_part", "ambient", "deepflow_0")
    assert job.wall_s == 4.0 and job.cpu_s == 2.0
    once = read_benchmark(_bench(tmp_path / "benchmarks/summary.tsv", 1.0, 3.0), RULES)
    assert (once.rule, once.scenario, once.wall_s) == ("summary", "", 2.0)  # mean of repeats


def test_unknown_rule_and_empty_file_are_errors(tmp_path):
    with pytest.raises(ValueError, match="matches none of the rules"):
        read_benchmark(_bench(tmp_path / "a/benchmarks/nope.tsv", 1.0), RULES)
    empty = tmp_path / "a/benchmarks/render.tsv"
    empty.write_text(HEADER)
    with pytest.raises(ValueError, match="not a Snakemake benchmark"):
        read_benchmark(empty, RULES)


def test_table_sums_per_rule_and_scenario(tmp_path):
    paths = [_bench(tmp_path / "ambient/benchmarks/track_deepflow.tsv", 30.0, rss=500),
             _bench(tmp_path / "ambient/benchmarks/track_klt.tsv", 10.0),
             _bench(tmp_path / "occlusion/benchmarks/render.tsv", 20.0),
             _bench(tmp_path / "benchmarks/summary.tsv", 0.5)]
    found = find_benchmarks(tmp_path)
    assert [(p, s) for p, s in found] == [(paths[3], ""), (paths[0], "ambient"), (paths[1], "ambient"),
                                         (paths[2], "occlusion")]
    text = timings_markdown([read_benchmark(p, RULES, s) for p, s in found])
    assert "4 jobs, 1.0 min" in text
    assert "| track | 2 | 40.0 | 66.1 | 30.0 (ambient/deepflow) | 500 |" in text
    assert "| ambient | 2 | 40.0 | 40.0 |" in text and "| occlusion | 1 | 20.0 | 0.0 |" in text


def test_cli_writes_the_table_and_fails_without_benchmarks(tmp_path, capsys):
    _bench(tmp_path / "res/ambient/benchmarks/render.tsv", 2.0)
    out = tmp_path / "timings.md"
    assert main(["timings", str(tmp_path / "res"), "--rules", *RULES, "--out", str(out)]) == 0
    assert "| render | 1 | 2.0 |" in out.read_text()
    assert main(["timings", str(tmp_path / "none"), "--rules", *RULES, "--out", str(out)]) == 2
    assert "no benchmarks" in capsys.readouterr().err
