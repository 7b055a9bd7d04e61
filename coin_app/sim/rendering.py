"""Top-down rendering of the native scenarios: RGB frames, GIFs and trajectory plots.

Only matplotlib's object-oriented Agg API is used (``Figure`` + ``FigureCanvasAgg``), so
nothing needs a display and pyplot's global backend is left alone. The static map layer
(lane polygons, solid lines, sidewalks) of each (map, frame size) is drawn once into a
cached figure; each frame restores that background and draws only the vehicles (one
``PolyCollection`` of boxes and one of heading markers), which takes a few milliseconds.

World coordinates are drawn as is: x to the right, y up, equal scale on both axes.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import LineCollection, PolyCollection
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from PIL import Image

from coin_app.sim.road_map import RoadMap
from coin_app.sim.simulator import ACTIVE, DYING, EMPTY

VEHICLE_LENGTH = 4.515  # m, used when the env gives no vehicle size
VEHICLE_WIDTH = 1.852
MAP_MARGIN = 3.0  # m of empty border around the map bounds

BACKGROUND = "#f3f4ee"
LANE_FACE = "#d4d4d4"
LANE_EDGE = "#c2c2c2"
SIDEWALK_FACE = "#c9b99b"
SOLID_LINE = "#505050"
DYING_FACE = "#d62728"
DYING_EDGE = "#6e6e6e"
ARRIVAL_COLOR = "#2ca02c"
CRASH_COLOR = "#e8000b"
OFF_ROAD_COLOR = "#ff8c00"

# tab20 without its reds (6, 7) and greys (14, 15): red and grey mean "dying"
AGENT_COLORS = np.array(colormaps["tab20"].colors)[[i for i in range(20) if i not in (6, 7, 14, 15)]]


def agent_colors(agent_num: np.ndarray) -> np.ndarray:
    """RGB colour (n, 3) of each agent number; ids never map to red or grey."""
    return AGENT_COLORS[np.asarray(agent_num, dtype=np.int64) % len(AGENT_COLORS)]


def vehicle_corners(pos: np.ndarray, heading: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Corners (n, 4, 2) of oriented boxes with half length/width ``half`` (2,), counter-clockwise."""
    local = np.array([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]]) * np.asarray(half, dtype=float)
    return _place(local, pos, heading)


