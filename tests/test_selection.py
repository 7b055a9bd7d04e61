"""Validation-seed selection's rule: the highest validation success wins, a tie goes to the later checkpoint."""

import json
import math

import pandas as pd
import pytest

from coin_app.algorithms.checkpoint_files import META_FILE
from coin_app.evaluation import selection
from coin_app.evaluation.protocol import EvalRun, Evaluation
from coin_app.evaluation.selection import Candidates, best_index, select_checkpoints
from coin_app.evaluation.sweep_results import TrialRecord


@pytest.mark.parametrize(
    ("successes", "expected"),
    [
        ([0.2, 0.5, 0.5, 0.1], 2),  # the later of two equal bests
        ([0.9, 0.5, 0.7], 0),  # an early best is kept
        ([0.0, 0.0, 0.0], 2),  # all equal: the final checkpoint
        ([math.nan, 0.3, math.nan], 1),  # a checkpoint that could not be evaluated never wins
        ([math.nan, math.nan], 1),
        ([0.4], 0),
    ],
)
def test_best_index_takes_the_highest_success_and_the_later_of_ties(successes, expected):
    assert best_index(successes) == expected


def test_bad_selection_input_is_refused_by_name():
    with pytest.raises(ValueError, match="no checkpoints to select from"):
        best_index([])
    with pytest.raises(ValueError, match="bad validation episodes 0; allowed: an integer >= 1"):
        select_checkpoints([], 0)
    with pytest.raises(ValueError, match="1 env-step counts for 2 checkpoints; allowed: one per checkpoint"):
        Candidates(EvalRun("m", "default", 0, "a1", 10), ("a0", "a1"), (10,))


def test_select_checkpoints_picks_per_trial_skips_failures_and_carries_env_steps(monkeypatch):
    """``run_evaluation`` replaced by crafted validation episodes: the choice, failures and env steps by hand."""
    episodes = {  # checkpoint -> validation success of each episode
        "a0": [0.2, 0.4],
        "a1": [0.8, 0.6],  # the best of trial a, not its final one
        "a2": [0.5, 0.5],
        "b1": [0.1, 0.1],  # b0 cannot be loaded
        "d0": [0.1 + 0.2, 0.3],  # mean 0.30000000000000004: one ulp above d1, a tie all the same
        "d1": [0.3, 0.3],
    }
    seen = []

    def fake(runs, seeds, workers=1, log=print, cache=None):
        seen.append((len(runs), list(seeds)))
        rows = [{"checkpoint": r.checkpoint, "success_rate": s} for r in runs if r.checkpoint in episodes for s in episodes[r.checkpoint]]
        failed = [{"checkpoint": r.checkpoint, "error": "cannot load"} for r in runs if r.checkpoint not in episodes]
        return Evaluation(pd.DataFrame(rows), failed)

    monkeypatch.setattr(selection, "run_evaluation", fake)
    trials = [
        selection.Candidates(EvalRun("m", "default", 0, "a2", 3000), ("a0", "a1", "a2"), (1000, 2000, 3000)),
        selection.Candidates(EvalRun("m", "default", 1, "b1", 500), ("b0", "b1"), (None, 500)),  # b0: unreadable metadata
        selection.Candidates(EvalRun("m", "default", 2, "c1", 900), ("c0", "c1"), (400, 900)),  # nothing loads: left out
        selection.Candidates(EvalRun("m", "default", 3, "d1", 200), ("d0", "d1"), (100, 200)),
    ]
    chosen, table, failures = selection.select_checkpoints(trials, 2, log=lambda _: None)
    assert seen == [(9, selection.validation_seeds(2))]  # every kept checkpoint once, on the validation seeds
    assert [(r.trained_seed, r.checkpoint, r.trained_env_steps) for r in chosen] == [(0, "a1", 2000), (1, "b1", 500), (3, "d1", 200)]
    assert sorted(f["checkpoint"] for f in failures) == ["b0", "c0", "c1"]
    by = table.set_index("checkpoint")
    assert list(by.index) == ["a0", "a1", "a2", "b0", "b1", "d0", "d1"]  # the failed trial has no rows
    assert by.loc["a1", "validation_success"] == pytest.approx(0.7) and by.loc["a2", "trained_env_steps"] == 3000
    assert math.isnan(by.loc["b0", "validation_success"]) and pd.isna(by.loc["b0", "trained_env_steps"])
    assert str(table["trained_env_steps"].dtype) == "Int64"  # whole numbers even with an empty cell
    assert by["selected"].sum() == 3 and bool(by.loc["d1", "selected"])


def test_checkpoint_env_steps_come_from_metadata_with_the_trials_count_for_an_old_final_one(tmp_path):
    """A trial's checkpoints: one with recorded env steps, one unreadable, a final one saved before steps were recorded."""
    dirs = [tmp_path / f"checkpoint_00000{i}" for i in range(3)]
    for d in dirs:
        d.mkdir()
    (dirs[0] / META_FILE).write_text(json.dumps({"env_steps": 500}))
    (dirs[1] / META_FILE).write_text("{not json")
    (dirs[2] / META_FILE).write_text(json.dumps({"seed": 0}))
    trial = TrialRecord(tmp_path, {"algo": "m", "variant": "default", "seed": 0}, [{"env_steps": 500}, {"env_steps": 1500}], dirs)
    assert [trial.checkpoint_env_steps(d) for d in dirs] == [500, None, 1500]
