"""Dict-of-agents driving env over the simulator core: the one interface every adapter wraps.

Semantics are PettingZoo's parallel API: ``agents`` are the ids that act next; ``step``
takes one action per agent in ``agents`` and returns rewards / terminations /
truncations for those agents, and observations / infos for them *and* for agents that
spawned in this step (new, never reused ids ``agent<N>``, reward 0, not done).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np

from coin_app.sim import schema
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.simulator import ACTIVE, DrivingSimulator, StepResult, agent_name


class DrivingEnv:
    """A native multi-agent driving scenario with respawning vehicles."""

    def __init__(self, config: ScenarioConfig | None = None, scenario: str = "intersection", preset: str = "paper", **overrides: Any):
        self.config = config if config is not None else make_config(scenario, preset, **overrides)
        self.sim = DrivingSimulator(self.config)
        self.possible_agents = [agent_name(i) for i in range(self.sim.max_agent_ids)]
        self.observation_space = gym.spaces.Box(0.0, 1.0, (self.config.obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (schema.ACT_DIM,), np.float32)
        self.agents: list[str] = []
        self._slot_of: dict[str, int] = {}
        self._returns = np.zeros(self.sim.num_slots)
        self.episode_over = True

    @property
    def scenario(self) -> str:
        """Name of the scenario (map)."""
        return self.config.scenario

    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start a new episode; returns observations and infos of the initial agents."""
        res = self.sim.reset(seed)
        self._returns[:] = 0.0
        self.episode_over = False
        obs, _, _, _, infos = self._unpack(res)
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply one action per agent in ``agents``; returns obs, rewards, terminations, truncations, infos."""
        if self.episode_over:
            raise RuntimeError("the episode is over (every vehicle is done); call reset() first")
        arr = np.zeros((self.sim.num_slots, schema.ACT_DIM))
        for aid, a in checked_actions(actions, self.agents).items():
            arr[self._slot_of[aid]] = a
        return self._unpack(self.sim.step(arr))

    def _unpack(self, res: StepResult) -> tuple[dict, dict, dict, dict, dict]:
        """Turn a per-slot step result into PettingZoo-style per-agent dicts."""
        out = result_dicts(res, np.arange(self.sim.num_slots), self._returns, 0)
        status = self.sim.status
        self._slot_of = {agent_name(int(self.sim.agent_num[s])): int(s) for s in np.nonzero(status == ACTIVE)[0]}
        self.agents = list(self._slot_of)
        self.episode_over = bool(res.episode_over[0])
        return out

    def agent_slot(self, agent_id: str) -> int:
        """Simulator slot of an acting agent."""
        return self._slot_of[agent_id]

    def close(self) -> None:
        """Nothing to release (the MetaDrive backend's ``close`` shuts its engine down)."""


def checked_actions(actions: dict[str, Any], agents: list[str]) -> dict[str, np.ndarray]:
    """``actions`` as float arrays of shape (2,), after checking there is exactly one per agent in ``agents``."""
    unknown = sorted(set(actions) - set(agents))
    if unknown:
        raise ValueError(f"actions for agent(s) {unknown} that cannot act now; acting agents: {agents}")
    missing = [a for a in agents if a not in actions]
    if missing:
        raise ValueError(f"missing actions for agent(s) {missing}; every agent in env.agents must act")
    out = {}
    for aid, a in actions.items():
        a = np.asarray(a, dtype=float).reshape(-1)
        if a.shape != (schema.ACT_DIM,):
            raise ValueError(f"action of {aid} must have 2 numbers [steer, throttle_brake], got shape {a.shape}")
        out[aid] = a
    return out


def result_dicts(res: StepResult, slots: np.ndarray, returns: np.ndarray, env: int) -> tuple[dict, dict, dict, dict, dict]:
    """Per-agent (obs, rewards, terminations, truncations, infos) of env ``env`` from a step result.

    ``slots`` are the env's slots; ``returns`` (per slot, updated in place) accumulates each
    agent's episode reward. Agents that acted get reward / done entries; agents that
    spawned in the step only an observation and an info.
    """
    obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
    spawned, acted = res.spawned[slots], res.acted[slots]
    returns[slots[spawned]] = 0.0
    returns[slots[acted]] += res.reward[slots[acted]]
    step = int(res.env_step[env])
    g = float(res.global_reward[env])
    for slot in slots[acted | spawned]:
        aid = agent_name(int(res.agent_num[slot]))
        obs[aid] = res.obs[slot]
        infos[aid] = {
            schema.ARRIVE_DEST: bool(res.arrive_dest[slot]),
            schema.CRASH_VEHICLE: bool(res.crash_vehicle[slot]),
            schema.OUT_OF_ROAD: bool(res.out_of_road[slot]),
            schema.MAX_STEP: bool(res.max_step[slot]),
            schema.STEP_REWARD: float(res.reward[slot]),
            schema.EPISODE_LENGTH: int(res.episode_length[slot]) if not res.spawned[slot] else 0,
            schema.EPISODE_REWARD: float(returns[slot]),
            schema.STATE: res.state[slot],
            schema.ENV_STEP: step,
            schema.GLOBAL_REWARD: g,
        }
        if res.acted[slot]:
            rewards[aid] = float(res.reward[slot])
            terms[aid] = bool(res.terminated[slot])
            truncs[aid] = bool(res.truncated[slot])
    return obs, rewards, terms, truncs, infos
