"""The batched env runner: RLlib's ``EnvRunner`` over the vectorized simulator, one forward pass per lock step.

RLlib's ``MultiAgentEnvRunner`` builds its episodes agent by agent and step by step
(``MultiAgentEpisode.add_env_step``), about 0.3 ms per agent step, although the simulator
steps every vehicle of many envs as arrays. :class:`BatchedEnvRunner` steps a
:class:`~coin_app.adapters.vector_env.VectorEnv` (``num_envs_per_env_runner`` copies of the
scenario in lock step), computes the actions of all vehicles of all envs in one
``forward_exploration`` / ``forward_inference`` of the shared RLModule, and builds its
``MultiAgentEpisode`` chunks in bulk from arrays after ``rollout_fragment_length`` lock steps
(one ``SingleAgentEpisode`` per vehicle life per chunk). The episodes are what the
``MultiAgentEnvRunner`` on :class:`~coin_app.adapters.rllib_env.CoinMultiAgentEnv` returns
for the same seeds and actions (``tests/test_batched_runner.py``), so every learner
connector (PPO's GAE, the CPPO / MFPO critic inputs, CoPO's advantages, CIG-TD3's joint-step
replay) reads them unchanged:

* one ``MultiAgentEpisode`` per env episode per chunk; a chunk continues its episode's id and
  ``env_t``; vehicles with no action in a chunk (born on its last step) are left to the next
  chunk, as RLlib prunes them;
* a vehicle's ``SingleAgentEpisode`` keeps its id across chunks; its flags are RLlib's: the
  vehicle's own, and in the step that ends the env's episode ``terminated`` for every vehicle
  (and ``truncated`` too when every vehicle that ended was truncated), as
  ``MultiAgentEpisode.add_env_step`` records them (``docs/decisions.md`` §6.2 item 5);
* infos, ids, ``env_step`` stamps, local states and CoPO's LCF are the adapter's;
* actions: the module's output, or a sample of its action distribution with ``ACTION_LOGP``
  and ``ACTION_DIST_INPUTS`` stored (RLlib's ``GetActions``); the env gets them clipped to the
  action space; ``random_actions=True`` draws them uniformly from the runner's seeded RNG;
* metrics: env and agent steps, episodes, the episode return and length of every finished
  env episode, and the agent outcomes (``agents_<outcome>``) the ``AgentOutcomes`` callback
  logs on the other path.

Env steps are counted as on the other path: one per env per lock step (``E * T`` per chunk).
The runner only steps the native simulator; MetaDrive keeps RLlib's runner. Selected with
``AlgorithmConfig.env_runners(env_runner_cls=BatchedEnvRunner)``.
"""

from __future__ import annotations

import math
import uuid
from collections import defaultdict
from typing import Any

import numpy as np
import ray
import torch
from ray.rllib.core import COMPONENT_RL_MODULE, DEFAULT_MODULE_ID
from ray.rllib.core.columns import Columns
from ray.rllib.env import INPUT_ENV_SINGLE_SPACES, INPUT_ENV_SPACES
from ray.rllib.env.env_runner import EnvRunner
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.rllib.env.single_agent_episode import SingleAgentEpisode
from ray.rllib.env.utils.infinite_lookback_buffer import InfiniteLookbackBuffer
from ray.rllib.utils.checkpoints import Checkpointable
from ray.rllib.utils.metrics import (
    EPISODE_LEN_MAX,
    EPISODE_LEN_MEAN,
    EPISODE_LEN_MIN,
    EPISODE_RETURN_MAX,
    EPISODE_RETURN_MEAN,
    EPISODE_RETURN_MIN,
    NUM_AGENT_STEPS_SAMPLED,
    NUM_AGENT_STEPS_SAMPLED_LIFETIME,
    NUM_ENV_STEPS_SAMPLED,
    NUM_ENV_STEPS_SAMPLED_LIFETIME,
    NUM_EPISODES,
    NUM_EPISODES_LIFETIME,
    NUM_MODULE_STEPS_SAMPLED,
    NUM_MODULE_STEPS_SAMPLED_LIFETIME,
    WEIGHTS_SEQ_NO,
)

