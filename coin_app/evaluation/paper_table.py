"""COIN's Table 5.1, the paper's own figures, and a report's results beside them.

``TABLE_5_1[scene][method]`` holds the six metrics' mean and standard deviation as the paper prints
them (rates in %, efficiency and safety per episode, travel steps), for the seven methods on the
three scenes at the paper's densities (``PAPER_COUNTS``). :func:`beside_paper` puts a report's
summary (``statistics.summarize``) at the same density next to them, metric by metric, with the
difference in the paper's units.
"""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd

from coin_app.evaluation.statistics import METRIC_BY_KEY, METRICS

PAPER_COUNTS = {"intersection": 30, "roundabout": 40, "bottleneck": 20}  # initial vehicles of each scene in Table 5.1
PAPER_METRICS = tuple(m.key for m in METRICS)  # the table's columns, in its order
AUTHORS = "coin_authors"  # the label of the COIN authors' released actors in a report: beside the paper's COIN row
PAPER_NAMES = {"ippo": "IPPO", "mfpo": "MFPO", "cppo": "CPPO", "copo": "CoPo", "itd3": "ITD3", "traco": "TraCo", "cig_td3": "COIN"}
PAPER_NAMES[AUTHORS] = "COIN, the authors' actors"
PAPER_ROW = {AUTHORS: "cig_td3"}  # a label's Table 5.1 row where it is not the label's own

_ROWS = {  # (mean, std) per metric in PAPER_METRICS' order, as printed in Table 5.1
    "intersection": {
        "ippo": ((69.96, 15.21), (8.01, 4.73), (18.00, 7.20), (42.70, 24.5), (-22.87, 6.99), (588.59, 122.50)),
        "mfpo": ((69.95, 16.54), (7.41, 5.18), (19.08, 7.92), (44.73, 27.64), (-23.76, 7.34), (579.62, 142.27)),
        "cppo": ((65.68, 13.34), (8.59, 4.32), (24.39, 8.14), (38.01, 25.05), (-35.07, 8.58), (570.42, 109.10)),
        "copo": ((75.20, 12.99), (5.86, 3.08), (16.35, 7.64), (49.20, 20.85), (-19.59, 7.29), (567.22, 102.62)),
        "itd3": ((72.66, 9.08), (5.61, 3.57), (21.82, 7.43), (59.58, 22.79), (-36.98, 13.66), (469.18, 65.43)),
        "traco": ((73.08, 9.07), (7.52, 4.01), (19.21, 7.88), (57.06, 22.81), (-32.86, 11.50), (482.16, 70.32)),
        "cig_td3": ((88.78, 10.09), (4.13, 3.90), (3.94, 3.74), (68.64, 15.47), (-6.73, 4.72), (509.60, 79.94)),
    },
    "roundabout": {
        "ippo": ((66.99, 9.61), (7.82, 4.16), (10.52, 4.26), (40.16, 14.03), (-15.09, 5.54), (738.75, 57.92)),
        "mfpo": ((66.95, 9.63), (8.12, 4.01), (13.32, 5.60), (39.27, 13.47), (-18.45, 5.78), (736.59, 44.43)),
        "cppo": ((71.57, 8.01), (7.02, 2.89), (20.20, 8.12), (45.82, 15.64), (-28.66, 9.51), (667.04, 47.11)),
        "copo": ((69.03, 12.17), (5.16, 2.59), (11.82, 5.32), (43.17, 15.72), (-13.87, 5.13), (729.40, 57.01)),
        "itd3": ((81.12, 7.73), (4.66, 2.95), (12.14, 6.85), (64.85, 15.73), (-16.94, 6.66), (624.35, 63.41)),
        "traco": ((72.10, 6.22), (12.82, 5.98), (13.94, 7.01), (48.93, 12.21), (-29.38, 8.11), (649.67, 42.81)),
        "cig_td3": ((90.68, 4.82), (5.36, 2.99), (3.22, 3.38), (80.66, 9.46), (-8.58, 5.03), (579.01, 39.14)),
    },
    "bottleneck": {
        "ippo": ((71.46, 12.50), (17.70, 10.49), (11.10, 6.14), (34.12, 19.28), (-22.16, 8.55), (523.20, 105.81)),
        "mfpo": ((66.71, 12.43), (18.72, 8.67), (14.90, 6.98), (28.26, 21.70), (-29.35, 11.91), (534.84, 94.61)),
        "cppo": ((70.08, 9.46), (15.99, 6.05), (14.16, 6.22), (33.68, 14.77), (-26.61, 9.92), (512.12, 63.10)),
        "copo": ((70.61, 11.23), (19.14, 9.17), (10.57, 5.21), (30.83, 17.27), (-22.86, 9.54), (535.51, 78.55)),
        "itd3": ((87.87, 5.69), (5.76, 2.71), (6.63, 4.75), (84.40, 13.33), (-13.87, 6.58), (301.27, 49.6)),
        "traco": ((86.44, 12.86), (7.90, 8.43), (6.12, 5.36), (84.22, 30.18), (-16.44, 15.31), (303.77, 107.50)),
        "cig_td3": ((96.33, 3.12), (2.13, 1.77), (1.57, 2.08), (96.91, 10.64), (-3.79, 3.17), (246.42, 36.40)),
    },
}
TABLE_5_1: dict[str, dict[str, dict[str, tuple[float, float]]]] = {
    scene: {method: dict(zip(PAPER_METRICS, values)) for method, values in rows.items()} for scene, rows in _ROWS.items()
}
BESIDE_COLUMNS = ["scenario", "label", "metric", "ours", "ours_std", "paper", "paper_std", "difference", "n"]


