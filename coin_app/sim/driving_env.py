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
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.inputs import check_seed, checked_actions
from coin_app.sim.scenarios import env_config
from coin_app.sim.simulator import ACTIVE, DrivingSimulator, StepResult, agent_name

__all__ = ["DrivingEnv", "checked_actions", "result_dicts"]  # checked_actions: coin_app.sim.inputs, re-exported


class DrivingEnv:
    """A native multi-agent driving scenario with respawning vehicles."""

    def __init__(self, config: ScenarioConfig | None = None, scenario: str | None = None, preset: str | None = None, **overrides: Any):
        """A ``config``, or ``scenario`` (default intersection) with ``preset`` (default paper) and overrides; never both
        (:func:`~coin_app.sim.inputs.env_config`, the check every env API shares)."""
        self.config: ScenarioConfig = env_config(config, scenario, preset, overrides, "DrivingEnv", arena=False)  # type: ignore[assignment]
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
        """Start a new episode (``seed``: None or an integer >= 0); returns observations and infos of the initial agents."""
        res = self.sim.reset(check_seed(seed))
        self._returns[:] = 0.0
        self.episode_over = False
        obs, _, _, _, infos = self._unpack(res)
        return obs, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply one action per agent in ``agents``; returns obs, rewards, terminations, truncations, infos."""
        if self.episode_over:
            raise RuntimeError("the episode is over (every vehicle is done); call reset() first")
        arr = np.zeros((self.sim.num_slots, schema.ACT_DIM))
        checked = checked_actions(actions, self.agents)
        if checked:
            arr[[self._slot_of[aid] for aid in checked]] = np.stack(list(checked.values()))
        return self._unpack(self.sim.step(arr))

    def _unpack(self, res: StepResult) -> tuple[dict, dict, dict, dict, dict]:
        """Turn a per-slot step result into PettingZoo-style per-agent dicts."""
        out = result_dicts(res, np.arange(self.sim.num_slots), self._returns, 0)
        status = self.sim.status
        active = np.nonzero(status == ACTIVE)[0]
        self._slot_of = {agent_name(num): s for num, s in zip(self.sim.agent_num[active].tolist(), active.tolist())}
        self.agents = list(self._slot_of)
        self.episode_over = bool(res.episode_over[0])
        return out

    def set_num_agents(self, n: int) -> None:
        """Vehicles at reset (and the respawn cap) from the next ``reset`` on: 1 to the config's num_agents (a curriculum's phase)."""
        self.sim.set_num_agents(n)

    def agent_slot(self, agent_id: str) -> int:
        """Simulator slot of an acting agent."""
        return self._slot_of[agent_id]

    def close(self) -> None:
        """Nothing to release (the MetaDrive backend's ``close`` shuts its engine down)."""


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
    out = slots[acted | spawned]
    # per-agent Python values, converted once per array (tolist gives the same bool / float / int as bool(), float(), int())
    columns = zip(
        out.tolist(), res.agent_num[out].tolist(), res.acted[out].tolist(), res.spawned[out].tolist(),
        res.arrive_dest[out].tolist(), res.crash_vehicle[out].tolist(), res.out_of_road[out].tolist(), res.max_step[out].tolist(),
        res.reward[out].tolist(), res.episode_length[out].tolist(), returns[out].tolist(), res.terminated[out].tolist(),
        res.truncated[out].tolist(),
    )  # fmt: skip
    for slot, num, did_act, is_new, arrive, crash, oor, max_step, reward, ep_len, ep_return, term, trunc in columns:
        aid = agent_name(num)
        obs[aid] = res.obs[slot]
        infos[aid] = {
            schema.ARRIVE_DEST: arrive,
            schema.CRASH_VEHICLE: crash,
            schema.OUT_OF_ROAD: oor,
            schema.MAX_STEP: max_step,
            schema.STEP_REWARD: reward,
            schema.EPISODE_LENGTH: ep_len if not is_new else 0,
            schema.EPISODE_REWARD: ep_return,
            schema.STATE: res.state[slot],
            schema.ENV_STEP: step,
            schema.GLOBAL_REWARD: g,
        }
        if did_act:
            rewards[aid] = reward
            terms[aid] = term
            truncs[aid] = trunc
    return obs, rewards, terms, truncs, infos