from coin_app.adapters.episodes import OrderedMultiAgentEpisode
from coin_app.adapters.rllib_env import OUTCOMES, parse_env_config
from coin_app.adapters.vector_env import VectorEnv, VectorStep, make_vector_env, vector_spaces
from coin_app.sim.simulator import agent_name

ILB = InfiniteLookbackBuffer
ALL_AGENTS = "__all_agents__"  # the agent key of the agent-step counters (RLlib's runner keeps one per vehicle id)


class BatchedEnvRunner(EnvRunner, Checkpointable):
    """An RLlib env runner stepping ``num_envs_per_env_runner`` envs in lock step with one module call per step (module doc)."""

    def __init__(self, *, config: Any, **kwargs: Any):
        super().__init__(config=config, **kwargs)
        self.worker_index = int(kwargs.get("worker_index") or 0)
        self.num_envs = int(self.config.num_envs_per_env_runner)
        self.scenario, self.lcf = parse_env_config(self.config.env_config)
        self.vector_env: VectorEnv | None = None
        obs_space, act_space = vector_spaces(self.scenario, self.lcf)
        module_ids = list(self.config.policies or [DEFAULT_MODULE_ID])
        self.spaces = {INPUT_ENV_SPACES: (obs_space, act_space), INPUT_ENV_SINGLE_SPACES: (obs_space, act_space)}
        self.spaces.update(dict.fromkeys(module_ids, (obs_space, act_space)))
        self._seeded = False  # RLlib's runners seed their envs at the first reset only
        self._device = torch.device("cuda" if self.config.num_gpus_per_env_runner > 0 and torch.cuda.is_available() else "cpu")
        self._weights_seq_no = 0
        self._needs_reset = True
        self._rng = np.random.default_rng(self._seed)
        self._done_episodes: list[tuple[float, int]] = []  # (return, length) of env episodes finished since get_metrics
        if self.worker_index > 0 or self.config.num_env_runners == 0 or self.config.create_env_on_local_worker:
            self.make_env()
        self.make_module()

    # ------------------------------------------------------------------ EnvRunner API
    def assert_healthy(self) -> None:
        """The module exists (and the env, where this runner samples)."""
        assert self.module is not None, "BatchedEnvRunner has no module"

    def make_env(self) -> None:
        """Build the vector env of the config's scenario (``num_envs_per_env_runner`` copies)."""
        if self.vector_env is not None:
            self.vector_env.close()
        self.vector_env = make_vector_env(self.scenario, self.num_envs, self.lcf)
        self._needs_reset = True

    def make_module(self) -> None:
        """Build the inference-only module of the config's one (shared) module on this runner's device."""
        self.module = self.config.get_multi_rl_module_spec(spaces=self.get_spaces(), inference_only=True).build()
        ids = list(self.module.keys())
        if len(ids) != 1:
            raise ValueError(f"the batched env runner steps one shared module, the config has {ids}; allowed: exactly one module")
        self.module_id = ids[0]
        self.module.foreach_module(lambda mid, mod: mod.to(self._device) if isinstance(mod, torch.nn.Module) else mod)

    def get_spaces(self) -> dict[str, Any]:
        """The env spaces and the shared module's (observation, action) spaces."""
        return dict(self.spaces)

    def sample(
        self,
        *,
        num_timesteps: int | None = None,
        num_episodes: int | None = None,
        explore: bool | None = None,
        random_actions: bool = False,
        force_reset: bool = False,
        **kwargs: Any,
    ) -> list[MultiAgentEpisode]:
        """Run the envs in lock step; the ``MultiAgentEpisode`` chunks of the steps taken (see module doc).

        Without arguments: ``rollout_fragment_length`` lock steps. ``num_timesteps``: at least
        that many env steps (whole lock steps). ``num_episodes``: from fresh episodes until that
        many env episodes finished; only finished episodes are returned then.
        """
        if self.vector_env is None:
            raise RuntimeError("this env runner has no env (a local runner beside remote ones); sample on the remote runners")
        explore = self.config.explore if explore is None else explore
        if force_reset or num_episodes is not None or self._needs_reset:
            self._reset()
        if num_episodes is not None:
            episodes: list[MultiAgentEpisode] = []
            while sum(e.is_done for e in episodes) < num_episodes:
                episodes += self._chunk(self.config.get_rollout_fragment_length(self.worker_index), explore, random_actions)
            done_ids = {e.id_ for e in episodes if e.is_done}
            self._needs_reset = True
            return [e for e in episodes if e.id_ in done_ids]  # every chunk of the finished episodes
        steps = self.config.get_rollout_fragment_length(self.worker_index)
        if num_timesteps is not None:
            steps = max(1, math.ceil(num_timesteps / self.num_envs))
        return self._chunk(steps, explore, random_actions)

    def get_metrics(self) -> dict[str, Any]:
        """The sampling metrics since the last call, with the finished episodes' returns and lengths."""
        window = max(1, self.config.metrics_num_episodes_for_smoothing // max(1, self.config.num_env_runners))
        for ret, length in self._done_episodes:
            self.metrics.log_value(EPISODE_LEN_MEAN, length, window=window)
            self.metrics.log_value(EPISODE_RETURN_MEAN, ret, window=window)
            self.metrics.log_value(EPISODE_LEN_MIN, length, reduce="min", window=window)
            self.metrics.log_value(EPISODE_RETURN_MIN, ret, reduce="min", window=window)
            self.metrics.log_value(EPISODE_LEN_MAX, length, reduce="max", window=window)
            self.metrics.log_value(EPISODE_RETURN_MAX, ret, reduce="max", window=window)
        self._done_episodes = []
        return self.metrics.reduce()

    def set_lcf_distribution(self, mean: float, std: float) -> None:
        """CoPO: draw the LCFs of vehicles spawned from now on from N(mean, std)."""
        if self.vector_env is not None:
            self.vector_env.set_lcf_distribution(mean, std)

    def set_start_difficulty(self, difficulty: float) -> None:
        """The arena curriculum's start spread for scenarios generated from now on (``ArenaConfig.start_difficulty``)."""
        if self.vector_env is not None:
            self.vector_env.set_start_difficulty(difficulty)

    def set_num_agents(self, n: int) -> None:
        """A driving curriculum's phase: vehicles at reset of every env's episodes started from now on."""
        if self.vector_env is not None:
            self.vector_env.set_num_agents(n)

    def stop(self) -> None:
        """Release the vector env."""
        if self.vector_env is not None:
            self.vector_env.close()

    # ------------------------------------------------------------------ Checkpointable
    def get_state(self, components: Any = None, *, not_components: Any = None, **kwargs: Any) -> dict[str, Any]:
        """The lifetime env-step count and the module's weights (with their sequence number)."""
        state: dict[str, Any] = {NUM_ENV_STEPS_SAMPLED_LIFETIME: self.num_env_steps_sampled_lifetime}
        if self._check_component(COMPONENT_RL_MODULE, components, not_components):
            state[COMPONENT_RL_MODULE] = self.module.get_state(
                components=self._get_subcomponents(COMPONENT_RL_MODULE, components),
                not_components=self._get_subcomponents(COMPONENT_RL_MODULE, not_components),
                **kwargs,
            )
            state[WEIGHTS_SEQ_NO] = self._weights_seq_no
        return state

    def set_state(self, state: dict[str, Any]) -> None:
        """Take newer module weights (or any with sequence number 0) and the lifetime env-step count."""
        if COMPONENT_RL_MODULE in state:
            seq = state.get(WEIGHTS_SEQ_NO, 0)
            if seq == 0 or self._weights_seq_no < seq:
                module_state = state[COMPONENT_RL_MODULE]
                if isinstance(module_state, ray.ObjectRef):  # remote weight syncs send a reference
                    module_state = ray.get(module_state)
                self.module.set_state(module_state)
            if seq > 0:
                self._weights_seq_no = seq
        if NUM_ENV_STEPS_SAMPLED_LIFETIME in state:
            self.num_env_steps_sampled_lifetime = state[NUM_ENV_STEPS_SAMPLED_LIFETIME]

    def get_ctor_args_and_kwargs(self) -> tuple[tuple, dict[str, Any]]:
        """How to rebuild this runner: its config."""
        return (), {"config": self.config}

    def get_checkpointable_components(self) -> list[tuple[str, Any]]:
        """The module."""
        return [(COMPONENT_RL_MODULE, self.module)]

    # ------------------------------------------------------------------ sampling
    def _reset(self) -> None:
        """Start fresh episodes in every env (seeded at the first reset only, as RLlib's runners do)."""
        env = self.vector_env
        infos = env.reset(None if self._seeded else self._seed)
        self._seeded = True
        n = env.num_slots
        self._life_id: list[str | None] = [None] * n  # SingleAgentEpisode id of each slot's current vehicle
        self._life_t = np.zeros(n, np.int64)  # its agent steps before the current chunk
        self._infos: dict[int, dict[str, Any]] = dict(infos)  # info of each slot's current observation
        for s in infos:
            self._life_id[s] = uuid.uuid4().hex
        self._ep_id = [uuid.uuid4().hex for _ in range(env.num_envs)]
        self._ep_t = np.zeros(env.num_envs, np.int64)  # env steps of each env's episode before the chunk
        self._ep_return = np.zeros(env.num_envs)  # return (all vehicles) and env steps of each env's episode so far
        self._ep_len = np.zeros(env.num_envs, np.int64)
        env.outcomes = dict.fromkeys(OUTCOMES, 0)
        self._needs_reset = False

    def _actions(self, obs: np.ndarray, explore: bool, random_actions: bool, t: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Module-space actions (n, A) of ``obs`` (n, D) and the extra model outputs to store (RLlib's ``GetActions``)."""
        space = self.spaces[self.module_id][1]
        if random_actions:
            return self._rng.uniform(space.low, space.high, (len(obs), *space.shape)).astype(np.float32), {}
        module = self.module[self.module_id]
        batch = {Columns.OBS: torch.from_numpy(obs).to(self._device)}
        with torch.no_grad():
            out = module.forward_exploration(batch, t=t) if explore else module.forward_inference(batch)
            if Columns.ACTIONS not in out:
                dist_cls = module.get_exploration_action_dist_cls() if explore else module.get_inference_action_dist_cls()
                dist = dist_cls.from_logits(out[Columns.ACTION_DIST_INPUTS])
                if not explore:
                    dist = dist.to_deterministic()
                out = dict(out)
                out[Columns.ACTIONS] = dist.sample()
                out.setdefault(Columns.ACTION_LOGP, dist.logp(out[Columns.ACTIONS]))
        arrays = {k: v.detach().cpu().numpy() for k, v in out.items() if isinstance(v, torch.Tensor) and v.shape[:1] == (len(obs),)}
        return arrays.pop(Columns.ACTIONS).astype(np.float32), arrays

    def _chunk(self, steps: int, explore: bool, random_actions: bool) -> list[MultiAgentEpisode]:
        """Run ``steps`` lock steps and return their episode chunks; count the metrics."""
        env = self.vector_env
        n, e_n, d = env.num_slots, env.num_envs, env.obs.shape[1]
        space = self.spaces[self.module_id][1]
        obs_buf = np.zeros((steps + 1, n, d), np.float32)
        num_buf = np.zeros((steps + 1, n), np.int64)
        active = np.zeros((steps, n), bool)
        act_buf = np.zeros((steps, n, *space.shape), np.float32)
        extra: dict[str, np.ndarray] = {}
        reward = np.zeros((steps, n), np.float32)
        term = np.zeros((steps, n), bool)
        trunc = np.zeros((steps, n), bool)
        results: list[VectorStep] = []
        infos_at: list[dict[int, dict[str, Any]]] = [self._infos]
        ep_bounds: list[tuple[int, int]] = []  # (env, step) of every episode end in the chunk
        runners = max(1, self.config.num_env_runners)
        lifetime0 = self.num_env_steps_sampled_lifetime
        for t in range(steps):
            obs_buf[t], num_buf[t], active[t] = env.obs, env.agent_num, env.active
            slots = np.nonzero(active[t])[0]
            actions = np.zeros((n, *space.shape), np.float32)
            if len(slots):
                a, outs = self._actions(obs_buf[t, slots], explore, random_actions, (lifetime0 // runners + t * e_n) * runners)
                act_buf[t, slots] = actions[slots] = a
                for key, value in outs.items():
                    if key not in extra:
                        extra[key] = np.zeros((steps, n, *value.shape[1:]), value.dtype)
                    extra[key][t, slots] = value
            res = env.step(np.clip(actions, space.low, space.high))
            results.append(res)
            reward[t] = res.reward
            over_slot = res.over[env.env_of] & res.acted
            term[t] = res.terminated | over_slot  # RLlib: the step that ends the episode terminates every vehicle in it
            trunc[t] = res.truncated | (over_slot & res.over_truncated[env.env_of])
            infos_at.append({**res.next_infos, **res.born_infos})
            self._ep_return += np.bincount(env.env_of, weights=res.reward, minlength=e_n)
            self._ep_len += 1
            for e in np.nonzero(res.over)[0]:
                ep_bounds.append((int(e), t))
                self._done_episodes.append((float(self._ep_return[e]), int(self._ep_len[e])))
                self._ep_return[e], self._ep_len[e] = 0.0, 0
        obs_buf[steps], num_buf[steps] = env.obs, env.agent_num
        episodes = self._episodes(steps, obs_buf, num_buf, active, act_buf, extra, reward, term, trunc, results, infos_at, ep_bounds)
        self._log_sample_metrics(steps, int(active.sum()), len(ep_bounds))
        return episodes

    def _episodes(
        self,
        steps: int,
        obs_buf: np.ndarray,
        num_buf: np.ndarray,
        active: np.ndarray,
        act_buf: np.ndarray,
        extra: dict[str, np.ndarray],
        reward: np.ndarray,
        term: np.ndarray,
        trunc: np.ndarray,
        results: list[VectorStep],
        infos_at: list[dict[int, dict[str, Any]]],
        ep_bounds: list[tuple[int, int]],
    ) -> list[MultiAgentEpisode]:
        """Build the chunk's episodes from the step arrays, and carry the vehicles' and episodes' state to the next chunk."""
        env = self.vector_env
        spe = env.slots_per_env
        # per env: the episodes the chunk touches, as (first step, last step or None, id, env steps before, truncated)
        episodes_of: list[list[list[Any]]] = [[[0, None, self._ep_id[e], int(self._ep_t[e]), False]] for e in range(env.num_envs)]
        for e, t in ep_bounds:
            current = episodes_of[e][-1]
            current[1], current[4] = t, bool(results[t].over_truncated[e])
            episodes_of[e].append([t + 1, None, uuid.uuid4().hex, 0, False])
        agents_of: dict[str, dict[str, SingleAgentEpisode]] = defaultdict(dict)
        seq = np.full(1, self._weights_seq_no)
        ended = active & (term | trunc)
        carried: dict[int, tuple[str, int]] = {}  # slot -> (life id, agent steps) of vehicles still driving at the end
        for s in np.nonzero(active.any(0))[0].tolist():
            act_t = np.nonzero(active[:, s])[0]
            for run in np.split(act_t, np.searchsorted(act_t, np.nonzero(ended[:, s])[0], side="right")):
                if not len(run):
                    continue
                t0, t1 = int(run[0]), int(run[-1])
                done = bool(ended[t1, s])
                if t0 == 0:  # the vehicle continues from the last chunk (or the reset before it)
                    life_id, t_started = self._life_id[s], int(self._life_t[s])
                else:
                    life_id, t_started = uuid.uuid4().hex, 0
                last_obs = results[t1].next_obs[s] if done else obs_buf[steps, s]
                last_info = results[t1].next_infos[s] if done else infos_at[steps][s]
                length = t1 - t0 + 1
                ep = next(x for x in episodes_of[s // spe] if x[0] <= t0 and (x[1] is None or t0 <= x[1]))
                aid = agent_name(int(num_buf[t0, s]))
                agents_of[ep[2]][aid] = SingleAgentEpisode(
                    id_=life_id,
                    observations=ILB(np.concatenate([obs_buf[t0 : t1 + 1, s], last_obs[None]])),
                    infos=ILB([infos_at[t][s] for t in range(t0, t1 + 1)] + [last_info]),
                    actions=ILB(act_buf[t0 : t1 + 1, s]),
                    rewards=ILB(reward[t0 : t1 + 1, s]),
                    extra_model_outputs={
                        **{k: ILB(v[t0 : t1 + 1, s]) for k, v in extra.items()},
                        WEIGHTS_SEQ_NO: ILB(np.repeat(seq, length)),
                    },
                    terminated=done and bool(term[t1, s]),
                    truncated=done and bool(trunc[t1, s]),
                    t_started=t_started,
                    len_lookback_buffer=0,
                    agent_id=aid,
                    module_id=self.module_id,
                    multi_agent_episode_id=ep[2],
                )
                if not done:  # still driving at the chunk's end: the next chunk continues this life
                    carried[s] = (life_id, t_started + length)
        for s in np.nonzero(env.active)[0].tolist():  # else: born on the chunk's last step
            self._life_id[s], self._life_t[s] = carried.get(s, (uuid.uuid4().hex, 0))
        self._infos = infos_at[steps]
        out = []
        for e, eps in enumerate(episodes_of):
            for first, last, ep_id, t_before, truncated in eps:
                env_steps = (steps if last is None else last + 1) - first
                if env_steps <= 0:
                    continue
                ma = OrderedMultiAgentEpisode(id_=ep_id, env_t_started=t_before, agent_to_module_mapping_fn=self.config.policy_mapping_fn)
                ma.env_t = t_before + env_steps
                ma.agent_episodes = agents_of.get(ep_id, {})
                ma._agent_to_module_mapping = dict.fromkeys(ma.agent_episodes, self.module_id)
                ma.agent_t_started = defaultdict(int, {a: sa.t_started for a, sa in ma.agent_episodes.items()})
                if last is not None:
                    ma.is_terminated, ma.is_truncated = True, truncated
                out.append(ma)
            first, _, ep_id, t_before, _ = eps[-1]
            self._ep_id[e], self._ep_t[e] = ep_id, t_before + steps - first
        return out

    def _log_sample_metrics(self, steps: int, agent_steps: int, episodes: int) -> None:
        """Env, agent and module steps, finished episodes and agent outcomes of one sample call."""
        env = self.vector_env
        env_steps = steps * env.num_envs
        self.num_env_steps_sampled_lifetime += env_steps
        m = self.metrics
        m.log_value(NUM_ENV_STEPS_SAMPLED, env_steps, reduce="sum")
        m.log_value(NUM_ENV_STEPS_SAMPLED_LIFETIME, env_steps, reduce="lifetime_sum", with_throughput=True)
        m.log_value((NUM_AGENT_STEPS_SAMPLED, ALL_AGENTS), agent_steps, reduce="sum")
        m.log_value((NUM_AGENT_STEPS_SAMPLED_LIFETIME, ALL_AGENTS), agent_steps, reduce="lifetime_sum")
        m.log_value((NUM_MODULE_STEPS_SAMPLED, self.module_id), agent_steps, reduce="sum")
        m.log_value((NUM_MODULE_STEPS_SAMPLED_LIFETIME, self.module_id), agent_steps, reduce="lifetime_sum")
        m.log_value(NUM_EPISODES, episodes, reduce="sum")
        m.log_value(NUM_EPISODES_LIFETIME, episodes, reduce="lifetime_sum")
        for key in OUTCOMES:
            m.log_value(f"agents_{key}", env.outcomes[key], reduce="sum")
            env.outcomes[key] = 0
