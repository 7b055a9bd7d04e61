"""The paper's result figures as PNG files (matplotlib, no display needed).

* :func:`plot_radar` - Fig. 5: success, safety and efficiency per method, each metric min-max
  normalized across the methods of the scenario to [0.1, 1] (the paper normalizes to [0, 1];
  the floor keeps the worst method's polygon visible; a metric on which all methods tie is
  drawn at 1 and labelled "all equal").
* :func:`plot_generalization` - Figs. 4/6: success rate vs initial agent count, one line per
  method (mean over trained seeds of the per-seed mean, band = std over seeds), the training
  count marked.
* :func:`plot_learning_curves` - Fig. 4: training episode return (and train success rate) vs
  env steps from Tune's progress files, mean +- std over seeds on a common step grid.
* :func:`plot_latent_tsne` - App. B.1: t-SNE of CVAE latents, all scenarios coloured by
  scenario, then per scenario coloured by a 6-cluster k-means fitted before the projection.
* :func:`plot_attention` - where CIG-TD3's GAT looks: one crossing conflict's scene with each
  neighbour coloured by its attention share, and the mean share by distance, conflict partners
  beside the other neighbours (:mod:`coin_app.evaluation.attention`).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pandas as pd
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import PolyCollection
from matplotlib.figure import Figure

from coin_app.sim.rendering import draw_map, vehicle_corners

RADAR_METRICS = (("success_rate", "Success"), ("safety", "Safety"), ("efficiency", "Efficiency"))
PALETTE = ("#d62728", "#1f77b4", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf")


def label_colors(labels: Sequence[str]) -> dict[str, str]:
    """A fixed colour per label, in the given order (the chosen method first gets red)."""
    return {label: PALETTE[i % len(PALETTE)] for i, label in enumerate(labels)}


def _seeds(n: int) -> str:
    return f"{n} seed" if n == 1 else f"{n} seeds"


def _figure(width: float, height: float) -> Figure:
    fig = Figure(figsize=(width, height), dpi=100, facecolor="white", layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _z(colors: dict[str, str], label: str) -> float:
    """Drawing order: labels earlier in ``colors`` (the chosen method first) are drawn on top."""
    order = list(colors)
    return 2.0 + (len(order) - order.index(label)) / max(len(order), 1) if label in order else 2.0


def _save(fig: Figure, path: Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    return path


def radar_values(summary: pd.DataFrame) -> pd.DataFrame:
    """Per label, the radar metrics min-max normalized across labels to [0.1, 1] (all equal: 1)."""
    wide = summary.pivot_table(index="label", columns="metric", values="mean", sort=False)
    out = pd.DataFrame(index=wide.index)
    for key, _ in RADAR_METRICS:
        v = wide[key].astype(float)
        span = v.max() - v.min()
        out[key] = 1.0 if not span > 0 else 0.1 + 0.9 * (v - v.min()) / span
    return out


def plot_radar(summary: pd.DataFrame, path: Path, scenario: str, colors: dict[str, str]) -> Path:
    """Radar chart of success, safety and efficiency per method for one scenario (a comparison: two methods at least)."""
    values = radar_values(summary)
    if len(values) < 2:
        raise ValueError(f"a radar compares methods after min-max normalization; only {', '.join(values.index)} is here")
    angles = np.linspace(0.0, 2.0 * np.pi, len(RADAR_METRICS), endpoint=False)
    closed = np.append(angles, angles[0])
    fig = _figure(5.2, 4.6)
    ax = fig.add_subplot(1, 1, 1, projection="polar")
    for label, row in values.iterrows():
        r = np.array([row[k] for k, _ in RADAR_METRICS])
        z = _z(colors, label)
        ax.plot(closed, np.append(r, r[0]), color=colors[label], lw=2, marker="o", ms=4, label=label, zorder=z)
        ax.fill(closed, np.append(r, r[0]), color=colors[label], alpha=0.12, zorder=z - 1)
    ax.set_xticks(angles)
    tied = [len(values) > 1 and values[key].nunique() == 1 for key, _ in RADAR_METRICS]
    ax.set_xticklabels([f"{name}\n(all equal)" if t else name for (_, name), t in zip(RADAR_METRICS, tied)])
    ax.set_ylim(0, 1.05)
    ax.set_yticks([0.25, 0.5, 0.75, 1.0])
    ax.set_yticklabels([])
    ax.set_title(f"{scenario}: min-max normalized across methods", fontsize=10)
    ax.legend(loc="upper right", bbox_to_anchor=(1.35, 1.1), fontsize=8, frameon=False)
    return _save(fig, path)


def plot_generalization(rows: pd.DataFrame, path: Path, scenario: str, colors: dict[str, str]) -> Path:
    """Success rate vs initial agent count for one scenario, one line per label, training count marked."""
    fig = _figure(6.0, 4.0)
    ax = fig.add_subplot(1, 1, 1)
    per_seed = rows.groupby(["label", "trained_seed", "agent_count"], sort=False)["success_rate"].mean().reset_index()
    for label, g in per_seed.groupby("label", sort=False):
        stats = g.groupby("agent_count")["success_rate"].agg(["mean", "std", "count"]).sort_index()
        x, m = stats.index.to_numpy(), 100.0 * stats["mean"].to_numpy()
        s = 100.0 * stats["std"].fillna(0.0).to_numpy()
        ax.plot(
            x, m, color=colors[label], marker="o", lw=2, label=f"{label} ({_seeds(int(stats['count'].max()))})", zorder=_z(colors, label)
        )
        ax.fill_between(x, m - s, m + s, color=colors[label], alpha=0.15)
    for count in sorted(rows["trained_agent_count"].unique()):
        ax.axvline(count, color="k", ls="--", lw=1)
        ax.annotate(
            f"trained at {count}", (count, 1.0), xycoords=("data", "axes fraction"), xytext=(3, -12), textcoords="offset points", fontsize=8
        )
    ax.xaxis.get_major_locator().set_params(integer=True)
    ax.set_ylim(-3, 103)
    ax.set_xlabel("initial number of agents")
    ax.set_ylabel("success rate (%)")
    ax.set_title(f"{scenario}: generalization over agent counts", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, frameon=False)
    return _save(fig, path)


def mean_curve(curves: pd.DataFrame, column: str, points: int = 50, x: str = "env_steps") -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(x, mean, std) of ``column`` over seeds, each seed's curve against ``x`` interpolated onto a common grid.

    The grid spans the ``x`` every seed reached (from the largest first point to the smallest last).
    """
    seeds = [g.dropna(subset=[column, x]).sort_values(x) for _, g in curves.groupby("seed")]
    seeds = [g for g in seeds if len(g)]
    if not seeds:
        return np.zeros(0), np.zeros(0), np.zeros(0)
    lo = max(float(g[x].iloc[0]) for g in seeds)
    hi = min(float(g[x].iloc[-1]) for g in seeds)
    grid = np.linspace(lo, hi, points) if hi > lo else np.array([hi])
    ys = np.array([np.interp(grid, g[x].to_numpy(float), g[column].to_numpy(float)) for g in seeds])
    return grid, ys.mean(0), ys.std(0)


