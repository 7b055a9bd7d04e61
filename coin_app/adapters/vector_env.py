"""Many copies of one scenario as flat per-slot arrays, with the semantics of the ``MultiAgentEnv`` adapter.

This is what the batched env runner (``batched_runner.py``) steps. Env ``e`` owns slots
``e * slots_per_env .. (e + 1) * slots_per_env - 1``; a slot holds one vehicle at a time, and a
vehicle's life in a slot runs from its first observation (spawn, respawn or env reset) to the
step it ends (arrival, crash, off-road, its own step limit or the force stop). Per env, every
rule of :class:`~coin_app.adapters.rllib_env.CoinMultiAgentEnv` holds (module doc there):

* vehicle ids ``agent<N>`` are fresh within an episode and restart at every reset;
* an env's episode is over when no vehicle acts after the step, or when every vehicle that
  acted in the step ended in it; the vehicles spawned in that step are dropped (never seen),
  and the env is reset at once, continuing its random stream (the adapter's ``reset(seed=None)``
  on the vector env's next step), so the new episode's vehicles are born in the same call;
* ``over_truncated``: every vehicle that ended in the over step was truncated (the adapter's
  ``truncateds["__all__"]``);
* infos carry the same keys and values as the adapter's (``coin_app.sim.driving_env.result_dicts``
  for the driving scenarios, ``ArenaEnv.infos`` for the arena), CoPO's LCF included;
* ``outcomes`` counts ended vehicles, successes, collisions, agent steps and the speed sum as the
  adapter does.

Env ``e`` is seeded ``seed + e`` at the first :meth:`reset` (as RLlib's vector env seeds its
sub-envs), so it reproduces an adapter env seeded the same way. The driving scenarios step one
:class:`~coin_app.sim.simulator.DrivingSimulator` for all envs; the arena steps one
``ArenaEnv`` per env (each vectorized over its vehicles).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from coin_app.adapters.lcf import LocalCoordination, check_distribution, encode, lcf_stream
from coin_app.adapters.rllib_env import OUTCOMES
from coin_app.sim import schema
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.simulator import DrivingSimulator, StepResult, agent_name


@dataclass
class VectorStep:
    """One lock step of all envs, per slot (flat over envs); rows of slots that did not act are zero."""

    acted: np.ndarray  # (N,) bool: the slot's vehicle acted in this step
    agent_num: np.ndarray  # (N,) int: number of the vehicle that acted in the slot
    reward: np.ndarray  # (N,) float32
    terminated: np.ndarray  # (N,) bool: the vehicle's own flags, as the adapter reports them
    truncated: np.ndarray  # (N,) bool
    next_obs: np.ndarray  # (N, D) float32: the acted vehicle's observation after the step (its last one if it ended)
    next_infos: dict[int, dict[str, Any]]  # slot -> info of that observation (acted slots)
    over: np.ndarray  # (E,) bool: the env's episode ended in this step (the env is reset; its new vehicles are born)
    over_truncated: np.ndarray  # (E,) bool: ... and every vehicle that ended in it was truncated
    born: np.ndarray  # (N,) bool: a new vehicle's first observation is now in ``obs`` (spawn or env reset)
    born_infos: dict[int, dict[str, Any]]  # slot -> info of that first observation


class VectorEnv:
    """Common state of a vector env: the current observation, acting mask and vehicle number of every slot."""

    num_envs: int
    slots_per_env: int
    observation_space: gym.spaces.Box
    action_space: gym.spaces.Box

    def _init_slots(self, obs_dim: int) -> None:
        """Allocate the per-slot state."""
        self.num_slots = self.num_envs * self.slots_per_env
        self.obs = np.zeros((self.num_slots, obs_dim), np.float32)  # current observation of each slot's vehicle
        self.active = np.zeros(self.num_slots, bool)  # the slot's vehicle acts in the next step
        self.agent_num = np.full(self.num_slots, -1, np.int64)  # number of the slot's current vehicle
        self.env_of = np.repeat(np.arange(self.num_envs), self.slots_per_env)
        self.outcomes = dict.fromkeys(OUTCOMES, 0)

    def agent_ids(self, slots: np.ndarray) -> list[str]:
        """The ids ``agent<N>`` of the current vehicles of ``slots``."""
        return [agent_name(int(n)) for n in self.agent_num[slots]]

    def _ended_envs(
        self, acted: np.ndarray, ended: np.ndarray, truncated: np.ndarray, no_vehicle_left: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(over, over_truncated) per env from the acted / ended / truncated slots, as the adapter decides them."""
        n_acted = np.bincount(self.env_of[acted], minlength=self.num_envs)
        n_ended = np.bincount(self.env_of[ended], minlength=self.num_envs)
        over = no_vehicle_left | ((n_acted > 0) & (n_ended == n_acted))
        return over, over & (np.bincount(self.env_of[ended & ~truncated], minlength=self.num_envs) == 0)

    def set_lcf_distribution(self, mean: float, std: float) -> None:
        """Refused: only a driving scenario with CoPO's LCFs has a distribution to move."""
        raise RuntimeError("this env has no local coordination factors (env_config has no 'lcf')")

    def set_start_difficulty(self, difficulty: float) -> None:
        """The arena's curriculum: the start spread of scenarios generated from now on (other scenarios have none)."""
        raise ValueError(f"start_difficulty is an arena setting; this vector env steps {type(self).__name__}")

    def set_num_agents(self, n: int) -> None:
        """A driving curriculum's phase: vehicles at reset of the episodes started from now on (the arena has none)."""
        raise ValueError(f"num_agents curricula are a driving setting; this vector env steps {type(self).__name__}")

    def close(self) -> None:
        """Nothing to release."""


