"""Several arena policies side by side on the 24-case suite, next to the seed-2 paper's Tables I and II.

``evaluate-arena`` scores each policy on the same fixed test scenarios
(``coin_app.evaluation.arena_suite``) and writes, besides each policy's own case table, one
side-by-side table (``arena_side_by_side.md`` / ``.csv``: success-to-goal rate, collisions per
metre and policy time per step of every policy, then the paper's figures for its agent and for
the A-GNN) and a page with the table and the trajectory plots (``arena_report.html``). The
settings go to ``arena_eval.json``, so ``report`` can take such a directory as a source and
rebuild the page elsewhere (:func:`load_arena_eval`).
"""

from __future__ import annotations

import json
import math
from html import escape
from pathlib import Path
from typing import Any

import pandas as pd

from coin_app.evaluation.html_report import STYLE, image_html
from coin_app.sim.arena.heuristic import DRIVERS

EVAL_FILE = "arena_eval.json"  # the settings of an evaluate-arena run: what marks its directory as a report source
SIDE_BY_SIDE = "arena_side_by_side"
PAGE = "arena_report.html"
# per-policy columns of the side-by-side table: (column suffix, summary column, scale, format)
POLICY_COLUMNS = (
    ("success", "success_to_goal_rate", 1.0, ".3f"),
    ("collisions/m", "collision_rate", 1.0, ".2e"),
    ("step ms", "step_time_s", 1e3, ".3f"),
)
# the papers' columns: (column, summary column, scale, format)
PAPER_COLUMNS = (
    ("paper success", "paper_success", 1.0, ".3f"),
    ("paper A-GNN success", "paper_agnn_success", 1.0, ".3f"),
    ("A-GNN own paper success", "agnn_supp_success", 1.0, ".3f"),
    ("paper collisions/m", "paper_collision_rate", 1.0, ".2e"),
    ("paper A-GNN collisions/m", "paper_agnn_collision_rate", 1.0, ".2e"),
    ("paper step ms", "paper_step_time_s", 1e3, ".3f"),
    ("paper A-GNN step ms", "paper_agnn_step_time_s", 1e3, ".3f"),
)


def policy_label(source: str | Path) -> str:
    """A short name for a policy source: a scripted driver's name, ``agnn``, a file's stem, or a checkpoint's run directory."""
    text = str(source)
    if text in (*DRIVERS, "agnn"):
        return text
    path = Path(text.rstrip("/"))
    if path.name == "checkpoint" and path.parent.name:
        return path.parent.name
    return path.stem or text


def policy_labels(sources: list[str]) -> list[str]:
    """The labels of ``sources`` (ValueError naming two sources that would share one)."""
    labels = [policy_label(s) for s in sources]
    for i, label in enumerate(labels):
        if label in labels[:i]:
            first = sources[labels.index(label)]
            raise ValueError(f"policies {first!r} and {sources[i]!r} would both be labelled {label!r}; give them different file names")
    return labels


def side_by_side(summaries: dict[str, pd.DataFrame]) -> pd.DataFrame:
    """One row per case: every policy's success, collisions/m and step ms (``arena_suite.summarize`` tables), then the papers'."""
    if not summaries:
        raise ValueError("no policy summaries to put side by side")
    first = next(iter(summaries.values()))
    keys = ["vehicles", "obstacles", "scenarios"]
    table = first[keys].copy()
    for label, summary in summaries.items():
        if list(summary["vehicles"]) != list(first["vehicles"]) or list(summary["obstacles"]) != list(first["obstacles"]):
            raise ValueError(f"policy {label!r} was evaluated on other cases than {next(iter(summaries))!r}")
        for suffix, column, scale, _ in POLICY_COLUMNS:
            table[f"{label} {suffix}"] = summary[column].to_numpy() * scale
    for name, column, scale, _ in PAPER_COLUMNS:
        table[name] = first[column].to_numpy() * scale
    return table


def _fmt(value: Any, fmt: str) -> str:
    """A number in ``fmt``, or an en dash where there is none."""
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    return format(value, fmt)


def _formats(labels: list[str]) -> dict[str, str]:
    """Column name -> number format of a side-by-side table of ``labels``."""
    out = {f"{label} {suffix}": fmt for label in labels for suffix, _, _, fmt in POLICY_COLUMNS}
    return out | {name: fmt for name, _, _, fmt in PAPER_COLUMNS}


