"""Zero-shot generalization over agent counts: evaluate trained checkpoints at other initial agent counts.

Each checkpoint is loaded once (its deterministic actor) and evaluated on the fixed test seeds
at every count of the grid, its scenario otherwise unchanged. The result is a tidy table, one
row per (method, variant, seed, scenario, agent count, metric) with the mean over the test
episodes (``value``), their std and count; ``trained_agent_count`` marks the training count.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pandas as pd

REPORTED = ("success_rate", "collision_rate", "out_of_road_rate", "efficiency", "safety", "avg_travel_steps", "episode_return")
COLUMNS = ("method", "variant", "seed", "scenario", "agent_count", "trained_agent_count", "metric", "value", "std", "episodes")


def evaluate_at_counts(
    runs: Sequence[dict[str, Any]],
    counts: Sequence[int],
    test_seeds: int,
    log: Callable[[str], None] = print,
) -> pd.DataFrame:
    """Tidy metrics of every run (``method``, ``variant``, ``seed``, ``checkpoint``) at every agent count in ``counts``."""
    from coin_app.algorithms.checkpoints import load_policy, scenario_of
    from coin_app.evaluation.evaluate import eval_test_seeds, evaluate_policy
    from coin_app.evaluation.metrics import aggregate

    bad = [c for c in counts if not (isinstance(c, int) and c >= 1)]
    if bad or not counts:
        raise ValueError(f"bad agent counts {list(counts)}; allowed: one or more integers >= 1")
    if test_seeds < 1:
        raise ValueError(f"bad test_seeds {test_seeds}; allowed: an integer >= 1")
    seeds = eval_test_seeds(test_seeds)
    rows = []
    for i, run in enumerate(runs, 1):
        checkpoint = Path(run["checkpoint"])
        policy = load_policy(checkpoint)
        trained = scenario_of(checkpoint)
        for count in counts:
            config = scenario_of(checkpoint, num_agents=int(count))
            agg = aggregate(evaluate_policy(policy, config, seeds))
            for metric in REPORTED:
                rows.append(
                    {
                        "method": run["method"],
                        "variant": run.get("variant", "default"),
                        "seed": int(run["seed"]),
                        "scenario": config.scenario,
                        "agent_count": int(count),
                        "trained_agent_count": trained.num_agents,
                        "metric": metric,
                        "value": agg[metric]["mean"],
                        "std": agg[metric]["std"],
                        "episodes": len(seeds),
                    }
                )
            label = f"{run['method']} {run.get('variant', 'default')} seed {run['seed']}"
            log(f"  [{i}/{len(runs)}] {label} at {count} agents: success {agg['success_rate']['mean']:.3f}")
    return pd.DataFrame(rows, columns=list(COLUMNS))
