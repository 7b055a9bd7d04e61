"""Results in marl-eval's raw-data JSON layout (https://github.com/instadeepai/marl-eval).

``{environment: {task: {algorithm: {run: {"step_0": {"step_count": int, metric: [per episode]},
"absolute_metrics": {metric: [per episode]}}}}}}`` with environment ``coin_app``, task
``<scenario>`` at the training agent count and ``<scenario>_<n>agents`` at other counts,
algorithm ``<method>[-<variant>]``, run ``seed_<trained seed>``. Only the final checkpoint is
evaluated, so there is one step, counted in trained env steps. Metrics that can be undefined
in an episode (``avg_travel_steps``) are left out: marl-eval needs a number per episode; a
rate of an episode without vehicles (undefined, NaN) is written as 0.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pandas as pd

from coin_app.evaluation.metrics import METRIC_KEYS

# every COIN metric but avg_travel_steps (undefined in an episode without arrivals), and the return
MARL_EVAL_METRICS = (*(k for k in METRIC_KEYS if k != "avg_travel_steps"), "episode_return")
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
