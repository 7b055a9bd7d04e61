"""``report.html``: the tables, tests and figures of a report in one self-contained page (images inlined)."""

from __future__ import annotations

import base64
import json
import platform
import sys
import time
from html import escape
from importlib import metadata
from pathlib import Path
from typing import Any

import pandas as pd

from coin_app.algorithms.checkpoint_files import META_FILE, git_commit
from coin_app.evaluation.tables import to_html

PACKAGES = ("ray", "torch", "numpy", "pandas", "scipy", "matplotlib", "gymnasium", "pettingzoo")
STYLE = """
body { font-family: sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
table { border-collapse: collapse; margin: 0.5em 0 1.5em; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 3px 8px; text-align: right; }
th:first-child, td:first-child { text-align: left; }
img { max-width: 100%; border: 1px solid #eee; margin: 0.3em 0; }
pre { background: #f6f6f6; padding: 0.6em; overflow-x: auto; font-size: 0.8em; }
.note { color: #a33; }
"""


def versions() -> dict[str, str]:
    """Python, platform, the coin_app git commit (``-dirty`` with uncommitted changes) and the installed versions of the key packages."""
    out = {"python": sys.version.split()[0], "platform": platform.platform()}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    out["coin_app commit"] = git_commit()
    return out


def image_html(value: Any) -> str:
    """An <img> embedding the PNG at ``value``, or a note with ``value``'s text when it is not a file."""
    if isinstance(value, Path) and value.is_file():
        data = base64.b64encode(value.read_bytes()).decode("ascii")
        return f'<img alt="{escape(value.name)}" src="data:image/png;base64,{data}">'
    return f'<p class="note">{escape(str(value))}</p>'


def _models(table: pd.DataFrame) -> str:
    """Per evaluated model: label, seed, episodes and the checkpoint's own metadata (what trained it)."""
    rows = []
    for ckpt, g in table.groupby("checkpoint", sort=True):
        meta_file = Path(ckpt) / META_FILE
        meta = meta_file.read_text() if meta_file.is_file() else "(checkpoint metadata not available)"
        params = Path(ckpt).parent / "params.json"
        trial = f"<pre>{escape(params.read_text())}</pre>" if params.is_file() else ""
        first = g.iloc[0]
        rows.append(
            f"<details><summary>{escape(str(first['label']))} seed {int(first['trained_seed'])}: {len(g)} episodes, "
            f"{escape(str(ckpt))}</summary><pre>{escape(meta)}</pre>{trial}</details>"
        )
    return "\n".join(rows)


def write_html(
    path: Path,
    table: pd.DataFrame,
    main_summary: pd.DataFrame,
    ablation_summary: pd.DataFrame | None,
    stats: pd.DataFrame,
    figures: dict[str, Any],
    context: dict[str, Any],
    transfer: pd.DataFrame | None = None,
    beside: pd.DataFrame | None = None,
    cost: pd.DataFrame | None = None,
) -> Path:
    """Write the report page (with the native -> other-backend gap when ``transfer`` is given, the models at Table
    5.1's density beside the paper's figures when ``beside`` has rows, and the trials' training cost when ``cost``
    has rows); returns its path."""
    opts = context["options"]
    fails = context["failures"]
    parts = [
        f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>coin_app report</title><style>{STYLE}</style></head><body>",
        "<h1>coin_app evaluation report</h1>",
        f"<p>Generated {time.strftime('%Y-%m-%d %H:%M:%S')} by <code>{escape(str(opts.get('command') or 'build_report()'))}</code>. "
        f"{len(table)} test episodes of {table['checkpoint'].nunique()} models, deterministic actions, fixed test seeds "
        "(disjoint from training and validation seeds).</p>",
    ]
    if fails:
        items = "".join(
            f"<li>{escape(f.get('trial') or f.get('checkpoint') or f.get('path', '?'))}: {escape(f['error'])}</li>" for f in fails
        )
        parts.append(f"<h2>Not evaluated or unreadable</h2><ul class='note'>{items}</ul>")
    parts += [
        "<h2>Main results (Table 5.1 layout)</h2>",
        "<p>Mean (std) over all test episodes of all trained seeds; best in bold, second underlined.</p>",
    ]
    parts.append(to_html(main_summary))
    if beside is not None and len(beside):
        parts += [
            "<h2>Beside COIN's Table 5.1</h2>",
            "<p>The models trained at the paper's density: our mean and std over test episodes, the paper's, and the difference "
            "(ours - paper), in the paper's units (rates in %).</p>",
            beside.to_html(index=False, float_format=lambda v: f"{v:.2f}", na_rep="-"),
        ]
    if ablation_summary is not None:
        parts += [f"<h2>Ablations of {escape(opts['method'])}</h2>", to_html(ablation_summary, "Variant")]
    if len(stats):
        parts.append("<h2>Paired t-tests</h2>")
        pairing = {"episode": "paired on (trained seed, test seed), as the paper", "seed": "paired on the trained seed (each seed's mean)"}
        for unit, tests in stats.groupby("unit", sort=False):
            thr, n = tests["threshold"].iloc[0], len(tests)
            parts += [
                f"<p>{escape(opts['method'])} vs each baseline, {escape(pairing.get(str(unit), str(unit)))}; {n} tests, "
                f"Bonferroni threshold p &lt; {opts['alpha']} / {n} = {thr:.3g}.</p>",
                tests.to_html(index=False, float_format=lambda v: f"{v:.4g}", na_rep="-"),
            ]
    else:
        parts.append(f"<h2>Paired t-tests</h2><p class='note'>No baseline shares a scenario with {escape(opts['method'])}: no tests.</p>")
    if transfer is not None:
        backend = escape(str(opts.get("transfer")))
        parts += [
            f"<h2>Transfer: native vs {backend}</h2>",
            f"<p>The same models on the same test seeds at the training agent count, on the native simulator and on {backend}; "
            f"gap = {backend} - native (rates as fractions).</p>",
            transfer.to_html(index=False, float_format=lambda v: f"{v:.4g}", na_rep="-"),
        ]
    if cost is not None and len(cost):
        parts += [
            "<h2>Training cost</h2>",
            "<p>Each method's trials, read off their last progress rows: CPU hours (every process of the trial) and "
            "wall-clock hours, per trial and in all.</p>",
            cost.to_html(index=False, float_format=lambda v: f"{v:.3g}", na_rep="-"),
        ]
    parts.append("<h2>Figures</h2>")
    for name, value in figures.items():
        parts.append(f"<h3>{escape(name)}</h3>{image_html(value)}")
    parts += [
        "<h2>Provenance</h2><h3>Versions</h3>",
        "<table>" + "".join(f"<tr><td>{escape(k)}</td><td>{escape(v)}</td></tr>" for k, v in versions().items()) + "</table>",
        "<h3>Report options, sources, sweep settings (with the command that ran each sweep) and evaluation grid</h3>",
        f"<pre>{escape(json.dumps(context, indent=2, default=str))}</pre>",
        "<h3>Models: checkpoint metadata and trial config</h3>",
        _models(table),
        "</body></html>",
    ]
    path = Path(path)
    path.write_text("\n".join(parts))
    return path