# the x axes of the learning curves: (progress column, axis label, scale to the axis unit)
CURVE_AXES = {
    "env_steps": ("env steps", 1.0),
    "cpu_s": ("CPU hours of the trial (its processes)", 1 / 3600),
    "wall_s": ("wall-clock hours of the trial", 1 / 3600),
}


def curve_axes(curves: pd.DataFrame) -> list[str]:
    """The time axes every run of ``curves`` has: ``cpu_s`` and ``wall_s`` where each run recorded them."""
    if curves.empty:
        return []
    runs = curves.groupby(["label", "seed"])
    return [x for x in ("cpu_s", "wall_s") if x in curves.columns and runs[x].apply(lambda v: v.notna().any()).all()]


def plot_learning_curves(curves: pd.DataFrame, path: Path, scenario: str, colors: dict[str, str], x: str = "env_steps") -> Path:
    """Training episode return and train success rate vs ``x`` (env steps, CPU or wall seconds), mean +- std over seeds, per label."""
    panels = [("episode_return_mean", "episode return (train)"), ("train_success_rate", "success rate (train)")]
    panels = [p for p in panels if p[0] in curves.columns]
    xlabel, factor = CURVE_AXES[x]
    fig = _figure(5.0 * len(panels), 3.8)
    for k, (column, ylabel) in enumerate(panels):
        ax = fig.add_subplot(1, len(panels), k + 1)
        for label, g in curves.groupby("label", sort=False):
            grid, m, s = mean_curve(g, column, x=x)
            if len(grid):
                grid = grid * factor
                ax.plot(grid, m, color=colors[label], lw=2, label=f"{label} ({_seeds(g['seed'].nunique())})", zorder=_z(colors, label))
                ax.fill_between(grid, m - s, m + s, color=colors[label], alpha=0.15)
        if column == "train_success_rate":
            ax.set_ylim(-0.03, 1.03)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(ylabel)
        ax.grid(alpha=0.3)
        if k == 0:
            ax.legend(fontsize=8, frameon=False)
    against = "" if x == "env_steps" else f" against {xlabel.split(' of ')[0]}"
    fig.suptitle(f"{scenario}: learning curves{against} (mean ± std over seeds)", fontsize=10)
    return _save(fig, path)