def paper_figure(scene: str, method: str, metric: str) -> tuple[float, float] | None:
    """Table 5.1's (mean, std) of ``method`` on ``scene`` in the paper's units (rates in %), or None where it has none."""
    return TABLE_5_1.get(scene, {}).get(method, {}).get(metric)


def at_paper_density(rows: pd.DataFrame) -> pd.DataFrame:
    """The episode rows of models trained and evaluated at Table 5.1's density of their scene (``PAPER_COUNTS``)."""
    density = rows["scenario"].map(PAPER_COUNTS)
    return rows[(rows["trained_agent_count"] == density) & (rows["agent_count"] == density)]


def beside_paper(summary: pd.DataFrame) -> pd.DataFrame:
    """A summary's rows (scenario, label, metric, mean, std, n) that Table 5.1 has, beside the paper's, in its units.

    ``summary`` must be at the paper's density of each scene (the caller filters by training agent count);
    labels are method names (``cig_td3``, ``ippo``...; the authors' actors, :data:`AUTHORS`, beside the paper's COIN row),
    others are left out. ``difference`` = ours - paper.
    """
    rows = []
    for r in summary.itertuples():
        paper = paper_figure(str(r.scenario), PAPER_ROW.get(str(r.label), str(r.label)), str(r.metric))
        if paper is None:
            continue
        scale = METRIC_BY_KEY[r.metric].scale
        ours, std = float(r.mean) * scale, float(r.std) * scale
        rows.append([r.scenario, r.label, r.metric, ours, std, paper[0], paper[1], ours - paper[0], int(r.n)])
    return pd.DataFrame(rows, columns=BESIDE_COLUMNS)


def to_markdown(beside: pd.DataFrame, title: str) -> str:
    """One markdown table per scene: per method and metric ``ours (std) | paper (std)``, methods in Table 5.1's order."""
    lines = [f"## {title}", ""]
    for scene, g in beside.groupby("scenario", sort=False):
        metrics = [m for m in PAPER_METRICS if m in set(g["metric"])]
        header = ["Method", *(f"{METRIC_BY_KEY[m].label}: ours / paper" for m in metrics)]
        lines += [f"### {scene} ({PAPER_COUNTS[scene]} vehicles)", "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
        for method in [m for m in (*TABLE_5_1[scene], AUTHORS) if m in set(g["label"])]:
            by_metric = g[g["label"] == method].set_index("metric")
            cells = []
            for m in metrics:
                d = METRIC_BY_KEY[m].decimals
                if m not in by_metric.index:
                    cells.append("-")
                    continue
                r = by_metric.loc[m]
                ours = f"{r.ours:.{d}f}" + ("" if math.isnan(r.ours_std) else f" ({r.ours_std:.{d}f})")
                cells.append(f"{ours} / {r.paper:.{d}f} ({r.paper_std:.{d}f})")
            lines.append("| " + " | ".join([f"{method} ({PAPER_NAMES[method]})", *cells]) + " |")
        lines.append("")
    return "\n".join(lines)


def write_beside(beside: pd.DataFrame, out_dir: Path, title: str) -> list[Path]:
    """``table_paper.md`` and ``table_paper.csv`` in ``out_dir``; the paths."""
    md, csv = out_dir / "table_paper.md", out_dir / "table_paper.csv"
    md.write_text(to_markdown(beside, title) + "\n")
    beside.to_csv(csv, index=False)
    return [md, csv]
