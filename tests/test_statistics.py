"""Report statistics and tables against hand-computed values: means, paired t-tests, Bonferroni, bold/underline."""

import math

import numpy as np
import pandas as pd
import pytest

from coin_app.evaluation import statistics, tables
from coin_app.evaluation.embedding import kmeans, tsne
from coin_app.evaluation.marl_eval import to_marl_eval


def _episodes(method, scenario, values, variant="default", seed=0, count=4):
    """Synthetic per-episode rows: values maps metric -> list over test seeds 0..k-1."""
    n = len(next(iter(values.values())))
    base = {
        "method": method,
        "variant": variant,
        "trained_seed": seed,
        "scenario": scenario,
        "agent_count": count,
        "trained_agent_count": 4,
        "checkpoint": f"/ckpt/{method}-{variant}-{seed}",
        "trained_env_steps": 1000,
    }
    rows = []
    for k in range(n):
        row = base | {"test_seed": k}
        for metric in ("success_rate", "collision_rate", "out_of_road_rate", "efficiency", "safety", "avg_travel_steps", "episode_return"):
            row[metric] = values.get(metric, [0.0] * n)[k]
        rows.append(row)
    return rows


def _table():
    rows = []
    # intersection: ours 0.5/0.7/0.9 vs base 0.4/0.5/0.6 -> differences 0.1, 0.2, 0.3
    rows += _episodes("ours", "intersection", {"success_rate": [0.5, 0.7, 0.9], "safety": [-2, -1, 0], "efficiency": [1, 3, 5]})
    rows += _episodes("base", "intersection", {"success_rate": [0.4, 0.5, 0.6, 0.9], "safety": [-3, -3, -3, 0], "efficiency": [1, 3, 5, 7]})
    # roundabout: differences 1, 3 on safety (two pairs)
    rows += _episodes("ours", "roundabout", {"success_rate": [1.0, 0.0], "safety": [0, 0], "efficiency": [2, 2]})
    rows += _episodes("base", "roundabout", {"success_rate": [0.0, 0.0], "safety": [-1, -3], "efficiency": [2, 2]})
    table = pd.DataFrame(rows)
    return table.sample(frac=1.0, random_state=3).reset_index(drop=True)  # row order must not matter


def test_paired_t_tests_match_hand_computation_and_bonferroni():
    main = statistics.main_rows(statistics.at_training_count(_table()))
    res = statistics.paired_tests(main, "ours", alpha=0.01).set_index(["scenario", "metric"])
    # 2 scenarios x 1 baseline x 3 metrics
    assert len(res) == 6 and (res["n_tests"] == 6).all()
    assert res["threshold"].iloc[0] == pytest.approx(0.01 / 6)
    # intersection success: the 4th base episode has no partner -> 3 pairs, d = (0.1, 0.2, 0.3)
    # mean 0.2, sd 0.1, t = 0.2 / (0.1 / sqrt 3) = 2 sqrt 3; df = 2: p = 1 - t / sqrt(t^2 + 2)
    row = res.loc[("intersection", "success_rate")]
    t = 2.0 * math.sqrt(3.0)
    assert row["n_pairs"] == 3 and row["mean_diff"] == pytest.approx(0.2)
    assert row["t"] == pytest.approx(t) and row["p"] == pytest.approx(1.0 - t / math.sqrt(t * t + 2.0))
    assert not row["significant"]
    # intersection safety: d = (1, 2, 3): mean 2, sd 1, t = 2 sqrt 3 again
    assert res.loc[("intersection", "safety"), "t"] == pytest.approx(t)
    # intersection efficiency: identical episodes -> all differences 0 -> undefined, not significant
    eff = res.loc[("intersection", "efficiency")]
    assert math.isnan(eff["t"]) and math.isnan(eff["p"]) and not eff["significant"]
    # roundabout safety: d = (1, 3) -> mean 2, sd sqrt 2, t = 2 / (sqrt 2 / sqrt 2) = 2; df = 1: p = 1 - 2 atan(t) / pi
    saf = res.loc[("roundabout", "safety")]
    assert saf["t"] == pytest.approx(2.0) and saf["p"] == pytest.approx(1.0 - 2.0 * math.atan(2.0) / math.pi)
    # roundabout success: d = (1, 0): mean 0.5, sd sqrt(0.5), t = 0.5 / (sqrt(0.5) / sqrt 2) = 1
    assert res.loc[("roundabout", "success_rate"), "t"] == pytest.approx(1.0)


