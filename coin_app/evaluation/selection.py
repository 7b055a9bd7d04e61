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

from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.evaluation.protocol import EvalRun, run_evaluation
from coin_app.evaluation.sweep_results import TrialRecord
from coin_app.sim.seeds import validation_seeds

FINAL, VALIDATION = "final", "validation"
SELECTIONS = (FINAL, VALIDATION)
SELECTION_FILE = "selection.csv"  # the per-checkpoint validation table, written beside the report
SELECTION_COLUMNS = ("method", "variant", "trained_seed", "checkpoint", "order", "trained_env_steps", "validation_success", "selected")
TIE_DECIMALS = 9  # validation means equal to this many decimals are a tie (means over different episodes can differ by an ulp)


@dataclass(frozen=True)
class Candidates:
    """One trial's model (its final checkpoint) and every checkpoint kept for it, oldest first, with the env steps each was saved at."""

    run: EvalRun
    checkpoints: tuple[str, ...]
    env_steps: tuple[int | None, ...]  # per checkpoint (``TrialRecord.checkpoint_env_steps``); None where unknown

    def __post_init__(self) -> None:
        """Refuse env steps that do not match the checkpoints one to one."""
        if len(self.env_steps) != len(self.checkpoints):
            raise ValueError(f"{len(self.env_steps)} env-step counts for {len(self.checkpoints)} checkpoints; allowed: one per checkpoint")


def trial_candidates(trial: TrialRecord) -> Candidates:
    """A sweep trial's model (its final checkpoint, which it must have) and every checkpoint it kept, with their env steps."""
    cfg, final = trial.config, trial.final_checkpoint
    assert final is not None  # callers pass trials with a checkpoint
    run = EvalRun(cfg["algo"], cfg["variant"], int(cfg["seed"]), str(final), trial.checkpoint_env_steps(final))
    return Candidates(run, tuple(str(c) for c in trial.checkpoints), tuple(trial.checkpoint_env_steps(c) for c in trial.checkpoints))


def best_index(successes: Sequence[float]) -> int:
    """Index of the highest success rate; a tie goes to the later entry (NaN never wins unless all are NaN)."""
    if not successes:
        raise ValueError("no checkpoints to select from; allowed: one or more")
    best = len(successes) - 1
    for i, s in enumerate(successes):
        if s == s and (successes[best] != successes[best] or s >= successes[best]):  # s == s: not NaN
            best = i
    return best


def selection_caption(select: str, validation_episodes: int | None) -> str:
    """How the models of a table were chosen, for its caption."""
    if select == VALIDATION:
        return f"checkpoints selected on {validation_episodes} validation seeds"
    return "final checkpoints" if select == FINAL else f"checkpoints chosen by {select}"


def select_checkpoints(
    trials: Sequence[Candidates],
    episodes: int,
    workers: int = 1,
    log: Callable[[str], None] = print,
    cache: EpisodeCache | None = None,
) -> tuple[list[EvalRun], pd.DataFrame, list[dict]]:
    """Per trial the checkpoint best on ``episodes`` validation seeds; the per-checkpoint table; the failures.

    A checkpoint that cannot be evaluated never wins (it is among the failures); a trial none of
    whose checkpoints can be evaluated is left out. Each checkpoint's trained env steps are the
    trial's (``Candidates.env_steps``). ``cache``: as :func:`~coin_app.evaluation.protocol.run_evaluation`'s.
    """
    if episodes < 1:
        raise ValueError(f"bad validation episodes {episodes}; allowed: an integer >= 1")
    candidates = [replace(t.run, checkpoint=c, trained_env_steps=n) for t in trials for c, n in zip(t.checkpoints, t.env_steps)]
    log(f"validation-seed selection: {len(candidates)} checkpoints of {len(trials)} trials, {episodes} validation seeds each")
    evaluation = run_evaluation(candidates, validation_seeds(episodes), workers=workers, log=log, cache=cache)
    means = evaluation.table.groupby("checkpoint", sort=False)["success_rate"].mean()
    selected, rows = [], []
    for trial in trials:
        scores = [round(float(means.get(c, float("nan"))), TIE_DECIMALS) for c in trial.checkpoints]
        if all(s != s for s in scores):  # no checkpoint could be evaluated: the trial is left out (its failures are listed)
            continue
        best = best_index(scores)
        steps = trial.env_steps
        chosen = trial.checkpoints[best]
        selected.append(replace(trial.run, checkpoint=chosen, trained_env_steps=steps[best]))
        for i, (c, s) in enumerate(zip(trial.checkpoints, scores)):
            row = {"method": trial.run.method, "variant": trial.run.variant, "trained_seed": trial.run.trained_seed, "checkpoint": c}
            rows.append(row | {"order": i, "trained_env_steps": steps[i], "validation_success": s, "selected": i == best})
        log(f"  {trial.run.label}: checkpoint {best + 1} of {len(scores)} ({Path(chosen).name}), validation success {scores[best]:.3f}")
    table = pd.DataFrame(rows, columns=list(SELECTION_COLUMNS))
    return selected, table.astype({"trained_env_steps": "Int64"}), evaluation.failures
