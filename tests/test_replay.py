"""HTML episode replays (coin_app/sim/replay.py): the embedded data, self-containment, size, and the page in headless Chromium.

The browser tests run Debian's ``chromium`` (``.ci/run`` installs it) with no Python driver:
``--dump-dom`` after the page's script has written its state (step, world-to-pixel transform,
vehicle pixel positions, JS errors) into ``#replay-state``, and ``--screenshot`` of the same
window size, read with PIL. They skip where Chromium is absent.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.heuristic import heuristic_actions
from coin_app.sim.arena.replay import arena_episode, record_arena_episode, write_arena_replay
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.rendering import ARRIVAL_COLOR, CRASH_COLOR, OFF_ROAD_COLOR, EpisodeTrace
from coin_app.sim.replay import frame_positions, read_replay, replay_data, replay_html, write_replay
from coin_app.sim.road_map import RoadMap
from coin_app.sim.rollout import DictEnvs, rollout

SCENARIO, NUM_AGENTS, SEED, STEPS = "intersection", 30, 0, 30  # the heuristic driver crashes two vehicles at step 13
WINDOW = (1200, 800)
MARKER_COLORS = {"crashed": CRASH_COLOR, "out_of_road": OFF_ROAD_COLOR, "arrived": ARRIVAL_COLOR}


@pytest.fixture(scope="module")
def episode():
    """A short real episode of the native simulator and the heuristic driver, recorded as ``cmd_demo`` does."""
    env = DrivingEnv(scenario=SCENARIO, num_agents=NUM_AGENTS)
    trace = EpisodeTrace()
    for step in rollout(DictEnvs([env]), HeuristicDriver(env), [SEED], STEPS):
        trace.record(env, step.results[0].infos)
    assert any(e.kind in MARKER_COLORS for e in trace.events), "the test episode should have a crash (or an arrival): pick another seed"
    return env, trace


@pytest.fixture(scope="module")
def page(episode, tmp_path_factory):
    env, trace = episode
    return write_replay(trace, env.sim.map, tmp_path_factory.mktemp("replay") / "episode.html", title="test <episode> & </script>")


def marked_event(trace):
    """The event whose marker the screenshot test looks for: the first crash, else the first off-road exit or arrival."""
    for kind in ("crashed", "out_of_road", "arrived"):
        for e in trace.events:
            if e.kind == kind:
                return e
    raise AssertionError("no marked event")


# ---------------------------------------------------------------------------- the data (no browser)
def test_embedded_data_round_trips(episode, page):
    env, trace = episode
    data = read_replay(page)
    assert data == read_replay(page.read_text())  # a path or the page's text
    assert data["title"] == "test <episode> & </script>"  # "</script>" in the data does not end the element early
    assert data["steps"] == trace.env_steps and len(data["frames"]) == len(trace)
    for frame in (0, len(trace) // 2, len(trace) - 1):
        got = frame_positions(data, frame)
        nums, xs, ys, hs, st = data["frames"][frame]
        assert nums == trace.agent_num[frame].tolist() and st == trace.status[frame].tolist()
        for k, num in enumerate(trace.agent_num[frame]):
            np.testing.assert_allclose(got[int(num)], trace.pos[frame][k], atol=0.0051)  # cm
        dh = np.asarray(hs) * data["angle_unit"] - trace.heading[frame]
        assert np.abs((dh + np.pi) % (2 * np.pi) - np.pi).max() < 6e-4  # mrad
    events = [(e["id"], e["kind"], e["step"]) for e in data["events"]]
    assert events == [(e.agent_num, e.kind, e.env_step) for e in trace.events]
    for got, e in zip(data["events"], trace.events):
        assert abs(got["x"] * data["unit"] - e.x) <= 0.0051 and abs(got["y"] * data["unit"] - e.y) <= 0.0051
        assert data["steps"][got["frame"]] == e.env_step
    crash = marked_event(trace)
    summary = data["vehicles"][str(crash.agent_num)]
    assert summary["outcome"] == crash.kind and summary["step"] == crash.env_step
    seen = {int(n) for nums in trace.agent_num for n in nums}
    assert {int(k) for k in data["vehicles"]} == seen
    ended = {e.agent_num for e in trace.events}
    assert all(data["vehicles"][str(n)]["label"] == "still driving" for n in seen - ended)
    # the road is the map's geometry
    road_map = env.sim.map
    assert len(data["map"]["lanes"]) == len(road_map.polygons) and len(data["map"]["solid"]) == 4 * len(road_map.solid_p1)
    np.testing.assert_allclose(np.reshape(data["map"]["lanes"][0], (-1, 2)) * data["unit"], road_map.polygons[0], atol=0.0051)
    assert data["vehicle"] == pytest.approx(list(trace.vehicle_size))


def test_page_is_self_contained(page):
    text = page.read_text()
    assert "http://" not in text and "https://" not in text
    assert not re.search(r"""\b(src|href)\s*=""", text, re.I)  # no external scripts, styles or images at all
    assert not re.search(r"<link\b|<iframe\b|@import|\bfetch\(|XMLHttpRequest", text, re.I)
    assert text.count('id="replay-data"') == 1 and text.isascii()


def test_size_of_a_long_episode_stays_small(tmp_path):
    """1000 steps of 30 vehicles (poses anywhere on a 300 m map) stay well under 3 MB."""
    rng = np.random.default_rng(0)
    trace = EpisodeTrace(scenario="intersection")
    pos = rng.uniform(-150, 150, (30, 2))
    for t in range(1000):
        pos = pos + rng.normal(0, 0.8, pos.shape)
        trace.add(t, np.arange(t // 40, t // 40 + 30), pos, rng.uniform(-np.pi, np.pi, 30), np.ones(30), [(t // 40, "arrived")])
    path = write_replay(trace, RoadMap("intersection"), tmp_path / "long.html")
    size = path.stat().st_size
    assert size < 1.5e6, f"{size / 1e6:.2f} MB"
    assert len(read_replay(path)["frames"]) == 1000


def test_bad_input_is_refused(tmp_path):
    with pytest.raises(ValueError, match="empty trace"):
        write_replay(EpisodeTrace(), RoadMap("intersection"), tmp_path / "x.html")
    trace = EpisodeTrace()
    trace.add(0, [1], [[0.0, 0.0]], [0.0], [1])
    with pytest.raises(ValueError, match="fps"):
        replay_data(trace, RoadMap("intersection"), fps=0)


@pytest.fixture(scope="module")
def arena(tmp_path_factory):
    env = ArenaEnv(num_vehicles=8, num_obstacles=6)
    trace = record_arena_episode(env, heuristic_actions, seed=2, max_steps=150)
    return trace, write_arena_replay(trace, tmp_path_factory.mktemp("arena") / "arena.html")


def test_arena_episode_data(arena):
    trace, path = arena
    data = read_replay(path)
    layout = trace.sim.layout
    np.testing.assert_allclose(np.reshape(data["map"]["obstacles"], (-1, 3)) * data["unit"], layout.obstacles, atol=0.0051)
    goals = np.array(data["map"]["goals"], dtype=float)
    assert goals[:, 0].tolist() == list(range(len(layout.targets)))
    np.testing.assert_allclose(goals[:, 1:3] * data["unit"], layout.targets[:, :2], atol=0.0051)
    assert data["crash_ends_run"] is False and data["map"]["lanes"] == []
    assert len(data["frames"]) == len(trace.positions) == 151
    collisions = [(e["id"], e["step"]) for e in data["events"] if e["kind"] == "crashed"]
    expected = [(int(i), t) for t, new in enumerate(trace.new_collisions) for i in np.nonzero(new)[0]]
    assert sorted(collisions) == sorted(expected) and collisions
    for n in range(trace.sim.num_vehicles):
        v = data["vehicles"][str(n)]
        assert v["outcome"] == ("arrived" if trace.sim.succeeded[n] else "driving" if trace.sim.driving[n] else "timeout")
    np.testing.assert_allclose(frame_positions(data, 150)[3], trace.positions[150][3], atol=0.0051)
    episode, scene = arena_episode(trace)
    assert len(episode) == 151 and scene.name == "arena"


# ---------------------------------------------------------------------------- the page in headless Chromium
CHROMIUM = shutil.which("chromium") or ("/usr/bin/chromium" if os.path.exists("/usr/bin/chromium") else None)
needs_chromium = pytest.mark.skipif(CHROMIUM is None, reason="chromium is not installed (apt-get install chromium): browser checks skipped")
STATE = re.compile(r'<script type="application/json" id="replay-state">(.*?)</script>', re.S)


def chromium(tmp_path: Path, page: Path, fragment: str, *args: str, window: tuple[int, int] = WINDOW) -> str:
    cmd = [
        CHROMIUM,
        "--headless",
        "--disable-gpu",
        "--no-sandbox",
        "--disable-dev-shm-usage",
        "--no-first-run",
        "--hide-scrollbars",
        "--force-device-scale-factor=1",
        f"--user-data-dir={tmp_path / 'chromium-profile'}",
        f"--window-size={window[0]},{window[1]}",
        *args,
        page.resolve().as_uri() + fragment,
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=180)
    assert done.returncode == 0, done.stderr[-2000:]
    return done.stdout


_DUMP_WINDOW: list[tuple[int, int]] = []


def page_state(tmp_path: Path, page: Path, fragment: str) -> tuple[dict, str]:
    """The state the page wrote into its DOM after loading at ``fragment``, and the whole dumped DOM.

    ``--screenshot`` sizes the viewport to ``--window-size`` but ``--dump-dom`` leaves room for
    window chrome, so the dump's window is made taller by that room (measured on the first call),
    and the page is laid out at the screenshot's viewport.
    """

    def dump(window: tuple[int, int]) -> tuple[dict, str]:
        dom = chromium(tmp_path, page, fragment, "--dump-dom", window=window)
        m = STATE.search(dom)
        assert m, dom[-2000:]
        return json.loads(m.group(1)), dom

    if not _DUMP_WINDOW:
        state, _ = dump(WINDOW)
        if state.get("viewport") is None:
            return state, _  # the page failed before writing its layout: let the caller's checks say why
        _DUMP_WINDOW.append((2 * WINDOW[0] - state["viewport"][0], 2 * WINDOW[1] - state["viewport"][1]))
    state, dom = dump(_DUMP_WINDOW[0])
    assert state.get("viewport") in (None, list(WINDOW)), state.get("viewport")
    return state, dom


def to_pixels(state: dict, xy: np.ndarray) -> np.ndarray:
    t = state["transform"]
    xy = np.asarray(xy, dtype=float).reshape(-1, 2)
    return np.stack([t["ox"] + xy[:, 0] * t["scale"], t["oy"] - xy[:, 1] * t["scale"]], 1)


@needs_chromium
def test_page_loads_and_steps_move_vehicles(episode, page, tmp_path):
    _, trace = episode
    a, b = 5, 12
    sa, _ = page_state(tmp_path, page, f"#step={a}")
    sb, _ = page_state(tmp_path, page, f"#step={b}")
    for state, step in ((sa, a), (sb, b)):
        assert state["ready"] and state["errors"] == [], state.get("errors")
        assert state["step"] == step and state["frame"] == trace.env_steps.index(step)
        nums = trace.agent_num[state["frame"]]
        assert sorted(int(k) for k in state["vehicles"]) == sorted(nums.tolist())
        got = np.array([state["vehicles"][str(n)] for n in nums])
        # the dumped pixel positions are the trace's positions through the page's own transform
        np.testing.assert_allclose(got, to_pixels(state, trace.pos[state["frame"]]), atol=0.1)
        left, top, width, height = state["canvas"]
        assert (
            (got[:, 0] > left).all() and (got[:, 0] < left + width).all() and (got[:, 1] > top).all() and (got[:, 1] < top + height).all()
        )
    assert sa["transform"] == sb["transform"]
    both = set(sa["vehicles"]) & set(sb["vehicles"])
    moved = [k for k in both if np.hypot(*np.subtract(sa["vehicles"][k], sb["vehicles"][k])) > 1.0]
    assert len(moved) >= len(both) // 2 > 0


@needs_chromium
def test_screenshot_shows_the_marker_where_and_when_it_happened(episode, page, tmp_path):
    _, trace = episode
    event = marked_event(trace)
    target = np.array([int(MARKER_COLORS[event.kind][i : i + 2], 16) for i in (1, 3, 5)])

    def marker_pixels(step: int) -> tuple[np.ndarray, np.ndarray]:
        state, _ = page_state(tmp_path, page, f"#step={step}")
        assert state["errors"] == []
        shot = tmp_path / f"step{step}.png"
        chromium(tmp_path, page, f"#step={step}", f"--screenshot={shot}")
        img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
        assert img.shape[:2] == (WINDOW[1], WINDOW[0])
        x, y = np.floor(to_pixels(state, [event.x, event.y])[0]).astype(int)
        patch = img[y - 1 : y + 2, x - 1 : x + 2].reshape(-1, 3)
        return np.abs(patch - target).max(1), img

    at, img = marker_pixels(event.env_step)
    assert at.min() <= 30, f"no {event.kind} marker colour at the event's pixel: {at}"
    assert img.std() > 10  # the map and the controls are drawn, not a blank page
    if event.env_step > trace.env_steps[0]:
        before, _ = marker_pixels(event.env_step - 1)
        assert before.min() > 30, "the marker shows before its step"


@needs_chromium
def test_selected_vehicle_shows_its_outcome(episode, page, tmp_path):
    _, trace = episode
    event = marked_event(trace)
    state, dom = page_state(tmp_path, page, f"#step={event.env_step}&select={event.agent_num}")
    assert state["errors"] == [] and state["selected"] == event.agent_num
    panel = re.search(r'<div id="vehicle-info">(.*?)</div>', dom, re.S).group(1)
    label = {"crashed": "crashed", "out_of_road": "off-road", "arrived": "arrived"}[event.kind]
    assert f"agent{event.agent_num}" in panel and label in panel and f"at step {event.env_step}" in panel


@needs_chromium
def test_js_errors_are_reported(episode, tmp_path):
    """The error capture works: a page whose script throws says so in its state (so "no errors" above means something)."""
    env, trace = episode
    html = replay_html(replay_data(trace, env.sim.map)).replace('"use strict";', '"use strict"; notAFunction();', 1)
    broken = tmp_path / "broken.html"
    broken.write_text(html)
    state, _ = page_state(tmp_path, broken, "#step=3")
    assert state["ready"] is False and any("notAFunction" in e for e in state["errors"])


@needs_chromium
def test_arena_page_loads(arena, tmp_path):
    trace, path = arena
    state, dom = page_state(tmp_path, path, "#step=100&select=1")
    assert state["ready"] and state["errors"] == [] and state["step"] == 100
    np.testing.assert_allclose(np.array([state["vehicles"][str(n)] for n in range(8)]), to_pixels(state, trace.positions[100]), atol=0.1)
    assert "obstacle" in dom and "goal (parking spot)" in dom


def test_writers_import_neither_ray_nor_torch():
    code = "import sys, coin_app.sim.replay, coin_app.sim.arena.replay; print(sorted(m for m in ('ray', 'torch') if m in sys.modules))"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=Path(__file__).parents[1])
    assert out.stdout.strip() == "[]"