def test_seed_unit_pairs_each_trained_seeds_mean_over_its_paired_episodes():
    rows = []
    # seed 0: ours 1.0, 0.0 vs base 0.0, 0.0 (+ an unpaired base episode 0.9, left out) -> seed means 0.5 vs 0.0
    rows += _episodes("ours", "intersection", {"success_rate": [1.0, 0.0]}, seed=0)
    rows += _episodes("base", "intersection", {"success_rate": [0.0, 0.0, 0.9]}, seed=0)
    # seed 1: 0.6 vs 0.3 -> d 0.3; seed 2: 0.2 vs 0.3 -> d -0.1 (one test seed each)
    rows += _episodes("ours", "intersection", {"success_rate": [0.6]}, seed=1)
    rows += _episodes("base", "intersection", {"success_rate": [0.3]}, seed=1)
    rows += _episodes("ours", "intersection", {"success_rate": [0.2]}, seed=2)
    rows += _episodes("base", "intersection", {"success_rate": [0.3]}, seed=2)
    main = statistics.main_rows(pd.DataFrame(rows).sample(frac=1.0, random_state=1))
    by_seed = statistics.paired_tests(main, "ours", metrics=["success_rate"], unit="seed").iloc[0]
    # d = (0.5, 0.3, -0.1): mean 0.7 / 3, sd sqrt(((0.5-m)^2 + (0.3-m)^2 + (-0.1-m)^2) / 2), df 2
    d = np.array([0.5, 0.3, -0.1])
    t = d.mean() / (d.std(ddof=1) / math.sqrt(3.0))
    assert by_seed["unit"] == "seed" and by_seed["n_pairs"] == 3
    assert by_seed["mean_method"] == pytest.approx(1.3 / 3) and by_seed["mean_baseline"] == pytest.approx(0.6 / 3)
    assert by_seed["t"] == pytest.approx(t) and by_seed["p"] == pytest.approx(1.0 - t / math.sqrt(t * t + 2.0))
    # the same rows by episode: 4 pairs d = (1, 0, 0.3, -0.1)
    by_episode = statistics.paired_tests(main, "ours", metrics=["success_rate"]).iloc[0]
    assert by_episode["unit"] == "episode" and by_episode["n_pairs"] == 4 and by_episode["mean_diff"] == pytest.approx(1.2 / 4)
    both = statistics.paired_tests_all_units(main, "ours", alpha=0.01)
    assert list(both["unit"]) == ["episode"] * 3 + ["seed"] * 3 and (both["n_tests"] == 3).all()
    with pytest.raises(ValueError, match="bad unit 'run'; allowed: episode, seed"):
        statistics.paired_tests(main, "ours", unit="run")


def test_constant_nonzero_difference_is_infinitely_significant():
    rows = _episodes("ours", "s", {"success_rate": [0.5, 0.6, 0.7]}) + _episodes("base", "s", {"success_rate": [0.4, 0.5, 0.6]})
    for r in rows:
        r["scenario"] = "intersection"
    res = statistics.paired_tests(statistics.main_rows(pd.DataFrame(rows)), "ours", metrics=["success_rate"])
    assert res["t"].iloc[0] == math.inf and res["p"].iloc[0] == 0.0 and res["significant"].iloc[0]
    with pytest.raises(ValueError, match="bad alpha 1.5"):
        statistics.paired_tests(statistics.main_rows(pd.DataFrame(rows)), "ours", alpha=1.5)


