"""Statistics of a results table: mean (std) per method, best/second marks, paired t-tests with Bonferroni.

Input is the per-episode table of :mod:`coin_app.evaluation.protocol`. Conventions (the COIN
paper's Table 5.1 and Section 5.2; ``docs/decisions.md`` §5.2):

* A method's figure pools every episode of every trained seed at the training agent count
  (8 seeds x 20 test seeds = 160 episodes in the paper): the mean and the sample std
  (``ddof=1``) over those episodes. ``avg_travel_steps`` is the paper's (a vehicle that did not
  arrive counts as the horizon; :mod:`coin_app.evaluation.metrics`), lower is better; undefined
  only in an episode without a finished vehicle, its mean is over the episodes that have one
  (``n`` counts them).
* Best and second best per (scenario, metric) are ranked on the value as displayed (rounded),
  in the metric's direction (:data:`METRICS`); ties share the mark, as a table reader sees them.
* Paired t-tests (``scipy.stats.ttest_rel``, two-sided) compare the chosen method with each
  baseline on success, safety and efficiency per scenario. Episodes are paired on
  (trained seed, test seed): the same test traffic and the same position in the seed list.
  The Bonferroni-corrected threshold is ``alpha / number of tests`` (the paper: 0.01 / 18).
* The same tests with the trained seed as the unit (``unit="seed"``): each seed's mean over the
  paired episodes, paired on the trained seed (5 pairs for 5 seeds). Test episodes of one
  trained model are not independent draws of the training run, so this is the stricter test of
  whether a method, not one set of models, is better; its Bonferroni family is its own tests.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd
from scipy import stats


@dataclass(frozen=True)
class MetricSpec:
    """How a metric is shown and ranked."""

    key: str
    label: str
    higher_is_better: bool
    scale: float = 1.0  # display multiplier (rates in %)
    decimals: int = 2


METRICS = (
    MetricSpec("success_rate", "Success (%)", True, 100.0),
    MetricSpec("out_of_road_rate", "Off-road (%)", False, 100.0),
    MetricSpec("collision_rate", "Collision (%)", False, 100.0),
    MetricSpec("efficiency", "Efficiency", True),
    MetricSpec("safety", "Safety", True),
    MetricSpec("avg_travel_steps", "Travel steps", False, 1.0, 1),
)
METRIC_BY_KEY = {m.key: m for m in METRICS}
TESTED_METRICS = ("success_rate", "safety", "efficiency")
TEST_UNITS = ("episode", "seed")  # what one pair of a paired t-test is: a (trained seed, test seed) episode, or a trained seed
MAIN_VARIANTS = ("default", "full")  # the variant that stands for a method in the main table, in order of preference


def at_training_count(table: pd.DataFrame) -> pd.DataFrame:
    """The episodes run at each model's training agent count (the tables' and tests' population)."""
    return table[table["agent_count"] == table["trained_agent_count"]]


def main_rows(table: pd.DataFrame) -> pd.DataFrame:
    """One variant per (scenario, method): ``default`` if present, else ``full``; column ``label`` = method."""
    parts = []
    for (_, method), rows in table.groupby(["scenario", "method"], sort=False):
        for variant in MAIN_VARIANTS:
            pick = rows[rows["variant"] == variant]
            if len(pick):
                parts.append(pick.assign(label=method))
                break
    return pd.concat(parts, ignore_index=True) if parts else table.iloc[:0].assign(label=pd.Series(dtype=str))


def ablation_rows(table: pd.DataFrame, method: str) -> pd.DataFrame:
    """The variants of ``method`` per scenario with two or more of them; column ``label`` = variant.

    Where an ablation sweep's ``full`` is present, ``default`` (the same configuration from a
    seeds sweep) is left out so the table compares the ablation sweep's own models.
    """
    parts = []
    for _, rows in table[table["method"] == method].groupby("scenario", sort=False):
        if "full" in set(rows["variant"]):
            rows = rows[rows["variant"] != "default"]
        if rows["variant"].nunique() >= 2:
            parts.append(rows.assign(label=rows["variant"]))
    return pd.concat(parts, ignore_index=True) if parts else table.iloc[:0].assign(label=pd.Series(dtype=str))


def summarize(rows: pd.DataFrame, metrics: Sequence[str] = tuple(METRIC_BY_KEY)) -> pd.DataFrame:
    """Long table (scenario, label, metric, mean, std, n) over episodes; labels in order of appearance."""
    out = []
    for (scenario, label), g in rows.groupby(["scenario", "label"], sort=False):
        for metric in metrics:
            v = g[metric].to_numpy(dtype=float)
            v = v[~np.isnan(v)]
            out.append(
                {
                    "scenario": scenario,
                    "label": label,
                    "metric": metric,
                    "mean": float(v.mean()) if len(v) else float("nan"),
                    "std": float(v.std(ddof=1)) if len(v) > 1 else float("nan"),
                    "n": len(v),
                }
            )
    return pd.DataFrame(out, columns=["scenario", "label", "metric", "mean", "std", "n"])


