"""Dict-of-agents arena env (PettingZoo parallel semantics, like ``DrivingEnv``): the interface every adapter wraps.

``agents`` are the vehicles still driving. A vehicle that reaches the success state is
``terminated`` (it stays parked as an obstacle); at the step limit the others are
``truncated``. Scenarios come from the seeded generator (``reset(seed)``; successive resets
without a seed continue the stream) or are given: ``reset(options={"layout": layout})``
(the fixed test sets). Infos carry ``success``, ``collided`` (any collision so far),
``collisions`` (events so far), ``distance`` (m driven), ``target_distance``,
``heading_error`` and ``env_step``.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from coin_app.sim import schema
from coin_app.sim.arena.config import ArenaConfig, make_arena_config
from coin_app.sim.arena.generator import Layout, generate, training_rng
from coin_app.sim.arena.simulator import ArenaSimulator
from coin_app.sim.inputs import checked_actions


class ArenaEnv:
    """The navigation-and-parking arena with the dict-of-agents API (see module doc)."""

    def __init__(self, config: ArenaConfig | None = None, **overrides: Any):
        self.config = config if config is not None else make_arena_config(**overrides)
        self.sim = ArenaSimulator(self.config)
        self.possible_agents = [f"agent{i}" for i in range(self.config.vehicle_pool)]
        self.observation_space = gym.spaces.Box(-np.inf, np.inf, (self.config.obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (schema.ACT_DIM,), np.float32)  # (steering, pedal)
        self.agents: list[str] = []
        self.episode_over = True
        self._rng = training_rng(0)

    @property
    def scenario(self) -> str:
        """Name of the scenario."""
        return "arena"

    def set_start_difficulty(self, difficulty: float) -> None:
        """The ``start_difficulty`` of the scenarios generated from now on (a curriculum's step; see ``ArenaConfig``)."""
        self.config = make_arena_config(**{**vars(self.config), "start_difficulty": float(difficulty)})

    def draw_layout(self) -> Layout:
        """The next generated scenario (vehicle and obstacle counts drawn from the config's ranges, or 1 x 0 at ``lone_fraction``)."""
        cfg = self.config
        if cfg.lone_fraction > 0 and self._rng.random() < cfg.lone_fraction:  # no extra draw at the default 0
            return generate(self._rng, cfg, 1, 0)
        n = cfg.num_vehicles if cfg.max_vehicles is None else int(self._rng.integers(cfg.num_vehicles, cfg.max_vehicles + 1))
        m = cfg.num_obstacles if cfg.max_obstacles is None else int(self._rng.integers(cfg.num_obstacles, cfg.max_obstacles + 1))
        return generate(self._rng, cfg, n, m)

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start an episode on a generated (or the given ``options["layout"]``) scenario."""
        if seed is not None:
            self._rng = training_rng(seed)
        layout = (options or {}).get("layout")
        if layout is None:
            layout = self.draw_layout()
        if len(layout.starts) > len(self.possible_agents):
            self.possible_agents = [f"agent{i}" for i in range(len(layout.starts))]
        obs = self.sim.reset(layout)
        self.agents = [f"agent{i}" for i in range(self.sim.num_vehicles)]
        self.episode_over = False
        return {a: obs[i] for i, a in enumerate(self.agents)}, self._infos(self.agents)

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply one (steering, pedal) action per driving vehicle; returns obs, rewards, terminations, truncations, infos."""
        if self.episode_over:
            raise RuntimeError("the episode is over (every vehicle is done); call reset() first")
        arr = np.zeros((self.sim.num_vehicles, schema.ACT_DIM))
        for aid, a in checked_actions(actions, self.agents).items():
            arr[int(aid[5:])] = a
        res = self.sim.step(arr)
        ids = [f"agent{i}" for i in np.nonzero(res.acted)[0]]
        idx = [int(a[5:]) for a in ids]
        out = (
            {a: res.obs[i] for a, i in zip(ids, idx)},
            {a: float(res.reward[i]) for a, i in zip(ids, idx)},
            {a: bool(res.success[i]) for a, i in zip(ids, idx)},
            {a: bool(res.truncated[i]) for a, i in zip(ids, idx)},
            self._infos(ids),
        )
        self.agents = [f"agent{i}" for i in np.nonzero(self.sim.driving)[0]]
        self.episode_over = not self.agents
        return out

    def _infos(self, ids: list[str]) -> dict[str, dict[str, Any]]:
        """Infos of the vehicles ``ids`` (see module doc)."""
        sim = self.sim
        dist, heading_error = sim.target_distance(), sim.heading_error()
        out = {}
        for aid in ids:
            i = int(aid[5:])
            out[aid] = {
                schema.SUCCESS: bool(sim.succeeded[i]),
                schema.COLLIDED: bool(sim.collided[i]),
                "collisions": int(sim.collision_events[i]),
                "distance": float(sim.distance[i]),
                "target_distance": float(dist[i]),
                "heading_error": float(heading_error[i]),
                schema.ENV_STEP: int(sim.t),
            }
        return out

    def close(self) -> None:
        """Nothing to release."""


def arena_metrics(sim: ArenaSimulator) -> dict[str, float]:
    """The paper's metrics of a finished episode: success-to-goal rate, collision events, metres, collisions per metre."""
    n = sim.num_vehicles
    events, metres = int(sim.collision_events.sum()), float(sim.distance.sum())
    return {
        "vehicles": n,
        "obstacles": len(sim.layout.obstacles),
        "success_to_goal_rate": float((sim.succeeded & ~sim.collided).sum() / n),
        "success_rate_any": float(sim.succeeded.sum() / n),
        "collisions": events,
        "distance": metres,
        "collision_rate": events / metres if metres > 0 else 0.0,
        "steps": int(sim.t),
    }