def heading_markers(pos: np.ndarray, heading: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Triangles (n, 3, 2) inside each box's front part, pointing in the driving direction."""
    hl, hw = float(half[0]), float(half[1])
    local = np.array([[hl - 0.15, 0.0], [hl - 0.15 - min(1.8, hl), 0.7 * hw], [hl - 0.15 - min(1.8, hl), -0.7 * hw]])
    return _place(local, pos, heading)


def _place(local: np.ndarray, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Rotate the body-frame points ``local`` (k, 2) by each heading and move them to each position."""
    pos = np.asarray(pos, dtype=float).reshape(-1, 2)
    c, s = np.cos(heading)[:, None], np.sin(heading)[:, None]
    x = c * local[None, :, 0] - s * local[None, :, 1] + pos[:, 0:1]
    y = s * local[None, :, 0] + c * local[None, :, 1] + pos[:, 1:2]
    return np.stack([x, y], -1)


def draw_map(ax: Any, road_map: RoadMap) -> None:
    """Draw the static road layer (sidewalks, lanes, solid lines) of ``road_map`` on a matplotlib axes."""
    ax.add_collection(PolyCollection(list(road_map.sidewalks), facecolors=SIDEWALK_FACE, edgecolors="none", zorder=1))
    ax.add_collection(PolyCollection(road_map.polygons, facecolors=LANE_FACE, edgecolors=LANE_EDGE, linewidths=0.4, zorder=2))
    if len(road_map.solid_p1):
        segs = np.stack([road_map.solid_p1, road_map.solid_p2], 1)
        ax.add_collection(LineCollection(segs, colors=SOLID_LINE, linewidths=0.9, zorder=3))


def _view_limits(bounds: np.ndarray, aspect: float, margin: float = MAP_MARGIN) -> tuple[tuple[float, float], tuple[float, float]]:
    """x and y limits covering ``bounds`` with a margin, widened so that one metre is as wide as high."""
    x0, y0, x1, y1 = (float(b) for b in bounds)
    x0, y0, x1, y1 = x0 - margin, y0 - margin, x1 + margin, y1 + margin
    w, h = x1 - x0, y1 - y0
    if w / h < aspect:
        pad = (h * aspect - w) / 2
        x0, x1 = x0 - pad, x1 + pad
    else:
        pad = (w / aspect - h) / 2
        y0, y1 = y0 - pad, y1 + pad
    return (x0, x1), (y0, y1)


class _FrameCanvas:
    """One reusable Agg figure of a map at a fixed pixel size, with the map layer pre-drawn."""

    DPI = 100

    def __init__(self, road_map: RoadMap, size: tuple[int, int]):
        w, h = size
        self.size = (w, h)
        self.fig = Figure(figsize=(w / self.DPI, h / self.DPI), dpi=self.DPI, facecolor=BACKGROUND)
        self.canvas = FigureCanvasAgg(self.fig)
        ax = self.ax = self.fig.add_axes((0.0, 0.0, 1.0, 1.0))
        ax.set_axis_off()
        draw_map(ax, road_map)
        xlim, ylim = _view_limits(road_map.bounds, w / h)
        ax.set_xlim(*xlim)
        ax.set_ylim(*ylim)
        self.bodies = PolyCollection([], linewidths=0.6, zorder=4, animated=True)
        self.noses = PolyCollection([], facecolors=(0.0, 0.0, 0.0, 0.55), edgecolors="none", zorder=5, animated=True)
        ax.add_collection(self.bodies)
        ax.add_collection(self.noses)
        self.label = ax.text(0.01, 0.99, "", transform=ax.transAxes, ha="left", va="top", fontsize=9, zorder=6, animated=True)
        self.canvas.draw()
        self.background = self.canvas.copy_from_bbox(self.fig.bbox)
        self.static = self._pixels()

    def _pixels(self) -> np.ndarray:
        return np.asarray(self.canvas.buffer_rgba())[..., :3].copy()

    def render(self, bodies: np.ndarray, noses: np.ndarray, face: np.ndarray, edge: np.ndarray, label: str) -> np.ndarray:
        """Draw the given vehicle polygons and label over the cached map; return (H, W, 3) uint8."""
        self.canvas.restore_region(self.background)
        self.bodies.set_verts(bodies)
        self.bodies.set_facecolors(face)
        self.bodies.set_edgecolors(edge)
        self.noses.set_verts(noses)
        self.label.set_text(label)
        for artist in (self.bodies, self.noses, self.label):
            self.ax.draw_artist(artist)
        return self._pixels()


_CANVASES: dict[tuple[str, int, int], _FrameCanvas] = {}


def _canvas(road_map: RoadMap, size: tuple[int, int]) -> _FrameCanvas:
    """The cached frame canvas of a map and pixel size (created on first use)."""
    w, h = (int(v) for v in size)
    if w < 16 or h < 16:
        raise ValueError(f"frame size must be at least 16 x 16 pixels, got {size!r}")
    key = (road_map.name, w, h)
    if key not in _CANVASES:
        _CANVASES[key] = _FrameCanvas(road_map, (w, h))
    return _CANVASES[key]


def _simulator(env: Any) -> Any:
    """The simulator behind ``env`` (a ``DrivingEnv``, anything with ``.sim``, or a simulator)."""
    sim = getattr(env, "sim", env)
    if not all(hasattr(sim, a) for a in ("status", "pos", "heading", "agent_num", "map")):
        raise TypeError(f"cannot render {type(env).__name__}: need a native DrivingEnv or DrivingSimulator")
    return sim


def _env_view(sim: Any, env_index: int) -> tuple[np.ndarray, int]:
    """Slot rows and current env step of one env of a (possibly batched) simulator."""
    if hasattr(sim, "env_slots"):
        num_envs = int(getattr(sim, "num_envs", 1))
        if not 0 <= env_index < num_envs:
            raise ValueError(f"bad env_index {env_index!r}; allowed: 0 .. {num_envs - 1}")
        rows = np.asarray(sim.env_slots(env_index))
    else:
        rows = np.arange(len(sim.status))
    steps = getattr(sim, "env_step", None)
    if isinstance(steps, np.ndarray) and steps.ndim == 1:
        step = int(steps[env_index])
    else:
        step = int(getattr(sim, "episode_step", 0))
    return rows, step


def _half(sim: Any) -> np.ndarray:
    return np.asarray(getattr(sim, "half", (VEHICLE_LENGTH / 2, VEHICLE_WIDTH / 2)), dtype=float)


def render_map(road_map: RoadMap, size: tuple[int, int] = (480, 480)) -> np.ndarray:
    """The static map layer alone as an (H, W, 3) uint8 image; ``size`` is (width, height) in pixels."""
    return _canvas(road_map, size).static.copy()


def render_frame(env: Any, size: tuple[int, int] = (480, 480), env_index: int = 0) -> np.ndarray:
    """Top-down RGB image (H, W, 3) uint8 of the env's current state; ``size`` is (width, height) in pixels.

    Every non-empty vehicle is an oriented box with a dark triangle at its front: active
    vehicles in a colour fixed by their agent id, dying ones (crashed / off road, left as
    obstacles) red with a grey edge. ``env_index`` picks one env of a batched simulator.
    """
    sim = _simulator(env)
    canvas = _canvas(sim.map, size)
    rows, step = _env_view(sim, env_index)
    status = sim.status[rows]
    live = rows[status != EMPTY]
    pos, hd, half = sim.pos[live], sim.heading[live], _half(sim)
    dying = sim.status[live] == DYING
    face = np.ones((len(live), 4))
    face[:, :3] = agent_colors(sim.agent_num[live])
    face[dying] = (*_rgb(DYING_FACE), 0.85)
    edge = np.zeros((len(live), 4))
    edge[:, 3] = 1.0
    edge[dying] = (*_rgb(DYING_EDGE), 1.0)
    label = f"{sim.map.name}  step {step}  active {int((status == ACTIVE).sum())}  dying {int(dying.sum())}"
    return canvas.render(vehicle_corners(pos, hd, half), heading_markers(pos, hd, half), face, edge, label)


def _rgb(color: str) -> tuple[float, float, float]:
    c = color.lstrip("#")
    return tuple(int(c[i : i + 2], 16) / 255 for i in (0, 2, 4))  # type: ignore[return-value]


# ---------------------------------------------------------------------------- episode traces
_ID_NUM = re.compile(r"(\d+)$")


def agent_number(agent_id: str | int) -> int:
    """The integer number of an agent id such as ``"agent12"`` (ints pass through)."""
    if isinstance(agent_id, (int, np.integer)):
        return int(agent_id)
    m = _ID_NUM.search(str(agent_id))
    if m is None:
        raise ValueError(f"agent id {agent_id!r} does not end in a number")
    return int(m.group(1))


@dataclass
class OutcomeEvent:
    """Where and when a vehicle arrived, crashed, left the road or timed out."""

    agent_num: int
    kind: str  # "arrived" | "crashed" | "out_of_road" | "timeout"
    x: float
    y: float
    env_step: int


_EVENT_FLAGS = (("arrive_dest", "arrived"), ("crash_vehicle", "crashed"), ("out_of_road", "out_of_road"), ("max_step", "timeout"))


@dataclass
class EpisodeTrace:
    """Per-step vehicle poses, statuses and outcome events of one episode, for plots and replays."""

    scenario: str = ""
    env_steps: list[int] = field(default_factory=list)
    agent_num: list[np.ndarray] = field(default_factory=list)  # per step (n,) int
    pos: list[np.ndarray] = field(default_factory=list)  # per step (n, 2)
    heading: list[np.ndarray] = field(default_factory=list)  # per step (n,)
    status: list[np.ndarray] = field(default_factory=list)  # per step (n,) EMPTY/ACTIVE/DYING
    events: list[OutcomeEvent] = field(default_factory=list)
    vehicle_size: tuple[float, float] | None = None  # (length, width) in m; record() takes it from the simulator

    def record(self, env: Any, infos: Mapping[str, Mapping[str, Any]] | None = None, env_index: int = 0) -> None:
        """Record the env's vehicles after ``reset``/``step`` and the outcomes flagged in that call's ``infos``.

        A vehicle that finished in this step is recorded at its final pose even if its
        slot is already empty (arrived vehicles vanish at once). ``env_index`` picks one
        env of a batched simulator.
        """
        sim = _simulator(env)
        if not self.scenario:
            self.scenario = sim.map.name
        if self.vehicle_size is None:
            half = _half(sim)
            self.vehicle_size = (2 * float(half[0]), 2 * float(half[1]))
        rows, step = _env_view(sim, env_index)
        flags = _flag_table(infos)
        finished = np.array([n for n, _ in flags], dtype=np.int64)
        sel = rows[(sim.status[rows] != EMPTY) | np.isin(sim.agent_num[rows], finished)]
        self.add(step, sim.agent_num[sel], sim.pos[sel], sim.heading[sel], sim.status[sel], flags)

    def add(
        self,
        env_step: int,
        agent_num: np.ndarray,
        pos: np.ndarray,
        heading: np.ndarray,
        status: np.ndarray,
        outcomes: Iterable[tuple[int, str]] = (),
    ) -> None:
        """Append one step of poses and outcome events given as (agent number, kind); backend-agnostic."""
        agent_num = np.asarray(agent_num, dtype=np.int64).copy()
        pos = np.asarray(pos, dtype=float).reshape(-1, 2).copy()
        self.env_steps.append(int(env_step))
        self.agent_num.append(agent_num)
        self.pos.append(pos)
        self.heading.append(np.asarray(heading, dtype=float).copy())
        self.status.append(np.asarray(status, dtype=np.int8).copy())
        for num, kind in outcomes:
            where = np.nonzero(agent_num == num)[0]
            if len(where):
                x, y = pos[where[0]]
                self.events.append(OutcomeEvent(int(num), kind, float(x), float(y), int(env_step)))

    def __len__(self) -> int:
        return len(self.env_steps)

    def trajectories(self) -> dict[int, np.ndarray]:
        """Each vehicle's path as an (k, 2) array of its recorded positions in time order."""
        if not self.env_steps:
            return {}
        nums = np.concatenate(self.agent_num)
        pts = np.concatenate(self.pos)
        order = np.argsort(nums, kind="stable")  # steps are appended in time order
        nums, pts = nums[order], pts[order]
        cuts = np.nonzero(np.diff(nums))[0] + 1
        return {int(g[0]): p for g, p in zip(np.split(nums, cuts), np.split(pts, cuts)) if len(g)}

    def events_of(self, kind: str) -> np.ndarray:
        """Positions (k, 2) of all events of one kind."""
        xy = [(e.x, e.y) for e in self.events if e.kind == kind]
        return np.array(xy, dtype=float).reshape(-1, 2)


def _flag_table(infos: Mapping[str, Mapping[str, Any]] | None) -> list[tuple[int, str]]:
    """(agent number, kind) of every outcome flag set in a step's infos."""
    out: list[tuple[int, str]] = []
    for aid, info in (infos or {}).items():
        if aid == "__all__":
            continue
        for key, kind in _EVENT_FLAGS:
            if info.get(key, False):
                out.append((agent_number(aid), kind))
    return out


# ---------------------------------------------------------------------------- outputs
def write_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 10) -> Path:
    """Write RGB frames (H, W, 3) uint8 as a looping GIF; returns the path.

    All frames share one 255-colour palette fitted to up to 16 evenly spaced frames (no
    dithering), which is several times faster than a palette per frame. Pillow merges a
    frame identical to the previous one into it (adding its duration).
    """

    if len(frames) == 0:
        raise ValueError("write_gif needs at least one frame")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    arrays = [np.ascontiguousarray(f, dtype=np.uint8) for f in frames]
    shapes = {a.shape for a in arrays}
    if len(shapes) != 1 or len(arrays[0].shape) != 3 or arrays[0].shape[2] != 3:
        raise ValueError(f"frames must all be (H, W, 3) uint8 arrays of one shape, got shapes {sorted(shapes)}")
    sample = arrays[:: max(1, len(arrays) // 16)][:16]
    palette = Image.fromarray(np.concatenate(sample, 0)).quantize(255, method=Image.Quantize.FASTOCTREE, dither=Image.Dither.NONE)
    images = [Image.fromarray(a).quantize(palette=palette, dither=Image.Dither.NONE) for a in arrays]
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    images[0].save(path, save_all=True, append_images=images[1:], duration=max(int(round(1000 / fps)), 10), loop=0)
    return path


def plot_trajectories(
    trace: EpisodeTrace,
    road_map: RoadMap,
    path: str | Path,
    title: str | None = None,
    width: float = 8.0,
    dpi: int = 120,
) -> Path:
    """Save a PNG of every vehicle's path over the map with arrivals, crashes and off-road points marked.

    The figure is ``width`` inches wide and as high as the map's aspect ratio needs.
    """
    x0, y0, x1, y1 = (float(b) for b in road_map.bounds)
    xlim, ylim = (x0 - MAP_MARGIN, x1 + MAP_MARGIN), (y0 - MAP_MARGIN, y1 + MAP_MARGIN)
    map_aspect = (ylim[1] - ylim[0]) / (xlim[1] - xlim[0])
    fig = Figure(figsize=(width, (width - 0.7) * map_aspect + 1.1), dpi=dpi, facecolor="white", layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    ax.set_facecolor(BACKGROUND)
    draw_map(ax, road_map)
    trajs = trace.trajectories()
    if trajs:
        nums = np.fromiter(trajs, dtype=np.int64)
        colors = agent_colors(nums)
        ax.add_collection(LineCollection(list(trajs.values()), colors=colors, linewidths=1.3, alpha=0.9, zorder=4))
        # a hollow circle at each spawn point keeps a vehicle that never moved visible
        starts = np.array([p[0] for p in trajs.values()])
        ax.scatter(starts[:, 0], starts[:, 1], s=14, marker="o", facecolors="none", edgecolors=colors, linewidths=1.0, zorder=5)
    arr, crash, oor = trace.events_of("arrived"), trace.events_of("crashed"), trace.events_of("out_of_road")
    ax.scatter(arr[:, 0], arr[:, 1], s=34, marker="o", c=ARRIVAL_COLOR, edgecolors="k", linewidths=0.5, zorder=6)
    ax.scatter(oor[:, 0], oor[:, 1], s=48, marker="^", c=OFF_ROAD_COLOR, edgecolors="k", linewidths=0.5, zorder=6)
    ax.scatter(crash[:, 0], crash[:, 1], s=60, marker="x", c=CRASH_COLOR, linewidths=2.0, zorder=7)
    handles = [
        Line2D(
            [],
            [],
            color=AGENT_COLORS[0],
            lw=1.3,
            marker="o",
            ms=4,
            mfc="none",
            markevery=[0],
            label=f"trajectory from spawn ({len(trajs)} vehicles)",
        ),
        Line2D([], [], ls="none", marker="o", ms=6, mfc=ARRIVAL_COLOR, mec="k", mew=0.5, label=f"arrival ({len(arr)})"),
        Line2D([], [], ls="none", marker="x", ms=7, mec=CRASH_COLOR, mew=2.0, label=f"crash ({len(crash)})"),
        Line2D([], [], ls="none", marker="^", ms=7, mfc=OFF_ROAD_COLOR, mec="k", mew=0.5, label=f"out of road ({len(oor)})"),
    ]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles), fontsize=8, frameon=False)
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_aspect("equal", adjustable="box")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    if title is None:
        steps = trace.env_steps[-1] if trace.env_steps else 0
        counts = f"{len(trajs)} vehicles, {len(arr)} arrived, {len(crash)} crashed, {len(oor)} out of road"
        title = f"{trace.scenario or road_map.name}: {counts} ({steps} steps)"
    ax.set_title(title, fontsize=10)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi, bbox_inches="tight", pad_inches=0.1)
    return path
