"""The figures quoted in README.md and docs/results/README.md are those of the committed report in docs/results."""

import re
from pathlib import Path

import pandas as pd
import pytest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "docs" / "results"
NAMES = {"cig_td3": "CIG-TD3", "traco": "TraCo", "itd3": "ITD3", "ippo": "IPPO", "copo": "CoPO"}


def _success(report: Path) -> tuple[pd.Series, pd.Series]:
    """Mean success per method and per (method, trained seed), recomputed from the per-episode table."""
    r = pd.read_csv(report / "results.csv")
    r = r[(r["backend"] == "native") & (r["agent_count"] == r["trained_agent_count"])]
    return r.groupby("method")["success_rate"].mean(), r.groupby(["method", "trained_seed"])["success_rate"].mean()


def _table_rows(columns: int, second_cell_has: str = "") -> dict[str, list[str]]:
    """Rows of the Results section's tables with ``columns`` cells (the second holding a text), keyed by their first."""
    text = (RESULTS / "README.md").read_text()
    section = text.split("\n## Results\n", 1)[1].split("\n## ", 1)[0]
    rows = {}
    for line in section.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if line.startswith("|") and len(cells) == columns and cells[0] in NAMES.values() and second_cell_has in cells[1]:
            rows[cells[0]] = cells
    return rows


def _number(cell: str) -> float:
    return float(cell.strip("* "))


def test_results_table_quotes_the_committed_reports_success():
    mean, per_seed = _success(RESULTS)
    selected, _ = _success(RESULTS / "validation_selected")
    rows = _table_rows(8)
    assert set(rows) == set(NAMES.values())
    for method, name in NAMES.items():
        cells = rows[name]
        assert _number(cells[1]) == pytest.approx(100 * mean[method], abs=0.051), name
        seeds = [float(x) for x in cells[2].split(",")]
        assert seeds == pytest.approx(per_seed[method].sort_index().to_numpy(), abs=0.00051), name
        assert _number(cells[7]) == pytest.approx(100 * selected[method], abs=0.051), name


def test_paired_tests_quoted_are_those_of_the_committed_stats():
    tables = {
        1: (RESULTS, "episode"),
        2: (RESULTS, "seed"),
        3: (RESULTS / "validation_selected", "episode"),
        4: (RESULTS / "validation_selected", "seed"),
    }
    rows = _table_rows(5, second_cell_has="p = ")
    assert set(rows) == set(NAMES.values()) - {"CIG-TD3"}
    for column, (report, unit) in tables.items():
        stats = pd.read_csv(report / "stats.csv")
        stats = stats[(stats["metric"] == "success_rate") & (stats["method"] == "cig_td3") & (stats["unit"] == unit)]
        for method, name in NAMES.items():
            if method == "cig_td3":
                continue
            row = stats[stats["baseline"] == method].iloc[0]
            cell = rows[name][column]
            p = float(re.search(r"p = ([0-9.e+-]+)", cell).group(1))
            assert p == pytest.approx(row["p"], rel=0.2), (name, unit, cell)
            assert ("not significant" not in cell) == bool(row["significant"]), (name, unit, cell)


def test_readme_quotes_the_committed_success_figures():
    mean, _ = _success(RESULTS)
    selected, _ = _success(RESULTS / "validation_selected")
    text = (ROOT / "README.md").read_text()
    paragraph = text.split("**Results** (`docs/results/`", 1)[1].split("\n\n", 1)[0]
    for method in NAMES:
        assert f"{100 * mean[method]:.1f} %" in paragraph, method
    assert f"({100 * selected['cig_td3']:.1f} %" in paragraph
