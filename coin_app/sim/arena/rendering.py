"""Arena trajectory plots: obstacles, every vehicle's path, its start and target poses, collisions and arrivals.

Matplotlib's object-oriented Agg API only (no display, pyplot untouched), like ``envs/rendering.py``
whose vehicle colours and box drawing it reuses.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PatchCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Circle

from coin_app.sim.rendering import ARRIVAL_COLOR, BACKGROUND, CRASH_COLOR, agent_colors, vehicle_corners


class ArenaTrace:
    """Positions and headings of every vehicle after each step, and where collisions started.

    Per recorded state (the reset, then each step) it also keeps which vehicles were still
    driving, which had reached the success state and how many collision events each started
    in that step: what the HTML replay (``arena/replay.py``) needs for its outcome markers.
    """

    def __init__(self) -> None:
        self.sim: Any = None
        self.positions: list[np.ndarray] = []
        self.headings: list[np.ndarray] = []
        self.collisions: list[np.ndarray] = []
        self.driving: list[np.ndarray] = []  # per state (N,) bool
        self.succeeded: list[np.ndarray] = []  # per state (N,) bool
        self.new_collisions: list[np.ndarray] = []  # per state (N,) int, 0 at the reset

    def start(self, sim: Any) -> None:
        """Begin recording an episode of ``sim`` (just reset)."""
        self.sim = sim
        self.positions, self.headings, self.collisions = [sim.pos.copy()], [sim.heading.copy()], []
        self.driving, self.succeeded = [sim.driving.copy()], [sim.succeeded.copy()]
        self.new_collisions = [np.zeros(sim.num_vehicles, int)]

    def record(self, new_collisions: np.ndarray) -> None:
        """Store the state after a step (and one point per collision event that started in it)."""
        self.positions.append(self.sim.pos.copy())
        self.headings.append(self.sim.heading.copy())
        self.driving.append(self.sim.driving.copy())
        self.succeeded.append(self.sim.succeeded.copy())
        new = np.asarray(new_collisions, int)
        self.new_collisions.append(np.broadcast_to(new, (self.sim.num_vehicles,)).copy())
        if new.any():
            self.collisions.append(np.repeat(self.sim.pos, new, axis=0))  # one point per collision event


def plot_arena_episode(trace: ArenaTrace, path: str | Path, title: str | None = None, size: float = 6.0, dpi: int = 110) -> Path:
    """Save a PNG of one arena episode (see module doc)."""
    sim, layout = trace.sim, trace.sim.layout
    n = sim.num_vehicles
    colors = agent_colors(np.arange(n))
    half = np.array([sim.config.vehicle_length / 2, sim.config.vehicle_width / 2])
    fig = Figure(figsize=(size, size + 0.5), dpi=dpi, facecolor="white", layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor(BACKGROUND)
    obstacles = [Circle((x, y), r) for x, y, r in layout.obstacles]
    ax.add_collection(PatchCollection(obstacles, facecolor="#7f7f7f", edgecolor="#404040", zorder=2))
    pos = np.stack(trace.positions, 1)  # (N, T, 2)
    ax.add_collection(LineCollection(list(pos), colors=colors, linewidths=1.4, zorder=4))
    starts = vehicle_corners(layout.starts[:, :2], layout.starts[:, 2], half)
    ax.add_collection(PolyCollection(list(starts), facecolors="none", edgecolors=colors, linewidths=1.0, linestyles="--", zorder=3))
    targets = vehicle_corners(layout.targets[:, :2], layout.targets[:, 2], half)
    ax.add_collection(PolyCollection(list(targets), facecolors=colors, edgecolors="k", linewidths=0.6, alpha=0.35, zorder=3))
    final = vehicle_corners(sim.pos, sim.heading, half)
    ax.add_collection(PolyCollection(list(final), facecolors=colors, edgecolors="k", linewidths=0.8, zorder=5))
    done = sim.succeeded & ~sim.collided
    ax.scatter(sim.pos[done, 0], sim.pos[done, 1], s=30, marker="o", c=ARRIVAL_COLOR, edgecolors="k", linewidths=0.5, zorder=6)
    hits = np.concatenate(trace.collisions) if trace.collisions else np.zeros((0, 2))
    ax.scatter(hits[:, 0], hits[:, 1], s=55, marker="x", c=CRASH_COLOR, linewidths=2.0, zorder=7)
    pts = np.concatenate([pos.reshape(-1, 2), layout.targets[:, :2], layout.obstacles[:, :2].reshape(-1, 2)])
    lo, hi = pts.min(0) - 4.0, pts.max(0) + 4.0
    span = float((hi - lo).max())
    mid = (lo + hi) / 2
    ax.set_xlim(mid[0] - span / 2, mid[0] + span / 2)
    ax.set_ylim(mid[1] - span / 2, mid[1] + span / 2)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    handles = [
        Line2D([], [], color=colors[0], lw=1.4, label="path"),
        Line2D([], [], ls="--", color="k", lw=1.0, label="start"),
        Line2D([], [], ls="none", marker="s", ms=7, mfc="#999999", mec="k", alpha=0.6, label="target"),
        Line2D([], [], ls="none", marker="o", ms=6, mfc=ARRIVAL_COLOR, mec="k", label=f"success to goal ({int(done.sum())})"),
        Line2D([], [], ls="none", marker="x", ms=7, mec=CRASH_COLOR, mew=2.0, label=f"collision ({len(hits)})"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=3, fontsize=8, frameon=False)
    ax.set_title(title or f"arena: {n} vehicles, {len(layout.obstacles)} obstacles, {sim.t} steps", fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    return path