def displayed(metric: str, value: float) -> float:
    """``value`` as a table shows it: scaled and rounded."""
    spec = METRIC_BY_KEY[metric]
    return round(value * spec.scale, spec.decimals)


def rank_marks(summary: pd.DataFrame) -> pd.DataFrame:
    """``summary`` with column ``rank``: 1 for the best displayed mean per (scenario, metric), 2 for the second, else 0.

    A (scenario, metric) with a single label has no ranks: nothing is "best" without a comparison.
    """
    ranks = np.zeros(len(summary), dtype=int)
    for _, g in summary.groupby(["scenario", "metric"], sort=False):
        if g["label"].nunique() < 2:
            continue
        spec = METRIC_BY_KEY[g["metric"].iloc[0]]
        shown = np.array([displayed(spec.key, v) if not np.isnan(v) else np.nan for v in g["mean"]])
        distinct = sorted({v for v in shown if not np.isnan(v)}, reverse=spec.higher_is_better)
        for pos, value in zip(g.index, shown):
            if not np.isnan(value) and value in distinct[:2]:
                ranks[summary.index.get_loc(pos)] = distinct.index(value) + 1
    return summary.assign(rank=ranks)


def _paired_t(a: np.ndarray, b: np.ndarray, stats: object) -> tuple[float, float]:
    """(t, two-sided p) of a paired t-test; see :func:`paired_tests` for the degenerate cases."""
    d = a - b
    if len(d) < 2 or not np.any(d):
        return float("nan"), float("nan")
    if np.ptp(d) == 0:  # the same nonzero difference in every pair: t is infinite
        return float(np.sign(d[0]) * np.inf), 0.0
    res = stats.ttest_rel(a, b)
    return float(res.statistic), float(res.pvalue)


def paired_tests(
    rows: pd.DataFrame,
    method: str,
    metrics: Sequence[str] = TESTED_METRICS,
    alpha: float = 0.01,
    unit: str = "episode",
) -> pd.DataFrame:
    """Paired two-sided t-tests of ``method`` against every other label per scenario and metric, Bonferroni-corrected.

    ``unit`` is what one pair is (:data:`TEST_UNITS`): an episode paired on (trained seed, test
    seed), the paper's; or a trained seed, each side's mean over the paired episodes of that seed.
    Degenerate cases: fewer than two pairs or all differences zero give t = p = NaN (never
    significant); the same nonzero difference in every pair gives t = +-inf and p = 0.
    """

    if not 0.0 < alpha < 1.0:
        raise ValueError(f"bad alpha {alpha}; allowed: a number in (0, 1)")
    if unit not in TEST_UNITS:
        raise ValueError(f"bad unit {unit!r}; allowed: {', '.join(TEST_UNITS)}")
    tests = []
    for scenario, g in rows.groupby("scenario", sort=False):
        ours = g[g["label"] == method].set_index(["trained_seed", "test_seed"])
        if ours.empty:
            continue
        for baseline in [b for b in g["label"].unique() if b != method]:
            theirs = g[g["label"] == baseline].set_index(["trained_seed", "test_seed"])
            both = ours.index.intersection(theirs.index)
            for metric in metrics:
                a = ours.loc[both, metric].to_numpy(dtype=float)
                b = theirs.loc[both, metric].to_numpy(dtype=float)
                keep = ~(np.isnan(a) | np.isnan(b))
                a, b = a[keep], b[keep]
                if unit == "seed":
                    seeds = both.get_level_values("trained_seed").to_numpy()[keep]
                    a, b = (pd.Series(v).groupby(seeds).mean().to_numpy() for v in (a, b))
                d = a - b
                t, p = _paired_t(a, b, stats)
                tests.append(
                    {
                        "scenario": scenario,
                        "metric": metric,
                        "method": method,
                        "baseline": baseline,
                        "unit": unit,
                        "n_pairs": len(d),
                        "mean_method": float(a.mean()) if len(a) else float("nan"),
                        "mean_baseline": float(b.mean()) if len(b) else float("nan"),
                        "mean_diff": float(d.mean()) if len(d) else float("nan"),
                        "t": t,
                        "p": p,
                    }
                )
    columns = ["scenario", "metric", "method", "baseline", "unit", "n_pairs", "mean_method", "mean_baseline", "mean_diff", "t", "p"]
    out = pd.DataFrame(tests, columns=columns)
    n = len(out)
    threshold = alpha / n if n else float("nan")
    return out.assign(alpha=alpha, n_tests=n, threshold=threshold, significant=out["p"] < threshold)


def paired_tests_all_units(rows: pd.DataFrame, method: str, alpha: float = 0.01) -> pd.DataFrame:
    """:func:`paired_tests` at every unit of :data:`TEST_UNITS`, one table; each unit is its own Bonferroni family."""
    return pd.concat([paired_tests(rows, method, alpha=alpha, unit=unit) for unit in TEST_UNITS], ignore_index=True)