def plot_latent_tsne(
    embeddings: dict[str, np.ndarray], clusters: dict[str, np.ndarray], joint: np.ndarray, joint_scenario: np.ndarray, path: Path
) -> Path:
    """Panel (a): the joint t-SNE coloured by scenario; then one panel per scenario coloured by k-means cluster."""
    scenarios = list(embeddings)
    fig = _figure(4.0 * (1 + len(scenarios)), 4.0)
    ax = fig.add_subplot(1, 1 + len(scenarios), 1)
    for i, name in enumerate(dict.fromkeys(joint_scenario)):
        pts = joint[joint_scenario == name]
        ax.scatter(pts[:, 0], pts[:, 1], s=5, color=PALETTE[i % len(PALETTE)], label=f"{name} ({len(pts)})")
    ax.set_title("(a) all scenarios", fontsize=10)
    ax.legend(fontsize=8, markerscale=3, loc="best", framealpha=0.85)
    for k, name in enumerate(scenarios):
        ax = fig.add_subplot(1, 1 + len(scenarios), k + 2)
        y, lab = embeddings[name], clusters[name]
        ax.scatter(y[:, 0], y[:, 1], s=5, c=[PALETTE[c % len(PALETTE)] for c in lab])
        ax.set_title(f"({chr(ord('b') + k)}) {name}: {len(set(lab.tolist()))} k-means clusters", fontsize=10)
    for a in fig.axes:
        a.set_xticks([])
        a.set_yticks([])
    fig.suptitle("t-SNE of the CVAE latent means z_ij", fontsize=10)
    return _save(fig, path)


def plot_attention(edges: pd.DataFrame, summary: pd.DataFrame, snapshot: dict | None, road_map: object, path: Path, title: str) -> Path:
    """(a) The snapshot's scene (if any): the ego, its partner ringed, each neighbour coloured by its share; (b) mean share
    per distance bin, conflict partners beside the other neighbours, edge counts on the bars; 1 = uniform attention."""
    fig = _figure(11.0, 5.0)
    ax = fig.add_subplot(1, 2, 1)
    if snapshot is not None:
        draw_map(ax, road_map)
        boxes = vehicle_corners(snapshot["pos"], snapshot["heading"], snapshot["half"])
        shares = np.array([snapshot["share"].get(k, np.nan) for k in range(len(boxes))])
        shares[snapshot["ego"]] = np.nan
        cars = PolyCollection(list(boxes), cmap="coolwarm", edgecolors="black", linewidths=0.4, zorder=5)
        cars.set_array(np.where(np.isfinite(shares), shares, 1.0))
        cars.set_clim(0.0, 2.0)  # white = uniform
        ax.add_collection(cars)
        ax.add_collection(PolyCollection([boxes[snapshot["ego"]]], facecolors="#d62728", edgecolors="black", zorder=6))
        ax.add_collection(PolyCollection([boxes[snapshot["partner"]]], facecolors="none", edgecolors="#d62728", linewidths=2.0, zorder=6))
        fig.colorbar(cars, ax=ax, shrink=0.8, label="attention share (1 = uniform)")
        centre = snapshot["pos"][snapshot["ego"]]
        ax.set_xlim(centre[0] - 45, centre[0] + 45)
        ax.set_ylim(centre[1] - 45, centre[1] + 45)
        ax.set_aspect("equal")
        partner = snapshot["share"][snapshot["partner"]]
        ax.set_title(
            f"(a) test seed {snapshot['seed']}, step {snapshot['env_step']}: ego (red), its crossing partner ringed (share {partner:.2f})",
            fontsize=9,
        )
    else:
        ax.text(0.5, 0.5, "no crossing conflict found", ha="center", va="center", transform=ax.transAxes)
    ax.set_xticks([])
    ax.set_yticks([])
    ax = fig.add_subplot(1, 2, 2)
    bins = list(dict.fromkeys(summary["bin"].astype(str)))
    x = np.arange(len(bins))
    for k, (conflict, label, color) in enumerate(((False, "other neighbours", "#7f7f7f"), (True, "crossing partners", "#d62728"))):
        part = summary[summary["conflict"] == conflict].assign(bin=lambda d: d["bin"].astype(str)).set_index("bin")
        means = [float(part["mean"].get(b, np.nan)) for b in bins]
        counts = [int(part["count"].get(b, 0)) for b in bins]
        bars = ax.bar(x + (k - 0.5) * 0.4, means, 0.4, color=color, label=label)
        for bar, n in zip(bars, counts, strict=True):
            if n:
                ax.annotate(f"{n:,}", (bar.get_x() + bar.get_width() / 2, bar.get_height()), ha="center", va="bottom", fontsize=7)
    ax.axhline(1.0, color="black", linewidth=0.8, linestyle="--")
    ax.set_xticks(x, [f"{b} m" for b in bins], fontsize=8)
    ax.set_ylabel("mean attention share (1 = uniform)")
    ax.set_title(f"(b) {len(edges):,} ego-neighbour edges by distance", fontsize=9)
    ax.legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    return _save(fig, path)
