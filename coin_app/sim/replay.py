"""Episode replays as one self-contained HTML page that a person can scrub in a browser.

:func:`write_replay` turns an :class:`~coin_app.sim.rendering.EpisodeTrace` and the scene it
was driven in (a :class:`~coin_app.sim.road_map.RoadMap`, or a :class:`ReplayScene` such as the
arena's, ``coin_app.sim.arena.replay``) into a single HTML file: the page's script and style
and the episode's data are all inline (no network, no server). The page draws the map the
way ``rendering.draw_map`` does (sidewalks, lane polygons, solid lines; obstacles, goals and
starts for the arena), the vehicles of the current step as oriented boxes in their id colour,
and arrival / crash / off-road markers where and from when they happened. It has play/pause, a
step slider with the events marked on it, a speed control, ids on hover, zoom (wheel) and pan
(drag), and a click on a vehicle (or an event in the side panel) selects it: its whole path is
drawn and the side panel shows its outcome (arrived / crashed / off-road / timed out / still
driving).

The data is one JSON object (:func:`replay_data`, read back by :func:`read_replay`) embedded in
a ``<script type="application/json" id="replay-data">`` element. Lengths are integers in
``unit`` metres (cm), headings integers in milliradians, and each recorded step is five
parallel arrays ``[agent numbers, x, y, heading, status]``, which keeps a 1000-step episode of
30 vehicles below 1 MB.

The page reads ``#step=K`` (an env step) and ``#select=N`` (an agent number) from its URL
hash and writes its state (current step, the world-to-pixel transform, each drawn vehicle's
pixel position, any JS errors) as JSON into ``<script type="application/json"
id="replay-state">``, so a headless browser can check it (``tests/test_replay.py``).
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.sim.rendering import (
    AGENT_COLORS,
    ARRIVAL_COLOR,
    BACKGROUND,
    CRASH_COLOR,
    DYING_EDGE,
    DYING_FACE,
    LANE_EDGE,
    LANE_FACE,
    MAP_MARGIN,
    OFF_ROAD_COLOR,
    SIDEWALK_FACE,
    SOLID_LINE,
    VEHICLE_LENGTH,
    VEHICLE_WIDTH,
    EpisodeTrace,
)
from coin_app.sim.road_map import RoadMap

FORMAT = "coin_app.replay/1"
UNIT = 0.01  # m per integer length unit in the embedded data
ANGLE_UNIT = 0.001  # rad per integer heading unit
PAGE = Path(__file__).with_name("replay_page.html")
DATA_OPEN = '<script type="application/json" id="replay-data">'
OUTCOME_LABELS = {"arrived": "arrived", "crashed": "crashed", "out_of_road": "off-road", "timeout": "timed out", None: "still driving"}


@dataclass(frozen=True)
class ReplayScene:
    """What a replay draws under the vehicles, in world metres (x right, y up).

    ``bounds`` (x0, y0, x1, y1) is the region the initial view fits (a margin is added by
    the page's caller, :func:`replay_data`). ``lanes`` and ``sidewalks`` are polygons (k, 2),
    ``solid_lines`` segments (s, 2, 2), ``obstacles`` circles (m, 3) as (x, y, radius),
    ``goals`` and ``starts`` vehicle poses (n, 4) as (agent number, x, y, heading).
    ``crash_ends_run``: a crash ends the vehicle's run (the road sim) or is only an event
    it drives on after (the arena's collisions).
    """

    name: str
    bounds: tuple[float, float, float, float]
    lanes: Sequence[np.ndarray] = ()
    sidewalks: Sequence[np.ndarray] = ()
    solid_lines: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    obstacles: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    goals: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    starts: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))
    crash_ends_run: bool = True
    margin: float = MAP_MARGIN


def road_scene(road_map: RoadMap) -> ReplayScene:
    """The scene of a road map: its sidewalks, lane polygons and solid lines, as ``rendering.draw_map`` draws them."""
    solid = np.stack([road_map.solid_p1, road_map.solid_p2], 1) if len(road_map.solid_p1) else np.zeros((0, 2, 2))
    sidewalks = [_dedupe(p) for p in road_map.sidewalks]  # padded with repeats of the last vertex
    x0, y0, x1, y1 = (float(b) for b in road_map.bounds)
    return ReplayScene(road_map.name, (x0, y0, x1, y1), list(road_map.polygons), sidewalks, solid)


def _dedupe(poly: np.ndarray) -> np.ndarray:
    """The polygon without consecutive repeated vertices."""
    poly = np.asarray(poly, dtype=float)
    keep = np.ones(len(poly), bool)
    keep[1:] = np.any(np.diff(poly, axis=0) != 0, axis=1)
    return poly[keep]


def _ints(a: Any, unit: float = UNIT) -> list[int]:
    """A flat list of ``a / unit`` rounded to integers."""
    return np.rint(np.asarray(a, dtype=float).reshape(-1) / unit).astype(np.int64).tolist()


def _angles(a: Any) -> list[int]:
    """Headings wrapped to [-pi, pi) in integer milliradians."""
    a = np.asarray(a, dtype=float).reshape(-1)
    return _ints((a + np.pi) % (2 * np.pi) - np.pi, ANGLE_UNIT)


def _hex(rgb: Sequence[float]) -> str:
    return "#" + "".join(f"{int(round(float(c) * 255)):02x}" for c in rgb[:3])


def _vehicle_summaries(trace: EpisodeTrace, crash_ends_run: bool) -> dict[str, dict[str, Any]]:
    """Per agent number: first and last recorded env step, outcome (kind, label, env step) and collision count."""
    seen: dict[int, list[int]] = {}
    for step, nums in zip(trace.env_steps, trace.agent_num):
        for n in np.asarray(nums).tolist():
            span = seen.setdefault(int(n), [step, step])
            span[1] = step
    ends = ("arrived", "crashed", "out_of_road", "timeout") if crash_ends_run else ("arrived", "out_of_road", "timeout")
    out: dict[str, dict[str, Any]] = {}
    for n, (first, last) in sorted(seen.items()):
        mine = [e for e in trace.events if e.agent_num == n]
        end = next((e for e in mine if e.kind in ends), None)
        collisions = sum(e.kind == "crashed" for e in mine)
        label = OUTCOME_LABELS[end.kind if end else None]
        if collisions and not (crash_ends_run and end is not None and end.kind == "crashed"):
            label += f" ({collisions} collision{'s' if collisions > 1 else ''})"
        out[str(n)] = {
            "outcome": end.kind if end else "driving",
            "label": label,
            "step": end.env_step if end else None,
            "first": first,
            "last": last,
            "collisions": collisions,
        }
    return out


def replay_data(
    trace: EpisodeTrace,
    scene: RoadMap | ReplayScene,
    *,
    title: str | None = None,
    fps: float = 10.0,
    vehicle_size: tuple[float, float] | None = None,
) -> dict[str, Any]:
    """The JSON-ready data a replay page embeds (format in the module doc); the trace must have at least one step.

    ``vehicle_size`` (length, width) in m defaults to the trace's (set by ``EpisodeTrace.record``)
    or the MetaDrive car's. ``fps`` is the playback rate at speed 1.
    """
    if len(trace) == 0:
        raise ValueError("cannot replay an empty trace (record at least the reset)")
    if not fps > 0:
        raise ValueError(f"fps must be > 0, got {fps!r}")
    if isinstance(scene, RoadMap):
        scene = road_scene(scene)
    length, width = vehicle_size or trace.vehicle_size or (VEHICLE_LENGTH, VEHICLE_WIDTH)
    frames = [
        [np.asarray(n, dtype=np.int64).tolist(), _ints(p[:, 0]), _ints(p[:, 1]), _angles(h), np.asarray(s, dtype=np.int64).tolist()]
        for n, p, h, s in zip(trace.agent_num, trace.pos, trace.heading, trace.status)
    ]
    steps = list(map(int, trace.env_steps))
    frame_of = {}
    for i, s in enumerate(steps):
        frame_of.setdefault(s, i)
    events = [
        {
            "id": e.agent_num,
            "kind": e.kind,
            "x": _ints(e.x)[0],
            "y": _ints(e.y)[0],
            "step": e.env_step,
            "frame": frame_of.get(e.env_step, 0),
        }
        for e in trace.events
    ]
    vehicles = _vehicle_summaries(trace, scene.crash_ends_run)
    counts = {k: sum(e["kind"] == k for e in events) for k in ("arrived", "crashed", "out_of_road", "timeout")}
    if title is None:
        title = (
            f"{trace.scenario or scene.name}: {len(vehicles)} vehicles, {counts['arrived']} arrived, {counts['crashed']} crashed, "
            f"{counts['out_of_road']} off road ({steps[-1]} steps)"
        )
    x0, y0, x1, y1 = scene.bounds
    m = scene.margin
    return {
        "format": FORMAT,
        "title": title,
        "scenario": trace.scenario or scene.name,
        "fps": float(fps),
        "unit": UNIT,
        "angle_unit": ANGLE_UNIT,
        "vehicle": [round(float(length), 3), round(float(width), 3)],
        "view": _ints([x0 - m, y0 - m, x1 + m, y1 + m]),
        "map": {
            "lanes": [_ints(p) for p in scene.lanes],
            "sidewalks": [_ints(p) for p in scene.sidewalks],
            "solid": _ints(scene.solid_lines),
            "obstacles": _ints(scene.obstacles),
            "goals": [[int(g[0]), *_ints(g[1:3]), *_angles(g[3])] for g in np.asarray(scene.goals).reshape(-1, 4)],
            "starts": [[int(g[0]), *_ints(g[1:3]), *_angles(g[3])] for g in np.asarray(scene.starts).reshape(-1, 4)],
        },
        "crash_ends_run": scene.crash_ends_run,
        "steps": steps,
        "frames": frames,
        "events": events,
        "vehicles": vehicles,
        "colors": [_hex(c) for c in AGENT_COLORS],
        "style": {
            "background": BACKGROUND,
            "lane_face": LANE_FACE,
            "lane_edge": LANE_EDGE,
            "sidewalk": SIDEWALK_FACE,
            "solid": SOLID_LINE,
            "dying_face": DYING_FACE,
            "dying_edge": DYING_EDGE,
            "arrived": ARRIVAL_COLOR,
            "crashed": CRASH_COLOR,
            "out_of_road": OFF_ROAD_COLOR,
            "timeout": "#7f7f7f",
            "obstacle_face": "#7f7f7f",
            "obstacle_edge": "#404040",
        },
    }


def replay_html(data: dict[str, Any]) -> str:
    """The self-contained page of :func:`replay_data`'s ``data`` (the page template with the data inlined)."""
    page = PAGE.read_text(encoding="utf-8")
    # "</" inside a script element would end it early; "<\/" is the same JSON string
    payload = json.dumps(data, separators=(",", ":"), ensure_ascii=True).replace("</", "<\\/")
    page = page.replace("__REPLAY_TITLE__", html.escape(str(data.get("title", "replay"))))
    head, tail = page.split(DATA_OPEN + "null", 1)
    return head + DATA_OPEN + payload + tail


def write_replay(
    trace: EpisodeTrace,
    road_map: RoadMap | ReplayScene,
    path: str | Path,
    *,
    title: str | None = None,
    fps: float = 10.0,
    vehicle_size: tuple[float, float] | None = None,
) -> Path:
    """Write the episode ``trace`` on ``road_map`` (or any :class:`ReplayScene`) as one self-contained HTML replay; returns the path.

    The file needs no network or server: open it in any browser. ``title`` defaults to a summary
    (scenario, vehicles, arrivals, crashes, off-road, steps); ``fps`` is the playback rate at
    speed 1 (10 = real time at the sim's 0.1 s step). Raises ``ValueError`` on an empty trace.
    """
    data = replay_data(trace, road_map, title=title, fps=fps, vehicle_size=vehicle_size)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(f".{path.name}.partial-{os.getpid()}")  # whole or not at all: a sibling renamed over it
    try:
        partial.write_text(replay_html(data), encoding="utf-8")
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def read_replay(source: str | Path) -> dict[str, Any]:
    """The data embedded in a replay page (a path, or the page's HTML text); inverse of :func:`replay_html`."""
    text = str(source)
    if DATA_OPEN not in text:
        text = Path(source).read_text(encoding="utf-8")
    start = text.index(DATA_OPEN) + len(DATA_OPEN)
    return json.loads(text[start : text.index("</script>", start)])  # JSON reads the escaped "<\\/" as "</"


def frame_positions(data: dict[str, Any], frame: int) -> dict[int, np.ndarray]:
    """World positions (x, y) in m of each vehicle of one recorded step of replay ``data``."""
    nums, xs, ys = data["frames"][frame][:3]
    unit = data["unit"]
    return {int(n): np.array([x * unit, y * unit]) for n, x, y in zip(nums, xs, ys)}
