"""COIN's Table 5.1 as data, and a report's results beside it (hand-computed differences, units, density filter)."""

import math

import pandas as pd

from coin_app.evaluation import paper_table
from coin_app.evaluation.paper_table import PAPER_METRICS, TABLE_5_1, at_paper_density, beside_paper, to_markdown
from coin_app.evaluation.reference import PAPER


def test_the_table_has_seven_methods_six_metrics_on_three_scenes_and_coin_leads_each():
    assert set(TABLE_5_1) == {"intersection", "roundabout", "bottleneck"}
    for scene, rows in TABLE_5_1.items():
        assert set(rows) == {"ippo", "mfpo", "cppo", "copo", "itd3", "traco", "cig_td3"}
        assert all(tuple(r) == PAPER_METRICS for r in rows.values())
        best = max(rows, key=lambda m: rows[m]["success_rate"][0])  # the paper's claim: COIN best in success and collision
        safest = min(rows, key=lambda m: rows[m]["collision_rate"][0])
        assert best == safest == "cig_td3", scene
    # the figures the issues quote, typed here by hand from the paper
    assert TABLE_5_1["intersection"]["ippo"]["success_rate"] == (69.96, 15.21)
    assert TABLE_5_1["bottleneck"]["itd3"]["avg_travel_steps"] == (301.27, 49.6)
    assert PAPER["intersection"] == (88.78, 4.13, 3.94) and PAPER["roundabout"][0] == 90.68 and PAPER["bottleneck"][0] == 96.33


def test_beside_the_paper_by_hand():
    summary = pd.DataFrame(
        [
            ["intersection", "cig_td3", "success_rate", 0.9, 0.1, 100],
            ["intersection", "cig_td3", "avg_travel_steps", 500.0, 50.0, 100],
            ["intersection", "ippo", "collision_rate", 0.25, float("nan"), 1],
            ["intersection", "heuristic", "success_rate", 0.5, 0.1, 20],  # not in the paper: left out
        ],
        columns=["scenario", "label", "metric", "mean", "std", "n"],
    )
    got = beside_paper(summary)
    assert got[["label", "metric"]].values.tolist() == [
        ["cig_td3", "success_rate"],
        ["cig_td3", "avg_travel_steps"],
        ["ippo", "collision_rate"],
    ]
    first = got.iloc[0]
    assert (first.ours, first.ours_std, first.paper, first.paper_std, first.n) == (90.0, 10.0, 88.78, 10.09, 100)
    assert math.isclose(first.difference, 1.22)
    assert math.isclose(got.iloc[1].difference, 500.0 - 509.60)  # travel steps are not scaled
    assert math.isclose(got.iloc[2].difference, 25.0 - 18.00)
    md = to_markdown(got, "t")
    assert "### intersection (30 vehicles)" in md
    assert "| ippo (IPPO) |" in md and md.index("ippo (IPPO)") < md.index("cig_td3 (COIN)")  # Table 5.1's order
    assert "90.00 (10.00) / 88.78 (10.09)" in md and "25.00 / 18.00 (7.20)" in md


def test_only_models_trained_and_tested_at_the_papers_density_are_beside_it():
    rows = pd.DataFrame(
        {
            "scenario": ["intersection", "intersection", "intersection", "roundabout", "bottleneck"],
            "trained_agent_count": [30, 4, 30, 40, 20],
            "agent_count": [30, 4, 40, 40, 20],
        }
    )
    assert at_paper_density(rows).index.tolist() == [0, 3, 4]
    assert paper_table.PAPER_COUNTS == {"intersection": 30, "roundabout": 40, "bottleneck": 20}
