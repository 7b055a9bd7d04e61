"""One rollout loop for every caller: reset, ask a batch policy for the acting agents' actions, step, hand back the dicts.

:func:`rollout` drives a *vector of dict-API envs*: either :class:`BatchedEnvs`, the envs of
one batched :class:`~coin_app.sim.simulator.DrivingSimulator` (many seeds, one simulator
step for all of them), or :class:`DictEnvs`, a list of dict-API envs (the native
:class:`~coin_app.sim.driving_env.DrivingEnv` or the MetaDrive backend). Each env step
makes one policy call for the acting agents of all envs together and yields, per env whose
episode is still running, the PettingZoo-parallel dicts the env's step returns. An env's
episode is over for good once it reports ``episode_over``; the rollout ends when every
episode is over or after ``max_steps`` env steps.

A policy is a callable on the observations alone, or an :class:`AgentPolicy` that also needs to
know which vehicle each row is (CoPO's per-vehicle LCF): the rollout then calls
``policy.act(obs, agents)`` with ``agents[i] = (seed of the row's episode, agent id)``.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol, runtime_checkable

import numpy as np

from coin_app.sim import schema
from coin_app.sim.driving_env import result_dicts
from coin_app.sim.simulator import ACTIVE, DrivingSimulator, agent_name

Policy = Callable[[np.ndarray], np.ndarray]  # observations (N, obs_dim) of the acting agents -> actions (N, 2)
AgentKey = tuple[int, str]  # (seed of the episode, agent id): one vehicle of one episode


@runtime_checkable
class AgentPolicy(Protocol):
    """A batch policy that also needs to know which vehicle each row is (e.g. CoPO's per-vehicle LCF)."""

    def act(self, obs: np.ndarray, agents: Sequence[AgentKey]) -> np.ndarray:
        """Actions (N, 2) for observations (N, obs_dim), row ``i`` of vehicle ``agents[i]``."""


class EnvStep(NamedTuple):
    """One env's per-agent dicts of a step (after a reset: the initial obs and infos, the other three empty)."""

    obs: dict[str, np.ndarray]
    rewards: dict[str, float]
    terminateds: dict[str, bool]
    truncateds: dict[str, bool]
    infos: dict[str, dict]


@dataclass
class RolloutStep:
    """What :func:`rollout` yields: ``t`` env steps taken (0 = the reset) and the dicts of each env that was running."""

    t: int
    results: dict[int, EnvStep]  # env index -> its dicts; envs whose episode ended before this step are left out


class VecEnv(Protocol):
    """``num_envs`` dict-API envs stepped in lockstep: what :func:`rollout` drives."""

    num_envs: int
    episode_over: np.ndarray  # bool (num_envs,): the env's episode has ended (and stays ended)

    def reset(self, seeds: Sequence[int]) -> dict[int, EnvStep]:
        """Start one episode per env, env ``e`` seeded with ``seeds[e]``; the initial obs and infos."""

    def observe(self) -> np.ndarray:
        """Observations (N, obs_dim) of the N agents that act next, over all running envs."""

    def acting_agents(self) -> list[tuple[int, str]]:
        """(env index, agent id) of each row of the last :meth:`observe`."""

    def step(self, actions: np.ndarray) -> dict[int, EnvStep]:
        """Apply actions (N, 2), one row per row of the last :meth:`observe`; the dicts of the envs that were running."""


class BatchedEnvs:
    """The envs of one batched :class:`DrivingSimulator` as a vector of dict-API envs (one seed per env).

    Every env's episode has the same dicts as a :class:`~coin_app.sim.driving_env.DrivingEnv`
    reset with its seed. The simulator steps all envs together; vehicles that respawn in an
    env after its episode ended still act (they are independent of the other envs) but
    are no longer reported.
    """

    def __init__(self, sim: DrivingSimulator):
        self.sim = sim
        self.num_envs = sim.num_envs
        self.episode_over = np.ones(sim.num_envs, bool)
        self.obs = np.zeros((sim.num_slots, sim.cfg.obs_dim), np.float32)  # latest observation of every slot
        self.state = np.zeros((sim.num_slots, schema.STATE_DIM), np.float32)  # latest local state of every slot
        self.acting = np.zeros(0, np.int64)  # slots of the rows of the last observe()
        self._returns = np.zeros(sim.num_slots)

    def reset(self, seeds: Sequence[int]) -> dict[int, EnvStep]:
        """Start one episode per env, env ``e`` seeded with ``seeds[e]``; the initial obs and infos."""
        res = self.sim.reset([int(s) for s in seeds])
        self._returns[:] = 0.0
        self.obs, self.state = res.obs.copy(), res.state.copy()
        self.episode_over[:] = False
        return {e: EnvStep(*result_dicts(res, self.sim.env_slots(e), self._returns, e)) for e in range(self.num_envs)}

    def observe(self) -> np.ndarray:
        """Observations (N, obs_dim) of the N active vehicles of the simulator, in slot order."""
        self.acting = np.nonzero(self.sim.status == ACTIVE)[0]
        return self.obs[self.acting]

    def acting_agents(self) -> list[tuple[int, str]]:
        """(env index, agent id) of each row of the last :meth:`observe` (its slot's env and vehicle)."""
        envs = self.acting // self.sim.slots_per_env
        return [(int(e), agent_name(int(n))) for e, n in zip(envs, self.sim.agent_num[self.acting])]

    def step(self, actions: np.ndarray) -> dict[int, EnvStep]:
        """Step the simulator with one action row per slot of ``acting``; the dicts of the envs that were running."""
        full = np.zeros((self.sim.num_slots, schema.ACT_DIM))
        full[self.acting] = actions
        res = self.sim.step(full)
        fresh = res.acted | res.spawned
        self.obs[fresh], self.state[fresh] = res.obs[fresh], res.state[fresh]
        running = np.nonzero(~self.episode_over)[0]
        out = {int(e): EnvStep(*result_dicts(res, self.sim.env_slots(e), self._returns, e)) for e in running}
        self.episode_over |= res.episode_over
        return out


class DictEnvs:
    """Dict-API driving envs (native ``DrivingEnv`` or MetaDrive) stepped in lockstep, one episode each."""

    def __init__(self, envs: Sequence[Any]):
        self.envs = list(envs)
        self.num_envs = len(self.envs)
        self._obs: list[dict[str, np.ndarray]] = [{} for _ in self.envs]  # latest observation of every agent seen
        self._agents: list[list[str]] = [[] for _ in self.envs]  # agents of the rows of the last observe()

    @property
    def episode_over(self) -> np.ndarray:
        """Bool (num_envs,): the env's episode has ended."""
        return np.array([env.episode_over for env in self.envs], bool)

    def reset(self, seeds: Sequence[int]) -> dict[int, EnvStep]:
        """Start one episode per env, env ``e`` seeded with ``seeds[e]``; the initial obs and infos."""
        out = {}
        for e, (env, seed) in enumerate(zip(self.envs, seeds)):
            obs, infos = env.reset(int(seed))
            self._obs[e] = dict(obs)
            out[e] = EnvStep(obs, {}, {}, {}, infos)
        return out

    def observe(self) -> np.ndarray:
        """Observations (N, obs_dim) of the agents in ``env.agents`` of every running env, env by env."""
        self._agents = [[] if env.episode_over else list(env.agents) for env in self.envs]
        rows = [self._obs[e][a] for e, agents in enumerate(self._agents) for a in agents]
        return np.stack(rows) if rows else np.zeros((0, 0), np.float32)

    def acting_agents(self) -> list[tuple[int, str]]:
        """(env index, agent id) of each row of the last :meth:`observe`."""
        return [(e, a) for e, agents in enumerate(self._agents) for a in agents]

    def step(self, actions: np.ndarray) -> dict[int, EnvStep]:
        """Step every running env with its rows of ``actions``; the dicts of those envs."""
        out, start = {}, 0
        for e, (env, agents) in enumerate(zip(self.envs, self._agents)):
            if env.episode_over:
                continue
            result = EnvStep(*env.step(dict(zip(agents, actions[start : start + len(agents)]))))
            start += len(agents)
            self._obs[e].update(result.obs)
            out[e] = result
        return out


def rollout(envs: VecEnv, policy: Policy | AgentPolicy, seeds: Sequence[int], max_steps: int) -> Iterator[RolloutStep]:
    """Run ``policy`` for one episode per env (env ``e`` seeded ``seeds[e]``); yield the reset, then every env step.

    Each step calls ``policy`` once on the observations of all acting agents (not at all when
    none acts; ``policy.act(obs, agents)`` for an :class:`AgentPolicy`); it must return actions
    of shape (N, 2). Ends when every episode is over or after ``max_steps`` steps.
    """
    if len(seeds) != envs.num_envs:
        raise ValueError(f"need one seed per env: {envs.num_envs} envs, {len(seeds)} seeds")
    yield RolloutStep(0, envs.reset(seeds))
    t = 0
    while t < max_steps and not envs.episode_over.all():
        t += 1
        obs = envs.observe()
        actions = np.zeros((len(obs), schema.ACT_DIM))
        if len(obs) and isinstance(policy, AgentPolicy):
            agents = [(int(seeds[e]), aid) for e, aid in envs.acting_agents()]
            actions = np.asarray(policy.act(obs, agents), dtype=float)
        elif len(obs):
            actions = np.asarray(policy(obs), dtype=float)
        if len(obs) and actions.shape != (len(obs), schema.ACT_DIM):
            raise ValueError(f"policy returned actions of shape {actions.shape}; expected ({len(obs)}, {schema.ACT_DIM})")
        yield RolloutStep(t, envs.step(actions))


__all__ = ["AgentKey", "AgentPolicy", "BatchedEnvs", "DictEnvs", "EnvStep", "Policy", "RolloutStep", "VecEnv", "rollout"]
