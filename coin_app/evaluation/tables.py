"""Table 5.1-style result tables: mean (std) per method x scenario x metric, best in bold, second underlined.

Input is a ranked summary (:func:`coin_app.evaluation.statistics.rank_marks`). Markdown marks
the best with ``**...**`` and the second with ``<u>...</u>``; LaTeX with ``\\textbf{}`` and
``\\underline{}`` (plain ``tabular`` with ``\\hline``, no extra packages); the CSV holds the raw
mean, std, episode count and rank (1 best, 2 second, 0 neither) per metric, one row per
(scenario, method).
"""

from __future__ import annotations

import math
from html import escape
from pathlib import Path

import pandas as pd

from coin_app.evaluation.statistics import METRIC_BY_KEY


def cell(metric: str, mean: float, std: float) -> str:
    """``mean (std)`` as displayed for ``metric`` (rates in %); ``-`` when undefined."""
    spec = METRIC_BY_KEY[metric]
    if math.isnan(mean):
        return "-"
    body = f"{mean * spec.scale:.{spec.decimals}f}"
    return body if math.isnan(std) else f"{body} ({std * spec.scale:.{spec.decimals}f})"


def _blocks(summary: pd.DataFrame) -> list[tuple[str, list[str], list[tuple[str, list[tuple[str, int]]]]]]:
    """Per scenario: (scenario, metrics, [(label, [(cell text, rank)])])."""
    out = []
    for scenario, g in summary.groupby("scenario", sort=False):
        metrics = list(dict.fromkeys(g["metric"]))
        rows = []
        for label, r in g.groupby("label", sort=False):
            by_metric = r.set_index("metric")
            rows.append(
                (label, [(cell(m, by_metric.at[m, "mean"], by_metric.at[m, "std"]), int(by_metric.at[m, "rank"])) for m in metrics])
            )
        out.append((scenario, metrics, rows))
    return out


def to_markdown(summary: pd.DataFrame, title: str, label_header: str = "Method") -> str:
    """Markdown tables, one per scenario, best **bold** and second <u>underlined</u>."""
    lines = [f"## {title}", ""]
    for scenario, metrics, rows in _blocks(summary):
        lines += [f"### {scenario}", "", "| " + " | ".join([label_header, *(METRIC_BY_KEY[m].label for m in metrics)]) + " |"]
        lines.append("|" + "---|" * (len(metrics) + 1))
        for label, cells in rows:
            shown = [f"**{t}**" if r == 1 else f"<u>{t}</u>" if r == 2 else t for t, r in cells]
            lines.append("| " + " | ".join([label, *shown]) + " |")
        lines.append("")
    return "\n".join(lines)


def _tex_escape(text: str) -> str:
    for a, b in (("\\", "\\textbackslash{}"), ("_", "\\_"), ("%", "\\%"), ("&", "\\&"), ("#", "\\#")):
        text = text.replace(a, b)
    return text


def to_latex(summary: pd.DataFrame, caption: str) -> str:
    """One LaTeX table, a block per scenario, best ``\\textbf`` and second ``\\underline``."""
    blocks = _blocks(summary)
    metrics = blocks[0][1] if blocks else []
    cols = len(metrics) + 1
    lines = [
        "\\begin{table}[t]",
        "\\centering",
        f"\\caption{{{_tex_escape(caption)}}}",
        "\\begin{tabular}{l" + "c" * len(metrics) + "}",
        "\\hline",
        " & ".join(["Method", *(_tex_escape(METRIC_BY_KEY[m].label) for m in metrics)]) + " \\\\",
        "\\hline",
    ]
    for scenario, _, rows in blocks:
        lines.append(f"\\multicolumn{{{cols}}}{{l}}{{\\textit{{{_tex_escape(scenario)}}}}} \\\\")
        for label, cells in rows:
            shown = [f"\\textbf{{{t}}}" if r == 1 else f"\\underline{{{t}}}" if r == 2 else t for t, r in cells]
            lines.append(" & ".join([_tex_escape(label), *shown]) + " \\\\")
        lines.append("\\hline")
    lines += ["\\end{tabular}", "\\end{table}", ""]
    return "\n".join(lines)


def to_wide(summary: pd.DataFrame) -> pd.DataFrame:
    """One row per (scenario, label) with ``<metric>_{mean,std,n,rank}`` columns."""
    rows = []
    for (scenario, label), g in summary.groupby(["scenario", "label"], sort=False):
        row = {"scenario": scenario, "method": label}
        for r in g.itertuples():
            row |= {f"{r.metric}_mean": r.mean, f"{r.metric}_std": r.std, f"{r.metric}_n": r.n, f"{r.metric}_rank": r.rank}
        rows.append(row)
    return pd.DataFrame(rows)


def write_tables(summary: pd.DataFrame, out_dir: Path, stem: str, title: str, label_header: str = "Method") -> list[Path]:
    """Write ``<stem>.md``, ``<stem>.csv`` and ``<stem>.tex``; returns their paths."""
    out_dir = Path(out_dir)
    md, csv, tex = out_dir / f"{stem}.md", out_dir / f"{stem}.csv", out_dir / f"{stem}.tex"
    md.write_text(to_markdown(summary, title, label_header))
    to_wide(summary).to_csv(csv, index=False)
    tex.write_text(to_latex(summary, title))
    return [md, csv, tex]


def to_html(summary: pd.DataFrame, label_header: str = "Method") -> str:
    """HTML tables, one per scenario, best in <b> and second in <u>."""

    parts = []
    for scenario, metrics, rows in _blocks(summary):
        head = "".join(f"<th>{escape(h)}</th>" for h in [label_header, *(METRIC_BY_KEY[m].label for m in metrics)])
        body = []
        for label, cells in rows:
            shown = [f"<b>{escape(t)}</b>" if r == 1 else f"<u>{escape(t)}</u>" if r == 2 else escape(t) for t, r in cells]
            body.append("<tr>" + "".join(f"<td>{c}</td>" for c in [escape(label), *shown]) + "</tr>")
        parts.append(f"<h3>{escape(scenario)}</h3><table><thead><tr>{head}</tr></thead><tbody>{''.join(body)}</tbody></table>")
    return "\n".join(parts)
