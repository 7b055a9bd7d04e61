"""The native -> other-backend gap: the same models on the same test seeds, on the native simulator and on MetaDrive.

A policy trained on the native simulator is meant to drive MetaDrive's car as well (the
simulator-fidelity issue: MetaDrive's vehicle, maps and rules). :func:`transfer_table` pairs
each model's transfer episodes with its native episodes on the same test seeds at the training
agent count and reports, per (scenario, method) and metric of the main table, the native mean,
the other backend's mean and the gap (other - native) over those paired episodes. The native
table may hold more test seeds than the transfer evaluation (MetaDrive runs at about 2,000
agent-steps/s per core): only the shared ones enter.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import pandas as pd

from coin_app.evaluation.statistics import METRIC_BY_KEY, displayed, main_rows

PAIR_KEYS = ("checkpoint", "scenario", "agent_count", "test_seed")
COLUMNS = ("scenario", "label", "metric", "native", "transfer", "gap", "n")


def transfer_table(native: pd.DataFrame, other: pd.DataFrame, metrics: Sequence[str] = tuple(METRIC_BY_KEY)) -> pd.DataFrame:
    """Long table (scenario, label, metric, native, transfer, gap, n) over episodes present in both tables."""
    keep = list(PAIR_KEYS)
    both = main_rows(native[native["agent_count"] == native["trained_agent_count"]]).merge(
        other[[*keep, *metrics]], on=keep, suffixes=("", "_transfer")
    )
    out = []
    for (scenario, label), g in both.groupby(["scenario", "label"], sort=False):
        for metric in metrics:
            pair = g[[metric, f"{metric}_transfer"]].dropna()  # travel steps: undefined where no vehicle arrived
            a, b = pair[metric].mean(), pair[f"{metric}_transfer"].mean()
            row = {"scenario": scenario, "label": label, "metric": metric, "native": a, "transfer": b, "gap": b - a}
            out.append(row | {"n": len(pair)})
    return pd.DataFrame(out, columns=list(COLUMNS))


def to_markdown(table: pd.DataFrame, backend: str) -> str:
    """Per scenario: one row per method, ``native / backend (gap)`` per metric, as the main table displays values."""
    lines = []
    for scenario, g in table.groupby("scenario", sort=False):
        metrics = list(dict.fromkeys(g["metric"]))
        lines += [
            f"### {scenario}: native / {backend} (gap) on the same test episodes",
            "",
            "| Method | episodes | " + " | ".join(METRIC_BY_KEY[m].label for m in metrics) + " |",
            "|---|---:|" + "---:|" * len(metrics),
        ]
        for label, rows in g.groupby("label", sort=False):
            by = rows.set_index("metric")
            cells = [
                f"{displayed(m, by.at[m, 'native']):g} / {displayed(m, by.at[m, 'transfer']):g} ({displayed(m, by.at[m, 'gap']) + 0.0:+g})"
                if by.at[m, "n"]
                else "-"
                for m in metrics
            ]
            lines.append(f"| {label} | {int(by['n'].max())} | " + " | ".join(cells) + " |")
        lines.append("")
    return "\n".join(lines)


def write_transfer(table: pd.DataFrame, out_dir: Path, backend: str) -> list[Path]:
    """Write ``table_transfer.csv`` and ``table_transfer.md`` into ``out_dir``."""
    csv, md = Path(out_dir) / "table_transfer.csv", Path(out_dir) / "table_transfer.md"
    table.to_csv(csv, index=False)
    md.write_text(to_markdown(table, backend))
    return [csv, md]
