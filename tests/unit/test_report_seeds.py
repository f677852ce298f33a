"""The summary's seed-replicate block: mean and range per method, winners only where apart."""

from __future__ import annotations

from analysis.report import seeds_markdown, separated, summary_markdown


def _row(scenario, method, rmse, seed, group="ambient"):
    return {"scenario": scenario, "method": method, "group": group, "seed": seed, "rmse_mm": rmse,
            "rmse_pct_of_max_ref": 100 * rmse / 1.8, "max_disp_error_pct": -1.0, "valid_frac": 1.0,
            "p2p_first_cycles_error_pct": -0.5}


ROWS = [
    _row("ambient", "deepflow", 0.020, 7), _row("ambient-seed8", "deepflow", 0.030, 8),
    _row("ambient-seed9", "deepflow", 0.025, 9),
    _row("ambient", "dis", 0.028, 7), _row("ambient-seed8", "dis", 0.018, 8),
    _row("ambient-seed9", "dis", 0.022, 9),
    _row("ambient", "klt", 0.40, 7), _row("ambient-seed8", "klt", 0.35, 8), _row("ambient-seed9", "klt", 0.38, 9),
    _row("occlusion", "deepflow", 0.05, 7, group="occlusion"),
]


def test_ranges_decide_who_beats_whom() -> None:
    by = {m: [r for r in ROWS if r["method"] == m and r["group"] == "ambient"] for m in ("deepflow", "dis", "klt")}
    assert separated(by["deepflow"], by["klt"]) and separated(by["dis"], by["klt"])
    assert not separated(by["deepflow"], by["dis"]) and not separated(by["dis"], by["deepflow"])
    assert not separated(by["klt"], by["deepflow"])


def test_seed_block_reports_mean_and_range() -> None:
    text = "\n".join(seeds_markdown(ROWS))
    assert "## ambient: 3 seeds (7, 8, 9)" in text
    assert "| deepflow | 3 | 0.025 [0.02, 0.03] |" in text
    assert "dis < klt" in text and "deepflow < klt" in text
    assert "~" in text and ("dis ~ deepflow" in text or "deepflow ~ dis" in text)
    assert "occlusion:" not in text  # one seed: no replicate block
    assert "## ambient-seed8" in summary_markdown(ROWS)  # each seed's own block stays
