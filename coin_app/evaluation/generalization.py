"""Zero-shot generalization over agent counts: evaluate trained checkpoints at other initial agent counts.

A thin summary over :func:`~coin_app.evaluation.protocol.run_evaluation`: each checkpoint is
evaluated on the fixed test seeds at every count of the grid, its scenario otherwise
unchanged, and the per-episode rows are reduced to one row per (method, variant, seed,
scenario, agent count, metric) with the mean over the test episodes (``value``), their
population std and count; ``trained_agent_count`` marks the training count.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import pandas as pd

from coin_app.evaluation.metrics import METRIC_KEYS
from coin_app.evaluation.protocol import EvalRun, check_grid, run_evaluation
from coin_app.sim.seeds import eval_test_seeds

REPORTED = (*METRIC_KEYS, "episode_return")
COLUMNS = ("method", "variant", "seed", "scenario", "agent_count", "trained_agent_count", "metric", "value", "std", "episodes")


def evaluate_at_counts(
    runs: Sequence[dict[str, Any]],
    counts: Sequence[int],
    test_seeds: int,
    log: Callable[[str], None] = print,
) -> pd.DataFrame:
    """Tidy metrics of every run (``method``, ``variant``, ``seed``, ``checkpoint``) at every agent count in ``counts``."""

    check_grid([0], list(counts), None)
    if test_seeds < 1:
        raise ValueError(f"bad test_seeds {test_seeds}; allowed: an integer >= 1")
    evaluation = run_evaluation(
        [EvalRun(r["method"], r.get("variant", "default"), int(r["seed"]), str(r["checkpoint"])) for r in runs],
        eval_test_seeds(test_seeds),
        counts=list(counts),
        log=log,
    )
    if evaluation.failures:
        first = evaluation.failures[0]
        raise ValueError(f"could not evaluate {first['checkpoint']}: {first['error']}")
    episodes = evaluation.table[evaluation.table["agent_count"].isin(list(counts))]
    rows = []
    keys = ["method", "variant", "trained_seed", "scenario", "agent_count", "trained_agent_count"]
    for key, g in episodes.groupby(keys, sort=False):
        for metric in REPORTED:
            v = g[metric].dropna()
            rows.append(dict(zip(COLUMNS, key)) | {"metric": metric, "value": v.mean(), "std": v.std(ddof=0), "episodes": len(g)})
    return pd.DataFrame(rows, columns=list(COLUMNS))