class DrivingVectorEnv(VectorEnv):
    """``num_envs`` copies of a driving scenario in one :class:`DrivingSimulator` (see module doc)."""

    def __init__(self, config: ScenarioConfig, num_envs: int, lcf: dict[str, float] | None = None):
        if config.backend != "native":
            raise ValueError(
                f"the batched env runner steps the native simulator, not backend {config.backend!r}; "
                "allowed: backend='native', or env_runner='multi_agent' for MetaDrive"
            )
        self.config = config
        self.sim = DrivingSimulator(config, num_envs)
        self.num_envs, self.slots_per_env = num_envs, self.sim.slots_per_env
        self.lcf = None if lcf is None else LocalCoordination(**lcf)  # the distribution; draws use per-env streams
        self.observation_space, self.action_space = vector_spaces(config, lcf)
        self._init_slots(int(self.observation_space.shape[0]))
        self._returns = np.zeros(self.num_slots)
        self._lcf_value = np.zeros(self.num_slots)
        self._lcf_rngs = [lcf_stream(0) for _ in range(num_envs)]

    def set_lcf_distribution(self, mean: float, std: float) -> None:
        """Draw the LCFs of vehicles spawned from now on from N(mean, std) (an env with LCFs only)."""
        if self.lcf is None:
            raise RuntimeError("this env has no local coordination factors (env_config has no 'lcf')")
        self.lcf.set_distribution(*check_distribution(mean, std))

    def set_num_agents(self, n: int) -> None:
        """Vehicles at reset (and the respawn cap) of every env's episodes started from now on: 1 to the config's num_agents."""
        self.sim.set_num_agents(n)

    def reset(self, seed: int | None = None) -> dict[int, dict[str, Any]]:
        """Start new episodes in every env (env ``e`` seeded ``seed + e``); the infos of the vehicles born."""
        seeds = [None if seed is None else int(seed) + e for e in range(self.num_envs)]
        res = self.sim.reset_envs(np.arange(self.num_envs), seeds)
        self.active[:] = False
        return self._born(res, np.arange(self.num_envs), seeds, res.spawned)

    def step(self, actions: np.ndarray) -> VectorStep:
        """Step every env with one action row per slot (rows of slots that do not act are ignored)."""
        res = self.sim.step(actions)
        acted = res.acted
        ended = acted & (res.terminated | res.truncated)
        over, over_trunc = self._ended_envs(acted, ended, res.truncated, res.episode_over)
        spawned = res.spawned & ~over[self.env_of]  # the adapter drops vehicles spawned in an over step
        self._count_outcomes(res, acted, ended)
        self._returns[res.spawned] = 0.0
        self._returns[acted] += res.reward[acted]
        next_obs = self._with_lcf(res.obs)
        next_infos = self._infos(res, np.nonzero(acted)[0], res.spawned)
        self.obs[acted] = next_obs[acted]
        self.active = acted & ~ended
        born_infos = self._born(res, np.zeros(0, np.int64), [], spawned) if spawned.any() else {}
        born = spawned.copy()
        over_envs = np.nonzero(over)[0]
        if len(over_envs):
            self.active[np.isin(self.env_of, over_envs)] = False
            reset = self.sim.reset_envs(over_envs, [None] * len(over_envs))
            born_infos.update(self._born(reset, over_envs, [None] * len(over_envs), reset.spawned))
            born |= reset.spawned
        return VectorStep(
            acted=acted,
            agent_num=np.where(acted, res.agent_num, -1),
            reward=res.reward.astype(np.float32),
            terminated=res.terminated & acted,
            truncated=res.truncated & acted,
            next_obs=next_obs,
            next_infos=next_infos,
            over=over,
            over_truncated=over_trunc,
            born=born,
            born_infos=born_infos,
        )

    def _born(self, res: StepResult, reset_envs: np.ndarray, seeds: list[int | None], born: np.ndarray) -> dict[int, dict[str, Any]]:
        """Make the ``born`` slots' vehicles current (LCF draws first, in slot order per env); their infos."""
        for e, sd in zip(reset_envs, seeds):  # an env reset forgets the LCFs and reseeds (or continues) their stream
            if sd is not None:
                self._lcf_rngs[e] = lcf_stream(sd)
        slots = np.nonzero(born)[0]
        if self.lcf is not None and len(slots):
            for e in np.unique(self.env_of[slots]):
                s = slots[self.env_of[slots] == e]
                self._lcf_value[s] = np.clip(self._lcf_rngs[e].normal(self.lcf.mean, self.lcf.std, len(s)), -1.0, 1.0)
        self._returns[slots] = 0.0
        self.obs[slots] = self._with_lcf(res.obs)[slots]
        self.active[slots] = True
        self.agent_num[slots] = res.agent_num[slots]
        return self._infos(res, slots, res.spawned)

    def _with_lcf(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` with each slot's LCF feature appended (as is without LCFs)."""
        if self.lcf is None:
            return obs
        return np.concatenate([obs, encode(self._lcf_value)[:, None]], axis=1)

    def _infos(self, res: StepResult, slots: np.ndarray, spawned: np.ndarray) -> dict[int, dict[str, Any]]:
        """The adapter's info of each slot in ``slots`` (``coin_app.sim.driving_env.result_dicts``, LCF added)."""
        if not len(slots):
            return {}
        env = self.env_of[slots]
        cols = zip(
            slots.tolist(),
            res.arrive_dest[slots].tolist(),
            res.crash_vehicle[slots].tolist(),
            res.out_of_road[slots].tolist(),
            res.max_step[slots].tolist(),
            res.reward[slots].astype(float).tolist(),
            np.where(spawned[slots], 0, res.episode_length[slots]).tolist(),
            self._returns[slots].astype(float).tolist(),
            res.env_step[env].tolist(),
            res.global_reward[env].astype(float).tolist(),
            self._lcf_value[slots].tolist(),
        )
        out = {}
        for slot, arrive, crash, oor, max_step, reward, length, ret, step, g, lcf in cols:
            info = {
                schema.ARRIVE_DEST: arrive,
                schema.CRASH_VEHICLE: crash,
                schema.OUT_OF_ROAD: oor,
                schema.MAX_STEP: max_step,
                schema.STEP_REWARD: reward,
                schema.EPISODE_LENGTH: length,
                schema.EPISODE_REWARD: ret,
                schema.STATE: res.state[slot],
                schema.ENV_STEP: step,
                schema.GLOBAL_REWARD: g,
            }
            if self.lcf is not None:
                info["lcf"] = lcf
            out[slot] = info
        return out

    def _count_outcomes(self, res: StepResult, acted: np.ndarray, ended: np.ndarray) -> None:
        """Add the ended vehicles' outcomes and the acting vehicles' steps and speeds (m/s) to ``outcomes``."""
        o = self.outcomes
        o["finished"] += int(ended.sum())
        o["succeeded"] += int((res.arrive_dest & ended).sum())
        o["collided"] += int((res.crash_vehicle & ended).sum())
        if acted.any():
            velocity = res.state[acted][:, 2:4]  # v / max_speed (sim/sensors.py local_state)
            o["agent_steps"] += int(acted.sum())
            o["speed_sum"] += float(np.hypot(velocity[:, 0], velocity[:, 1]).sum()) * self.config.max_speed


class ArenaVectorEnv(VectorEnv):
    """``num_envs`` arena envs stepped in lock step, one slot per vehicle of the pool (see module doc)."""

    def __init__(self, config: ArenaConfig, num_envs: int):
        self.config = config
        self.envs = [ArenaEnv(config) for _ in range(num_envs)]
        self.num_envs, self.slots_per_env = num_envs, config.vehicle_pool
        self.observation_space, self.action_space = vector_spaces(config)
        self._init_slots(config.obs_dim)

    def set_start_difficulty(self, difficulty: float) -> None:
        """The start spread (``ArenaConfig.start_difficulty``) of every env's scenarios generated from now on."""
        for env in self.envs:
            env.set_start_difficulty(difficulty)

    def reset(self, seed: int | None = None) -> dict[int, dict[str, Any]]:
        """Start new episodes in every env (env ``e`` seeded ``seed + e``); the infos of the vehicles born."""
        self.active[:] = False
        out: dict[int, dict[str, Any]] = {}
        for e in range(self.num_envs):
            out.update(self._reset_env(e, None if seed is None else int(seed) + e))
        return out

    def _reset_env(self, e: int, seed: int | None) -> dict[int, dict[str, Any]]:
        """Reset env ``e``; its vehicles are born in slots ``e * slots_per_env + i``."""
        obs, infos = self.envs[e].reset(seed)
        base = e * self.slots_per_env
        out = {}
        for aid, o in obs.items():
            slot = base + int(aid[5:])
            self.obs[slot], self.active[slot], self.agent_num[slot] = o, True, int(aid[5:])
            out[slot] = infos[aid]
        return out

    def step(self, actions: np.ndarray) -> VectorStep:
        """Step every env with one action row per slot (rows of slots that do not act are ignored)."""
        n, d = self.num_slots, self.obs.shape[1]
        acted, term, trunc = self.active.copy(), np.zeros(n, bool), np.zeros(n, bool)
        reward, next_obs = np.zeros(n, np.float32), np.zeros((n, d), np.float32)
        next_infos: dict[int, dict[str, Any]] = {}
        for e in np.unique(self.env_of[acted]):
            base = e * self.slots_per_env
            slots = np.nonzero(acted[base : base + self.slots_per_env])[0]
            obs, rew, te, tr, infos = self.envs[e].step({f"agent{i}": actions[base + i] for i in slots.tolist()})
            for aid in obs:
                slot = base + int(aid[5:])
                next_obs[slot], reward[slot], term[slot], trunc[slot] = obs[aid], rew[aid], te[aid], tr[aid]
                next_infos[slot] = infos[aid]
        ended = acted & (term | trunc)
        no_vehicle_left = np.array([env.episode_over for env in self.envs])
        over, over_trunc = self._ended_envs(acted, ended, trunc, no_vehicle_left)
        o = self.outcomes
        o["finished"] += int(ended.sum())
        slots = np.nonzero(ended)[0].tolist()
        o["succeeded"] += sum(bool(next_infos[s][schema.SUCCESS]) for s in slots)
        o["collided"] += sum(bool(next_infos[s][schema.COLLIDED]) for s in slots)
        self.obs[acted] = next_obs[acted]
        self.active = acted & ~ended
        born_infos: dict[int, dict[str, Any]] = {}
        for e in np.nonzero(over)[0]:
            self.active[self.env_of == e] = False
            born_infos.update(self._reset_env(int(e), None))
        born = np.zeros(n, bool)
        born[list(born_infos)] = True
        return VectorStep(
            acted=acted,
            agent_num=np.where(acted, self.agent_num, -1),
            reward=reward,
            terminated=term,
            truncated=trunc,
            next_obs=next_obs,
            next_infos=next_infos,
            over=over,
            over_truncated=over_trunc,
            born=born,
            born_infos=born_infos,
        )


def vector_spaces(config: ScenarioConfig | ArenaConfig, lcf: dict[str, float] | None = None) -> tuple[gym.spaces.Box, gym.spaces.Box]:
    """(observation, action) space of one vehicle of a scenario, as the adapter declares them (LCF feature included)."""
    act_space = gym.spaces.Box(-1.0, 1.0, (schema.ACT_DIM,), np.float32)
    if isinstance(config, ArenaConfig):
        return gym.spaces.Box(-np.inf, np.inf, (config.obs_dim,), np.float32), act_space
    obs_space = gym.spaces.Box(0.0, 1.0, (config.obs_dim,), np.float32)
    return (obs_space if lcf is None else LocalCoordination(**lcf).observation_space(obs_space)), act_space


def make_vector_env(config: ScenarioConfig | ArenaConfig, num_envs: int, lcf: dict[str, float] | None = None) -> VectorEnv:
    """The vector env of a parsed scenario config (CoPO's LCF distribution for a driving scenario)."""
    if not isinstance(num_envs, int) or isinstance(num_envs, bool) or num_envs < 1:
        raise ValueError(f"bad num_envs {num_envs!r}; allowed: an integer >= 1")
    if isinstance(config, ArenaConfig):
        if lcf is not None:
            raise ValueError("the arena has no local coordination factors; allowed: lcf=None")
        return ArenaVectorEnv(config, num_envs)
    return DrivingVectorEnv(config, num_envs, lcf)


__all__ = ["ArenaVectorEnv", "DrivingVectorEnv", "VectorEnv", "VectorStep", "make_vector_env", "vector_spaces"]