def side_by_side_markdown(table: pd.DataFrame, labels: list[str]) -> str:
    """The side-by-side table as Markdown (case, then each policy's three columns, then the papers')."""
    formats = _formats(labels)
    columns = ["case", *formats]
    lines = ["| " + " | ".join(columns) + " |", "|---|" + "---:|" * len(formats)]
    for r in table.to_dict("records"):
        cells = [f"{r['vehicles']}x{r['obstacles']}", *(_fmt(r[c], f) for c, f in formats.items())]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_side_by_side(out: Path, summaries: dict[str, pd.DataFrame], settings: dict[str, Any]) -> tuple[pd.DataFrame, str]:
    """Write ``arena_side_by_side.csv`` / ``.md`` and ``arena_eval.json`` into ``out``; return the table and its Markdown."""
    labels = list(summaries)
    table = side_by_side(summaries)
    table.to_csv(out / f"{SIDE_BY_SIDE}.csv", index=False)
    header = (
        f"Policies: {', '.join(f'`{s}`' for s in settings['policies'])}; {settings['scenarios_per_case']} test scenarios per case; "
        f"{settings['protocol']} protocol; the paper's columns are its Tables I and II (4,062 scenarios per case).\n\n"
    )
    if settings.get("generator", "agnn") != "agnn":
        header += f"Scenarios of the `{settings['generator']}` generator, not the paper's suite: the paper's columns do not apply.\n\n"
    markdown = side_by_side_markdown(table, labels)
    (out / f"{SIDE_BY_SIDE}.md").write_text(header + markdown)
    (out / EVAL_FILE).write_text(json.dumps(settings | {"labels": labels}, indent=2))
    return table, markdown


def is_arena_eval(path: str | Path) -> bool:
    """Whether ``path`` is the output directory of an ``evaluate-arena`` run."""
    return (Path(path) / EVAL_FILE).is_file()


def load_arena_eval(path: str | Path) -> tuple[pd.DataFrame, dict[str, Any], dict[str, list[Path]]]:
    """(side-by-side table, settings, trajectory plots per label) of an ``evaluate-arena`` output directory."""
    path = Path(path)
    try:
        settings = json.loads((path / EVAL_FILE).read_text())
        table = pd.read_csv(path / f"{SIDE_BY_SIDE}.csv")
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path} is not a readable evaluate-arena output ({str(exc).splitlines()[0]})") from None
    plots = {label: sorted((path / folder / "plots").glob("*.png")) for label, folder in settings["folders"].items()}
    return table, settings, plots


def arena_section(table: pd.DataFrame, settings: dict[str, Any], plots: dict[str, list[Path]]) -> str:
    """The HTML of one evaluate-arena run: its settings, the side-by-side table and each policy's trajectory plots."""
    labels = settings["labels"]
    formats = _formats(labels)
    head = "".join(f"<th>{escape(c)}</th>" for c in ["case", *formats])
    body = "".join(
        "<tr>"
        + f"<td>{r['vehicles']}x{r['obstacles']}</td>"
        + "".join(f"<td>{escape(_fmt(r[c], f))}</td>" for c, f in formats.items())
        + "</tr>"
        for r in table.to_dict("records")
    )
    parts = [
        f"<h2>Arena suite, {escape(settings['protocol'])} protocol</h2>",
        f"<p>Policies: {', '.join(f'<code>{escape(s)}</code>' for s in settings['policies'])}; {settings['scenarios_per_case']} fixed "
        f"test scenarios per case, up to {settings['max_steps']} steps of 0.1 s; deterministic actions. Paper columns: the seed "
        "paper's Tables I and II (its agent, and its re-run of the A-GNN) and the A-GNN paper's own success rates.</p>",
        f"<table><tr>{head}</tr>{body}</table>",
    ]
    for label in labels:
        if plots.get(label):
            parts.append(f"<h3>Trajectories: {escape(label)}</h3>")
            parts += [image_html(p) for p in plots[label]]
    return "\n".join(parts)


def write_arena_html(
    path: Path, runs: list[tuple[pd.DataFrame, dict[str, Any], dict[str, list[Path]]]], command: str | None = None
) -> Path:
    """Write a page with one section per evaluate-arena run (plots embedded); returns its path."""
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>coin_app arena report</title><style>{STYLE}</style></head><body>",
        "<h1>coin_app arena report: navigation and parking (seed-2 paper)</h1>",
    ]
    if command:
        parts.append(f"<p>Generated by <code>{escape(command)}</code>.</p>")
    parts += [arena_section(*run) for run in runs]
    parts.append("</body></html>")
    path = Path(path)
    path.write_text("\n".join(parts))
    return path
