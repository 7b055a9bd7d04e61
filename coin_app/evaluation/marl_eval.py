"""Results in marl-eval's raw-data JSON layout (https://github.com/instadeepai/marl-eval).

``{environment: {task: {algorithm: {run: {"step_0": {"step_count": int, metric: [per episode]},
"absolute_metrics": {metric: [per episode]}}}}}}`` with environment ``coin_app``, task
``<scenario>`` at the training agent count and ``<scenario>_<n>agents`` at other counts,
algorithm ``<method>[-<variant>]``, run ``seed_<trained seed>``. Only the final checkpoint is
evaluated, so there is one step, counted in trained env steps. The metrics are the six of
Table 5.1 and the return. ``avg_travel_steps`` (the paper's: a non-arrival counts as the
horizon) is defined in every episode with a finished vehicle, i.e. every complete one; it is
lower-is-better, where marl-eval's aggregate plots assume higher is better (negate it, or leave
it out of the metrics given to them). A run with an episode that has no travel steps (no
finished vehicle) leaves ``avg_travel_steps`` out rather than invent a figure; the
arrivals-only ``avg_travel_steps_arrived`` (undefined without arrivals) is not written. A rate
of an episode without vehicles (undefined, NaN) is written as 0.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pandas as pd

from coin_app.evaluation.metrics import METRIC_KEYS

MARL_EVAL_METRICS = (*METRIC_KEYS, "episode_return")  # the six COIN metrics and the return
NO_ZERO_FILL = ("avg_travel_steps",)  # undefined is not 0 (the best value): such a run leaves the metric out
ENVIRONMENT = "coin_app"


def run_label(method: str, variant: str) -> str:
    """``<method>`` for the default variant, else ``<method>-<variant>``."""
    return method if variant == "default" else f"{method}-{variant}"


def to_marl_eval(table: pd.DataFrame) -> dict[str, Any]:
    """The per-episode results table as a marl-eval raw-data dict."""
    data: dict[str, Any] = {ENVIRONMENT: {}}
    keys = ["scenario", "agent_count", "trained_agent_count", "method", "variant", "trained_seed"]
    for (scenario, count, trained, method, variant, seed), g in table.groupby(keys, sort=True):
        task = scenario if count == trained else f"{scenario}_{count}agents"
        g = g.sort_values("test_seed")
        metrics = {m: [float(v) for v in g[m]] for m in MARL_EVAL_METRICS if m in g}
        metrics = {m: values for m, values in metrics.items() if m not in NO_ZERO_FILL or not any(map(math.isnan, values))}
        if any(math.isnan(v) for values in metrics.values() for v in values):
            metrics = {m: [0.0 if math.isnan(v) else v for v in values] for m, values in metrics.items()}
        steps = g["trained_env_steps"].iloc[0] if "trained_env_steps" in g else None
        step_count = int(steps) if steps is not None and not pd.isna(steps) else 0
        algo = data[ENVIRONMENT].setdefault(task, {}).setdefault(run_label(method, variant), {})
        algo[f"seed_{int(seed)}"] = {"step_0": {"step_count": step_count, **metrics}, "absolute_metrics": metrics}
    return data


def write_marl_eval(table: pd.DataFrame, path: Path) -> Path:
    """Write :func:`to_marl_eval` of ``table`` as JSON."""
    path = Path(path)
    path.write_text(json.dumps(to_marl_eval(table), indent=1))
    return path