def test_summary_pools_episodes_and_skips_undefined_travel_steps():
    rows = _episodes("ours", "intersection", {"success_rate": [0.5, 0.7, 0.9], "avg_travel_steps": [100.0, float("nan"), 200.0]})
    rows += _episodes("ours", "intersection", {"success_rate": [0.1]}, seed=1)
    rows += _episodes("ours", "intersection", {"success_rate": [0.3]}, count=8)  # another agent count: not in the table
    summary = statistics.summarize(statistics.main_rows(statistics.at_training_count(pd.DataFrame(rows)))).set_index("metric")
    assert summary.loc["success_rate", "n"] == 4
    assert summary.loc["success_rate", "mean"] == pytest.approx(0.55)
    assert summary.loc["success_rate", "std"] == pytest.approx(np.std([0.5, 0.7, 0.9, 0.1], ddof=1))
    assert summary.loc["avg_travel_steps", "n"] == 3  # NaN skipped; the seed-1 episode has 0.0
    assert summary.loc["avg_travel_steps", "mean"] == pytest.approx(100.0)


def test_main_and_ablation_rows_pick_variants():
    rows = _episodes("cig", "intersection", {"success_rate": [0.5]}, variant="full")
    rows += _episodes("cig", "intersection", {"success_rate": [0.4]}, variant="wo_gat")
    rows += _episodes("itd3", "intersection", {"success_rate": [0.2]})
    table = pd.DataFrame(rows)
    main = statistics.main_rows(table)
    assert sorted(zip(main["label"], main["variant"])) == [("cig", "full"), ("itd3", "default")]
    abl = statistics.ablation_rows(table, "cig")
    assert sorted(abl["label"]) == ["full", "wo_gat"]
    assert statistics.ablation_rows(table, "itd3").empty  # one variant only: no ablation table
    # a seeds sweep's default beside an ablation sweep's full: full stands for it; a scenario with one variant has no ablation
    rows += _episodes("cig", "intersection", {"success_rate": [0.6]}, variant="default")
    rows += _episodes("cig", "roundabout", {"success_rate": [0.3]}, variant="default")
    table = pd.DataFrame(rows)
    abl = statistics.ablation_rows(table, "cig")
    assert sorted(zip(abl["scenario"], abl["label"])) == [("intersection", "full"), ("intersection", "wo_gat")]
    main = statistics.main_rows(table)
    assert sorted(zip(main["scenario"], main["variant"])) == [
        ("intersection", "default"),
        ("intersection", "default"),
        ("roundabout", "default"),
    ]


def _known_summary():
    """A summary with known means: success (higher better), collision (lower better), a tie and a NaN."""
    data = [
        ("intersection", "A", "success_rate", 0.8878, 0.05),
        ("intersection", "B", "success_rate", 0.70, 0.04),
        ("intersection", "C", "success_rate", 0.75, 0.03),
        ("intersection", "A", "collision_rate", 0.0394, 0.01),
        ("intersection", "B", "collision_rate", 0.10, 0.02),
        ("intersection", "C", "collision_rate", 0.03941, 0.02),  # displays as 3.94 too: tied best with A
        ("intersection", "A", "avg_travel_steps", float("nan"), float("nan")),
        ("intersection", "B", "avg_travel_steps", 250.0, 10.0),
        ("intersection", "C", "avg_travel_steps", 300.0, 10.0),
    ]
    summary = pd.DataFrame(data, columns=["scenario", "label", "metric", "mean", "std"]).assign(n=10)
    return statistics.rank_marks(summary)


