"""Arena policies side by side: evaluate-arena with several policies, the side-by-side table, the page, and report on it."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from coin_app.cli import main
from coin_app.evaluation.arena_report import load_arena_eval, policy_label, policy_labels, side_by_side
from coin_app.evaluation.arena_suite import PAPER_TABLE_I, PAPER_TABLE_II


def test_labels_name_each_source_and_refuse_a_clash():
    assert [policy_label(s) for s in ("heuristic", "agnn", "docs/arena/pair.json", "runs/short/checkpoint/", "x/long.npz")] == [
        "heuristic",
        "agnn",
        "pair",
        "short",
        "long",
    ]
    with pytest.raises(ValueError, match=r"policies 'a/pair.json' and 'b/pair.json' would both be labelled 'pair'"):
        policy_labels(["a/pair.json", "heuristic", "b/pair.json"])


def test_side_by_side_keeps_each_policys_figures_and_refuses_other_cases():
    def summary(success: list[float], cases: list[tuple[int, int]]) -> pd.DataFrame:
        return pd.DataFrame(
            {
                "vehicles": [n for n, _ in cases],
                "obstacles": [m for _, m in cases],
                "scenarios": 3,
                "success_to_goal_rate": success,
                "collision_rate": [1e-3, 2e-3][: len(cases)],
                "step_time_s": [1e-4, 3e-4][: len(cases)],
                "paper_success": [0.9, 0.8][: len(cases)],
                "paper_agnn_success": np.nan,
                "agnn_supp_success": np.nan,
                "paper_collision_rate": np.nan,
                "paper_agnn_collision_rate": np.nan,
                "paper_step_time_s": 2e-4,
                "paper_agnn_step_time_s": np.nan,
            }
        )

    table = side_by_side({"a": summary([0.5, 0.25], [(1, 0), (2, 4)]), "b": summary([1.0, 0.0], [(1, 0), (2, 4)])})
    assert list(table["a success"]) == [0.5, 0.25] and list(table["b success"]) == [1.0, 0.0]
    assert list(table["a step ms"]) == pytest.approx([0.1, 0.3]) and list(table["paper step ms"]) == pytest.approx([0.2, 0.2])
    assert list(table["paper success"]) == [0.9, 0.8]
    with pytest.raises(ValueError, match="policy 'b' was evaluated on other cases than 'a'"):
        side_by_side({"a": summary([0.5, 0.25], [(1, 0), (2, 4)]), "b": summary([1.0, 0.0], [(1, 0), (4, 4)])})


def test_evaluate_arena_puts_policies_side_by_side_and_report_rebuilds_the_page(tmp_path, capsys):
    out = tmp_path / "eval"
    common = ["--cases", "1x0,2x0", "--scenarios-per-case", "2", "--workers", "1", "--plots", "1"]
    assert main(["evaluate-arena", "heuristic", "agnn", *common, "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    table = pd.read_csv(out / "arena_side_by_side.csv")
    for label in ("heuristic", "agnn"):  # each policy's columns are its own case table's figures
        own = pd.read_csv(out / label / "arena_cases.csv")
        assert list(table[f"{label} success"]) == list(own["success_to_goal_rate"])
        assert list(table[f"{label} step ms"]) == pytest.approx(list(own["step_time_s"] * 1e3))
        assert len(list((out / label / "plots").glob("*.png"))) == 2  # one per case
        assert len(list((out / label / "plots").glob("*.html"))) == 2  # and its replay page
    # a lone vehicle on an empty arena: the scripted driver parks it (the suite's documented 1x0 result)
    assert table.loc[0, "heuristic success"] == 1.0 and table.loc[0, "heuristic collisions/m"] == 0.0
    assert list(table["paper success"]) == [PAPER_TABLE_I[(1, 0)][0], PAPER_TABLE_I[(2, 0)][0]]
    assert list(table["paper A-GNN success"]) == [PAPER_TABLE_I[(1, 0)][1], PAPER_TABLE_I[(2, 0)][1]]
    assert table.loc[1, "paper step ms"] == pytest.approx(PAPER_TABLE_II[(2, 0)][0] * 1e3)
    assert table.loc[1, "paper A-GNN step ms"] == pytest.approx(PAPER_TABLE_II[(2, 0)][1] * 1e3)
    assert "| 1x0 | 1.000 | 0.00e+00 |" in (out / "arena_side_by_side.md").read_text() and "| 1x0 | 1.000 |" in printed
    settings = json.loads((out / "arena_eval.json").read_text())
    assert settings["labels"] == ["heuristic", "agnn"] and settings["protocol"] == "arena" and settings["cases"] == ["1x0", "2x0"]
    page = (out / "arena_report.html").read_text()
    assert page.count("<img") == 4 and "Trajectories: heuristic" in page and "Trajectories: agnn" in page
    # report takes the directory as a source and writes the same section (with a sweep source it adds its own report)
    assert main(["report", str(out), "--out", str(tmp_path / "report")]) == 0
    rebuilt = (tmp_path / "report" / "arena_report.html").read_text()
    assert rebuilt.count("<img") == 4 and "<td>1x0</td><td>1.000</td>" in rebuilt
    _, loaded, plots = load_arena_eval(out)
    assert loaded["folders"] == {"heuristic": "heuristic", "agnn": "agnn"} and [len(v) for v in plots.values()] == [2, 2]


def test_evaluate_arena_refuses_a_bad_policy_before_evaluating_any(tmp_path, capsys):
    out = tmp_path / "eval"
    args = ["evaluate-arena", "heuristic", str(tmp_path / "missing.npz"), "--cases", "1x0", "--scenarios-per-case", "1", "--out", str(out)]
    assert main(args) != 0
    assert "missing.npz" in capsys.readouterr().err and not out.exists()
    assert main(["evaluate-arena", "heuristic", "--cases", "1x0", "--scenarios-per-case", "0", "--out", str(out)]) != 0
    assert "bad --scenarios-per-case 0; allowed: an integer from 1 to 10000" in capsys.readouterr().err and not out.exists()


def test_evaluate_arena_tables_say_how_many_entities_a_policy_observed(tmp_path):
    common = ["--cases", "1x0", "--scenarios-per-case", "1", "--workers", "1"]
    assert main(["evaluate-arena", "heuristic", *common, "--observed-entities", "3", "--out", str(tmp_path / "k3")]) == 0
    assert main(["evaluate-arena", "heuristic", *common, "--out", str(tmp_path / "k1")]) == 0
    assert "observes its 3 closest entities" in (tmp_path / "k3" / "arena_table.md").read_text()
    assert "closest entities" not in (tmp_path / "k1" / "arena_table.md").read_text()  # the paper's observation: nothing to say
