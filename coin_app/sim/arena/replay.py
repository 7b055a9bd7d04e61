"""HTML replays of arena episodes: the adapter from an :class:`ArenaTrace` to the replay writer (``coin_app/sim/replay.py``).

An arena episode becomes an :class:`~coin_app.sim.rendering.EpisodeTrace` (vehicle ``i`` is agent
number ``i``; driving vehicles are ACTIVE, parked or timed-out ones EMPTY, drawn as done) with
these events: ``crashed`` at each step a vehicle started a collision event (collisions do not
end a run in the arena, so its outcome stays open), ``arrived`` when it reaches the success
state, ``timeout`` when the step limit ends its run. The scene holds the obstacles, every
vehicle's goal (its parking spot, translucent in its colour) and start (dashed), in the region
``plot_arena_episode`` shows.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.sim.arena.rendering import ArenaTrace
from coin_app.sim.rendering import EpisodeTrace
from coin_app.sim.replay import ReplayScene, write_replay
from coin_app.sim.simulator import ACTIVE, EMPTY

ARENA_MARGIN = 4.0  # m around the paths, goals and obstacles (as plot_arena_episode)


def record_arena_episode(
    env: Any,
    policy: Callable[[np.ndarray], np.ndarray],
    *,
    seed: int | None = None,
    layout: Any = None,
    max_steps: int | None = None,
) -> ArenaTrace:
    """Run one episode of an ``ArenaEnv`` with a batch ``policy`` (observations (n, obs_dim) of the driving vehicles -> actions (n, 2)).

    The episode is the env's next generated scenario (``seed`` restarts the generator) or the
    given ``layout``; it runs until every vehicle is done or for ``max_steps`` steps. Returns its trace.
    """
    obs, _ = env.reset(seed=seed, options={"layout": layout} if layout is not None else None)
    trace = ArenaTrace()
    trace.start(env.sim)
    steps = 0
    while env.agents and (max_steps is None or steps < max_steps):
        actions = np.asarray(policy(np.stack([obs[a] for a in env.agents])))
        obs, _, _, _, _ = env.step(dict(zip(env.agents, actions)))
        trace.record(env.sim.last_new_collisions)
        steps += 1
    return trace


def arena_episode(trace: ArenaTrace) -> tuple[EpisodeTrace, ReplayScene]:
    """The replay's view of a recorded arena episode: its :class:`EpisodeTrace` and its :class:`ReplayScene` (module doc)."""
    if trace.sim is None or not trace.positions:
        raise ValueError("the arena trace is empty: call trace.start(sim) after the reset")
    if not len(trace.driving) == len(trace.succeeded) == len(trace.new_collisions) == len(trace.positions):
        raise ValueError("the arena trace lacks the per-step flags (record it with ArenaTrace.start / record)")
    sim, layout = trace.sim, trace.sim.layout
    n = len(layout.starts)
    nums = np.arange(n)
    out = EpisodeTrace(scenario="arena", vehicle_size=(float(sim.config.vehicle_length), float(sim.config.vehicle_width)))
    for t, (pos, heading, driving, done) in enumerate(zip(trace.positions, trace.headings, trace.driving, trace.succeeded)):
        events: list[tuple[int, str]] = []
        if t > 0:
            was_driving, was_done = trace.driving[t - 1], trace.succeeded[t - 1]
            events += [(int(i), "crashed") for i in np.nonzero(trace.new_collisions[t] > 0)[0]]
            events += [(int(i), "arrived") for i in np.nonzero(done & ~was_done)[0]]
            events += [(int(i), "timeout") for i in np.nonzero(was_driving & ~driving & ~done)[0]]
        out.add(t, nums, pos, heading, np.where(driving, ACTIVE, EMPTY), events)
    pts = np.concatenate([np.concatenate(trace.positions), layout.targets[:, :2], layout.starts[:, :2], layout.obstacles[:, :2]])
    lo, hi = pts.min(0) - ARENA_MARGIN, pts.max(0) + ARENA_MARGIN
    scene = ReplayScene(
        name="arena",
        bounds=(float(lo[0]), float(lo[1]), float(hi[0]), float(hi[1])),
        obstacles=np.asarray(layout.obstacles, dtype=float).reshape(-1, 3),
        goals=np.column_stack([nums, layout.targets[:, :3]]),
        starts=np.column_stack([nums, layout.starts[:, :3]]),
        crash_ends_run=False,
        margin=0.0,
    )
    return out, scene


def write_arena_replay(trace: ArenaTrace, path: str | Path, *, title: str | None = None, fps: float = 10.0) -> Path:
    """Write a recorded arena episode as one self-contained HTML replay (see ``coin_app.sim.replay``); returns the path.

    Obstacles, goals (parking spots) and starts are drawn under the vehicles; collisions,
    arrivals and timeouts are marked where and when they happened. ``title`` defaults to a
    summary; ``fps`` is the playback rate at speed 1 (10 = real time at the arena's 0.1 s step).
    """
    episode, scene = arena_episode(trace)
    if title is None:
        sim = trace.sim
        arrived = sum(e.kind == "arrived" for e in episode.events)
        collisions = int(sum(int(c.sum()) for c in trace.new_collisions))
        title = (
            f"arena: {sim.num_vehicles} vehicles, {len(sim.layout.obstacles)} obstacles, {len(trace.positions) - 1} steps: "
            f"{arrived} reached their goal, {collisions} collision events"
        )
    return write_replay(episode, scene, path, title=title, fps=fps)