def test_best_bold_second_underlined_in_every_format(tmp_path):
    ranked = _known_summary().set_index(["label", "metric"])["rank"]
    assert ranked[("A", "success_rate")] == 1 and ranked[("C", "success_rate")] == 2 and ranked[("B", "success_rate")] == 0
    # lower is better; A and C tie at 3.94 % as displayed -> both bold, B (10 %) second
    assert ranked[("A", "collision_rate")] == 1 and ranked[("C", "collision_rate")] == 1 and ranked[("B", "collision_rate")] == 2
    # NaN never ranked; travel steps lower is better
    assert ranked[("A", "avg_travel_steps")] == 0 and ranked[("B", "avg_travel_steps")] == 1 and ranked[("C", "avg_travel_steps")] == 2

    md = tables.to_markdown(_known_summary(), "T").splitlines()
    row = {
        line.split("|")[1].strip(): [c.strip() for c in line.split("|")[2:-1]]
        for line in md
        if line.startswith("| ") and "Method" not in line
    }
    assert row["A"] == ["**88.78 (5.00)**", "**3.94 (1.00)**", "-"]
    assert row["B"] == ["70.00 (4.00)", "<u>10.00 (2.00)</u>", "**250.0 (10.0)**"]
    assert row["C"] == ["<u>75.00 (3.00)</u>", "**3.94 (2.00)**", "<u>300.0 (10.0)</u>"]
    tex = tables.to_latex(_known_summary(), "caption_with_underscore")
    assert "A & \\textbf{88.78 (5.00)} & \\textbf{3.94 (1.00)} & - \\\\" in tex
    assert "C & \\underline{75.00 (3.00)} & \\textbf{3.94 (2.00)} & \\underline{300.0 (10.0)} \\\\" in tex
    assert "Success (\\%)" in tex and "caption\\_with\\_underscore" in tex
    paths = tables.write_tables(_known_summary(), tmp_path, "table_main", "T")
    wide = pd.read_csv(paths[1]).set_index("method")
    assert wide.loc["C", "collision_rate_rank"] == 1 and wide.loc["C", "collision_rate_mean"] == pytest.approx(0.03941)
    html = tables.to_html(_known_summary())
    assert "<b>88.78 (5.00)</b>" in html and "<u>75.00 (3.00)</u>" in html


def test_marl_eval_layout():
    data = to_marl_eval(_table())
    runs = data["coin_app"]["intersection"]["base"]
    assert list(runs) == ["seed_0"]
    step = runs["seed_0"]["step_0"]
    assert step["step_count"] == 1000 and step["success_rate"] == [0.4, 0.5, 0.6, 0.9]  # sorted by test seed
    assert runs["seed_0"]["absolute_metrics"]["safety"] == [-3, -3, -3, 0]
    assert step["avg_travel_steps"] == [0.0, 0.0, 0.0, 0.0]  # the table's values, as given
    assert "avg_travel_steps_arrived" not in step  # undefined without arrivals: not written


def test_marl_eval_never_writes_undefined_travel_steps_as_zero():
    rows = _episodes("m", "intersection", {"success_rate": [0.5, float("nan")], "avg_travel_steps": [700.0, float("nan")]})
    rows += _episodes("m", "intersection", {"success_rate": [0.5, 0.25], "avg_travel_steps": [700.0, 400.0]}, seed=1)
    runs = to_marl_eval(pd.DataFrame(rows))["coin_app"]["intersection"]["m"]
    assert runs["seed_0"]["step_0"]["success_rate"] == [0.5, 0.0]  # an undefined rate is written as 0
    assert "avg_travel_steps" not in runs["seed_0"]["step_0"]  # 0 would be the best travel steps: left out instead
    assert runs["seed_1"]["absolute_metrics"]["avg_travel_steps"] == [700.0, 400.0]


def test_tsne_separates_clusters_and_is_deterministic():
    rng = np.random.default_rng(0)
    centers = rng.normal(0.0, 10.0, (3, 8))
    labels = np.repeat([0, 1, 2], 40)
    x = centers[labels] + rng.normal(0.0, 1.0, (120, 8))
    y = tsne(x, perplexity=15.0, iterations=400, seed=1)
    d = ((y[:, None] - y[None]) ** 2).sum(-1)
    np.fill_diagonal(d, np.inf)
    assert (labels[d.argmin(1)] == labels).all()  # every point's nearest embedded neighbour is in its cluster
    assert np.array_equal(y, tsne(x, perplexity=15.0, iterations=400, seed=1))
    found, centers = kmeans(x, 3, seed=0)
    assert all(len(set(found[labels == c])) == 1 for c in range(3)) and len(set(found)) == 3
    assert np.allclose(centers[found[::40]], [x[labels == c].mean(0) for c in range(3)])  # each center: its cluster's mean
    with pytest.raises(ValueError, match="bad perplexity 200"):
        tsne(x, perplexity=200)


def test_a_single_label_has_no_best_or_second():
    summary = pd.DataFrame(
        {"scenario": ["s", "s"], "label": ["only", "only"], "metric": ["success_rate", "out_of_road_rate"], "mean": [0.0, 0.97]}
    )
    summary["std"], summary["n"] = 0.0, 5
    assert list(statistics.rank_marks(summary)["rank"]) == [0, 0]
