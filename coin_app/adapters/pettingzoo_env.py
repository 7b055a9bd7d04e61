"""PettingZoo parallel-API adapter of :class:`~coin_app.sim.driving_env.DrivingEnv`.

The driving env already follows PettingZoo's parallel semantics except for one detail:
an agent that spawns during a step gets an observation and an info in that step but no
reward / termination / truncation entry. ``pettingzoo.test.parallel_api_test`` (1.27.0)
needs those entries: after each step it computes the next actions only for the agents of
``env.agents`` that appear in the returned ``terminations`` or ``truncations`` with value
False, and it reads ``terminations[agent]`` for every live agent, newcomers included. A
newcomer without entries would therefore get no action (the driving env then rejects the
step) or raise a ``KeyError`` inside the test. This adapter gives every agent spawned in a
step ``reward 0.0``, ``terminated False`` and ``truncated False``, so all five returned
dicts have the same keys; nothing else about the driving env changes.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from pettingzoo import ParallelEnv

from coin_app.backends.factory import make_driving_env
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.inputs import check_seed
from coin_app.sim.rendering import render_frame
from coin_app.sim.scenarios import env_config


class CoinParallelEnv(ParallelEnv[str, np.ndarray, np.ndarray]):
    """A COIN driving scenario (or the ``"arena"``) as a PettingZoo ``ParallelEnv`` with respawning agents.

    ``possible_agents`` is the whole id pool of an episode (``agent0`` .. ``agentK``); ids
    restart at ``agent0`` after every ``reset`` and are never reused within an episode.
    Every pool id has its own observation / action space object (built on first use and
    cached). Because most pool ids never appear in an episode, ``parallel_api_test``
    warns "No agents present but not all possible_agents are terminated or truncated"
    at the end of each episode; that warning is expected.
    """

    metadata = {"name": "coin_driving_v0", "render_modes": ["rgb_array"], "render_fps": 10, "is_parallelizable": True}

    def __init__(
        self,
        scenario: Any = "intersection",
        preset: str | None = None,
        render_mode: str | None = None,
        **overrides: Any,
    ):

        config: Any
        if isinstance(scenario, (ScenarioConfig, ArenaConfig)):  # a config in the scenario's place (this env's first argument)
            config = env_config(scenario, None, preset, overrides, "CoinParallelEnv")
        else:
            config = env_config(None, scenario, preset, overrides, "CoinParallelEnv")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"unknown render_mode {render_mode!r}; allowed: {', '.join(self.metadata['render_modes'])} or None")
        if render_mode is not None and isinstance(config, ArenaConfig):
            raise ValueError(f"render_mode {render_mode!r} is not available for the arena; allowed: None")
        self.render_mode = render_mode
        self.driving_env = make_driving_env(config)
        self.config = config
        self.possible_agents: list[str] = list(self.driving_env.possible_agents)
        self._pool = frozenset(self.possible_agents)
        self.agents: list[str] = []
        self._obs_spaces: dict[str, gym.spaces.Box] = {}
        self._act_spaces: dict[str, gym.spaces.Box] = {}
        self._closed = False

    def _check_id(self, agent: str) -> None:
        if agent not in self._pool:
            raise KeyError(f"unknown agent id {agent!r}; ids are agent0 .. agent{len(self.possible_agents) - 1}")

    def observation_space(self, agent: str) -> gym.spaces.Box:
        """Observation space of ``agent`` (the same object on every call)."""
        space = self._obs_spaces.get(agent)
        if space is None:
            self._check_id(agent)
            base = self.driving_env.observation_space
            space = self._obs_spaces[agent] = gym.spaces.Box(base.low, base.high, base.shape, base.dtype)
        return space

    def action_space(self, agent: str) -> gym.spaces.Box:
        """Action space ``[steer, throttle_brake]`` of ``agent`` (the same object on every call)."""
        space = self._act_spaces.get(agent)
        if space is None:
            self._check_id(agent)
            base = self.driving_env.action_space
            space = self._act_spaces[agent] = gym.spaces.Box(base.low, base.high, base.shape, base.dtype)
        return space

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start a new episode (``seed``: None or an integer >= 0); returns observations and infos of the initial agents
        (``options`` is unused)."""
        self._check_open()
        obs, infos = self.driving_env.reset(check_seed(seed))
        self.agents = list(self.driving_env.agents)
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Act for every agent in ``agents``; newcomers get reward 0.0 and False flags (see module doc)."""
        self._check_open()
        obs, rewards, terms, truncs, infos = self.driving_env.step(actions)
        for aid in obs:
            if aid not in rewards:
                rewards[aid] = 0.0
                terms[aid] = False
                truncs[aid] = False
        self.agents = list(self.driving_env.agents)
        return obs, rewards, terms, truncs, infos

    def render(self) -> np.ndarray | None:
        """An RGB frame of the scene, or None without ``render_mode`` or a renderer."""
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; pass render_mode='rgb_array'")
            return None

        return render_frame(self.driving_env)

    def close(self) -> None:
        """Release the backend (shuts a MetaDrive engine down); ``reset`` and ``step`` are refused afterwards."""
        self.agents = []
        self._closed = True
        self.driving_env.close()

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError("the env is closed (close() was called); allowed: a new CoinParallelEnv")
