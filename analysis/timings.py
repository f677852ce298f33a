"""Per-rule wall time and memory of a workflow run, from Snakemake's benchmark files.

Every rule of the workflow writes ``benchmark:`` files named
``<results>/<scenario>/benchmarks/<rule>[_<detail>].tsv`` (per scenario) or
``<results>/benchmarks/<rule>.tsv`` (once per run). Snakemake fills them with
``s`` (wall seconds), ``max_rss`` (MB) and ``cpu_time`` (s). This module sums
them per rule so the budget of ``snakemake all`` can be read at a glance.

Wall times are measurements, not results: unlike every other summary in
``results/``, the table differs from run to run.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from refflow.io import atomic_path


@dataclass
class Job:
    """One benchmark file: a rule run on one scenario (and detail, e.g. a method)."""

    rule: str
    scenario: str
    detail: str
    wall_s: float
    cpu_s: float
    max_rss_mb: float


def _number(value: str) -> float:
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan  # Snakemake writes "NA" where it could not measure


def read_benchmark(path: str | os.PathLike[str], rules: Sequence[str], scenario: str = "") -> Job:
    """Read one benchmark TSV; the rule is the longest known rule name the file name starts with.

    Raises
    ------
    ValueError
        If the file has no data row, lacks the ``s`` column, or its name
        matches none of ``rules``.
    """
    path = Path(path)
    with path.open(newline="") as handle:
        rows = list(csv.DictReader(handle, delimiter="\t"))
    if not rows or "s" not in rows[0]:
        raise ValueError(f"{path}: not a Snakemake benchmark file (no 's' column or no data row)")
    stem = path.stem
    matches = [r for r in rules if stem == r or stem.startswith(r + "_")]
    if not matches:
        raise ValueError(f"{path}: file name matches none of the rules {', '.join(sorted(rules))}")
    rule = max(matches, key=len)
    detail = stem[len(rule) + 1:]
    # Repeated benchmarks (``repeat()``) give several rows: the mean is the honest figure.
    n = len(rows)
    return Job(rule=rule, scenario=scenario, detail=detail,
               wall_s=sum(_number(r["s"]) for r in rows) / n,
               cpu_s=sum(_number(r.get("cpu_time", "nan")) for r in rows) / n,
               max_rss_mb=max(_number(r.get("max_rss", "nan")) for r in rows))


def find_benchmarks(results_dir: str | os.PathLike[str]) -> list[tuple[Path, str]]:
    """``(path, scenario)`` of every benchmark file: once-per-run ones first (scenario "")."""
    root = Path(results_dir)
    once = [(p, "") for p in sorted(root.glob("benchmarks/*.tsv"))]
    return once + [(p, p.parent.parent.name) for p in sorted(root.glob("*/benchmarks/*.tsv"))]


def timings_markdown(jobs: Sequence[Job]) -> str:
    """Markdown: per rule (jobs, total and largest wall time, peak memory), then per scenario."""
    total = sum(j.wall_s for j in jobs if math.isfinite(j.wall_s))
    lines = ["# Workflow timings", "",
             f"{len(jobs)} jobs, {total / 60:.1f} min of job wall time in all (summed over jobs; "
             "jobs run side by side, so the elapsed time of the run is shorter). "
             "Measured by Snakemake's `benchmark:` files; the only file in `results/` that "
             "changes from run to run.", "",
             "| Rule | Jobs | Wall time (s) | Share (%) | Longest job (s) | Peak RSS (MB) |",
             "|---|---|---|---|---|---|"]
    by_rule: dict[str, list[Job]] = {}
    for job in jobs:
        by_rule.setdefault(job.rule, []).append(job)
    order = sorted(by_rule, key=lambda r: -sum(j.wall_s for j in by_rule[r]))
    for rule in order:
        group = by_rule[rule]
        wall = sum(j.wall_s for j in group)
        longest = max(group, key=lambda j: j.wall_s)
        where = "/".join(x for x in (longest.scenario, longest.detail) if x)
        lines.append(f"| {rule} | {len(group)} | {wall:.1f} | {100 * wall / total if total else 0:.1f} "
                     f"| {longest.wall_s:.1f}{f' ({where})' if where else ''} "
                     f"| {max(j.max_rss_mb for j in group):.0f} |")
    scenarios = sorted({j.scenario for j in jobs if j.scenario})
    if scenarios:
        lines += ["", "| Scenario | Jobs | Wall time (s) | Tracking (s) |", "|---|---|---|---|"]
        for scenario in scenarios:
            group = [j for j in jobs if j.scenario == scenario]
            track = sum(j.wall_s for j in group if j.rule.startswith("track"))
            lines.append(f"| {scenario} | {len(group)} | {sum(j.wall_s for j in group):.1f} "
                         f"| {track:.1f} |")
    return "\n".join(lines) + "\n"


def write_timings(results_dir: str | os.PathLike[str], rules: Sequence[str],
                  out: str | os.PathLike[str]) -> int:
    """Write the timings table of every benchmark under ``results_dir``; returns the job count."""
    paths = find_benchmarks(results_dir)
    if not paths:
        raise ValueError(f"{results_dir}: no benchmarks/*.tsv files found (run the workflow first)")
    jobs = [read_benchmark(p, rules, scenario) for p, scenario in paths]
    with atomic_path(out) as tmp:
        tmp.write_text(timings_markdown(jobs))
    return len(jobs)
