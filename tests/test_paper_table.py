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


def _results(method, seeds, success, count=30, scenario="intersection"):
    """Result rows of ``method``: 3 test seeds per trained seed, success rates from ``success`` (one per row)."""
    rows, k = [], 0
    for seed in seeds:
        for test_seed in (200000, 200001, 200002):
            s = success[k % len(success)]
            k += 1
            rows.append(
                {"method": method, "variant": "default", "trained_seed": seed, "test_seed": test_seed, "scenario": scenario}
                | {"agent_count": count, "trained_agent_count": count, "backend": "native", "success_rate": s}
                | {"collision_rate": 1 - s, "out_of_road_rate": 0.0, "efficiency": 10 * s, "safety": -10 * (1 - s)}
                | {"avg_travel_steps": 400.0, "avg_travel_steps_arrived": 300.0, "episode_return": 1.0, "num_vehicles": 40}
                | {"episode_length": 1000, "wall_time_s": 1.0, "trained_env_steps": 1000, "checkpoint": f"runs/{method}-s{seed}"}
            )
    return rows


def test_a_report_at_the_papers_density_has_the_paper_beside_it_and_the_authors_row_outside_the_tests(tmp_path, monkeypatch):
    from coin_app.evaluation import report
    from coin_app.evaluation.reference import REFERENCE_METHOD

    rows = _results("cig_td3", (0, 1), [0.9, 0.8, 1.0]) + _results("ippo", (0, 1), [0.6, 0.7, 0.5])
    rows += _results("itd3", (0,), [0.5], count=4, scenario="roundabout")  # 4 vehicles: in the main table, not beside the paper
    source = tmp_path / "in" / "results.csv"
    source.parent.mkdir()
    pd.DataFrame(rows).to_csv(source, index=False)
    asked = []

    def authors(root, scene, test_seeds, workers, log, backend="native", cache=None):
        asked.append((scene, list(test_seeds)))
        assert backend == "native"
        return pd.DataFrame(_results(REFERENCE_METHOD, (1000, 2000), [0.95]))

    monkeypatch.setattr(report, "test_seed_rows", authors)
    options = report.ReportOptions(tsne_samples=10, reference_actors=str(tmp_path))
    report.build_report([source], tmp_path / "out", options, log=lambda _line: None)
    assert asked == [("intersection", [200000, 200001, 200002])]  # only the scene at the paper's density, on its test seeds
    main = (tmp_path / "out" / "table_main.md").read_text()
    assert f"| {REFERENCE_METHOD} |" in main and "| itd3 |" in main and "### roundabout" in main
    beside = pd.read_csv(tmp_path / "out" / "table_paper.csv")
    success = beside[beside["metric"] == "success_rate"].set_index("label")
    assert sorted(success.index) == ["cig_td3", "coin_authors", "ippo"]
    assert (success.at["coin_authors", "ours"], success.at["coin_authors", "paper"]) == (95.0, 88.78)  # beside COIN's row
    assert math.isclose(success.at["cig_td3", "ours"], 90.0) and math.isclose(success.at["cig_td3", "difference"], 90.0 - 88.78)
    assert math.isclose(success.at["ippo", "ours"], 60.0) and math.isclose(success.at["ippo", "paper"], 69.96)
    stats = pd.read_csv(tmp_path / "out" / "stats.csv")
    assert set(stats["baseline"]) == {"ippo"}  # the authors' actors are a reference row, not a baseline
    # redrawn from its own results, the authors' rows are read, not evaluated again
    report.build_report([tmp_path / "out" / "results.csv"], tmp_path / "again", options, log=lambda _line: None)
    assert len(asked) == 1 and f"| {REFERENCE_METHOD} |" in (tmp_path / "again" / "table_main.md").read_text()


def test_a_missing_reference_actors_directory_is_refused_before_any_work(tmp_path):
    import pytest

    from coin_app.evaluation.report import ReportOptions

    with pytest.raises(ValueError, match=r"bad --reference-actors '.*nowhere'; allowed: a directory of the COIN authors' actors"):
        ReportOptions(reference_actors=str(tmp_path / "nowhere")).check()


def test_the_authors_actors_transfer_on_the_same_seeds_beside_the_models(tmp_path, monkeypatch):
    from coin_app.evaluation import report
    from coin_app.evaluation.protocol import Evaluation
    from coin_app.evaluation.reference import REFERENCE_METHOD

    source = tmp_path / "in" / "results.csv"
    source.parent.mkdir()
    pd.DataFrame(_results("cig_td3", (0,), [0.9])).to_csv(source, index=False)
    native_authors = pd.DataFrame(_results(REFERENCE_METHOD, (1000,), [0.95]))
    asked = []

    def authors(root, scene, test_seeds, workers, log, backend="native", cache=None):
        asked.append((backend, list(test_seeds)))
        rows = native_authors[native_authors["test_seed"].isin(test_seeds)]
        return rows.assign(backend=backend, success_rate=0.9 if backend == "metadrive" else 0.95)

    def models(runs, seeds, workers, log, backend, cache=None):  # the sweep's models on MetaDrive: 10 points lower
        rows = pd.DataFrame(_results("cig_td3", (0,), [0.8]))
        return Evaluation(rows[rows["test_seed"].isin(seeds)].assign(backend=backend), [], 1.0)

    monkeypatch.setattr(report, "test_seed_rows", authors)
    monkeypatch.setattr(report, "run_evaluation", models)
    monkeypatch.setattr(report, "metadrive_available", lambda: True)
    options = report.ReportOptions(tsne_samples=10, reference_actors=str(tmp_path), transfer="metadrive", transfer_test_seeds=2)
    report.build_report([source], tmp_path / "out", options, log=lambda _line: None)
    assert asked == [("native", [200000, 200001, 200002]), ("metadrive", [200000, 200001])]
    gap = pd.read_csv(tmp_path / "out" / "table_transfer.csv")
    success = gap[gap["metric"] == "success_rate"].set_index("label")
    assert math.isclose(success.at[REFERENCE_METHOD, "gap"], -0.05) and math.isclose(success.at["cig_td3", "gap"], -0.1)
    assert set(success["n"]) == {2}


def test_a_scene_without_the_authors_actors_is_named_and_the_report_goes_on(tmp_path, monkeypatch):
    from coin_app.evaluation import report
    from coin_app.evaluation.reference import REFERENCE_METHOD

    source = tmp_path / "in" / "results.csv"
    source.parent.mkdir()
    pd.DataFrame(_results("cig_td3", (0,), [0.9]) + _results("ippo", (0,), [0.6])).to_csv(source, index=False)

    def missing(root, scene, test_seeds, workers, log, backend="native", cache=None):
        raise ValueError(f"no {scene} actors (TD3_{scene}_<seed>_best_model_*_actor) under {root}")

    monkeypatch.setattr(report, "test_seed_rows", missing)
    options = report.ReportOptions(tsne_samples=10, reference_actors=str(tmp_path))
    summary = report.build_report([source], tmp_path / "out", options, log=lambda _line: None)
    assert [f["error"] for f in summary["failures"]] == [
        f"ValueError: no intersection actors (TD3_intersection_<seed>_best_model_*_actor) under {tmp_path}"
    ]
    main = (tmp_path / "out" / "table_main.md").read_text()
    assert "| cig_td3 |" in main and REFERENCE_METHOD not in main
