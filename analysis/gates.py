"""Accuracy gates: thresholds on the metrics that CI enforces.

``config/gates.yaml`` lists gates; each names a scenario and either a bound
on one method's metric (``method``, ``metric``, ``max``/``min``, optional
``abs: true``) or an ordering of two methods (``better``, ``worse``,
``metric``: the worse method's value must exceed the better one's).
:func:`check` returns one row per gate; :func:`format_table` prints them so a
failed CI run says which gate failed, by how much.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any


def load_metrics(paths: Sequence[str | Path]) -> dict[tuple[str, str], dict[str, Any]]:
    """``{(scenario, method): metrics}`` from evaluate's JSON files."""
    table: dict[tuple[str, str], dict[str, Any]] = {}
    for path in paths:
        data = json.loads(Path(path).read_text())
        if "scenario" not in data or "method" not in data:
            raise ValueError(f"{path}: not a metrics file (no 'scenario'/'method' keys)")
        table[(data["scenario"], data["method"])] = data
    return table


def _value(metrics: Mapping[tuple[str, str], Mapping[str, Any]], scenario: str, method: str,
           metric: str) -> float:
    try:
        raw = metrics[(scenario, method)][metric]
    except KeyError:
        return math.nan
    return math.nan if raw is None else float(raw)


def check(gates: Sequence[Mapping[str, Any]],
          metrics: Mapping[tuple[str, str], Mapping[str, Any]]) -> list[dict[str, Any]]:
    """Evaluate every gate; a missing or NaN value fails its gate."""
    rows = []
    for gate in gates:
        name, scenario, metric = gate["name"], gate["scenario"], gate["metric"]
        if "better" in gate:
            better = _value(metrics, scenario, gate["better"], metric)
            worse = _value(metrics, scenario, gate["worse"], metric)
            passed = math.isfinite(better) and math.isfinite(worse) and worse > better
            rows.append({"gate": name, "scenario": scenario,
                         "what": f"{metric}: {gate['worse']} > {gate['better']}",
                         "value": f"{worse:.4g} vs {better:.4g}", "passed": passed})
            continue
        value = _value(metrics, scenario, gate["method"], metric)
        shown = abs(value) if gate.get("abs") else value
        bounds = []
        passed = math.isfinite(shown)
        if "max" in gate:
            passed = passed and shown <= float(gate["max"])
            bounds.append(f"<= {gate['max']}")
        if "min" in gate:
            passed = passed and shown >= float(gate["min"])
            bounds.append(f">= {gate['min']}")
        if not bounds:
            raise ValueError(f"gate {name!r} needs 'max', 'min' or 'better'/'worse'")
        label = f"|{metric}|" if gate.get("abs") else metric
        rows.append({"gate": name, "scenario": scenario,
                     "what": f"{gate['method']} {label} {' and '.join(bounds)}",
                     "value": f"{shown:.4g}", "passed": passed})
    return rows


def format_table(rows: Sequence[Mapping[str, Any]]) -> str:
    """A fixed-width table of gate results, failures marked."""
    header = ("result", "gate", "scenario", "requirement", "measured")
    body = [("PASS" if r["passed"] else "FAIL", r["gate"], r["scenario"], r["what"], r["value"])
            for r in rows]
    widths = [max(len(str(x)) for x in col) for col in zip(header, *body, strict=True)]
    lines = ["  ".join(str(x).ljust(w) for x, w in zip(line, widths, strict=True))
             for line in (header, *body)]
    failed = sum(not r["passed"] for r in rows)
    lines.append(f"{len(rows) - failed} passed, {failed} failed")
    return "\n".join(lines)
