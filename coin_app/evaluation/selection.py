"""Validation-seed checkpoint selection: which of a trial's checkpoints the report scores on the test seeds.

COIN's released code keeps, per run, the model best by training success ("best_model"). The
protocol here never selects on the test seeds: with ``select="validation"`` every kept
checkpoint of a trial is run with its deterministic actor on the validation seeds
(:func:`~coin_app.sim.seeds.validation_seeds`, disjoint from the training and test seeds), and
the checkpoint with the highest mean success rate over those episodes is the trial's model;
a tie goes to the later checkpoint (more training). ``select="final"`` keeps the newest
checkpoint (the default protocol). The per-checkpoint validation table is written beside the
report (``selection.csv``) so the choice can be checked.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import pandas as pd

from coin_app.evaluation.protocol import EvalRun, run_evaluation
from coin_app.sim.seeds import validation_seeds

SELECTIONS = ("final", "validation")
SELECTION_COLUMNS = ("method", "variant", "trained_seed", "checkpoint", "order", "trained_env_steps", "validation_success", "selected")


@dataclass(frozen=True)
class Candidates:
    """One trial's model (its final checkpoint) and every checkpoint kept for it, oldest first."""

    run: EvalRun
    checkpoints: tuple[str, ...]


def best_index(successes: Sequence[float]) -> int:
    """Index of the highest success rate; a tie goes to the later entry (NaN never wins unless all are NaN)."""
    if not successes:
        raise ValueError("no checkpoints to select from; allowed: one or more")
    best = len(successes) - 1
    for i, s in enumerate(successes):
        if s == s and (successes[best] != successes[best] or s >= successes[best]):  # s == s: not NaN
            best = i
    return best


def select_checkpoints(
    trials: Sequence[Candidates], episodes: int, workers: int = 1, log: Callable[[str], None] = print
) -> tuple[list[EvalRun], pd.DataFrame, list[dict]]:
    """Per trial the checkpoint best on ``episodes`` validation seeds; the per-checkpoint table; the failures."""
    if episodes < 1:
        raise ValueError(f"bad validation episodes {episodes}; allowed: an integer >= 1")
    candidates = [replace(t.run, checkpoint=c, trained_env_steps=None) for t in trials for c in t.checkpoints]
    log(f"validation-seed selection: {len(candidates)} checkpoints of {len(trials)} trials, {episodes} validation seeds each")
    evaluation = run_evaluation(candidates, validation_seeds(episodes), workers=workers, log=log)
    means = evaluation.table.groupby("checkpoint", sort=False).agg(
        validation_success=("success_rate", "mean"), trained_env_steps=("trained_env_steps", "first")
    )
    selected, rows = [], []
    for trial in trials:
        scores = [float(means["validation_success"].get(c, float("nan"))) for c in trial.checkpoints]
        if all(s != s for s in scores):  # no checkpoint could be evaluated: the trial is left out (its failures are listed)
            continue
        best = best_index(scores)
        chosen = trial.checkpoints[best]
        steps = means["trained_env_steps"].get(chosen)
        selected.append(replace(trial.run, checkpoint=chosen, trained_env_steps=None if pd.isna(steps) else int(steps)))
        for i, (c, s) in enumerate(zip(trial.checkpoints, scores)):
            env_steps = means["trained_env_steps"].get(c)
            rows.append(
                {
                    "method": trial.run.method,
                    "variant": trial.run.variant,
                    "trained_seed": trial.run.trained_seed,
                    "checkpoint": c,
                    "order": i,
                    "trained_env_steps": None if env_steps is None or pd.isna(env_steps) else int(env_steps),
                    "validation_success": s,
                    "selected": i == best,
                }
            )
        log(f"  {trial.run.label}: checkpoint {best + 1} of {len(scores)} ({Path(chosen).name}), validation success {scores[best]:.3f}")
    return selected, pd.DataFrame(rows, columns=list(SELECTION_COLUMNS)), evaluation.failures
