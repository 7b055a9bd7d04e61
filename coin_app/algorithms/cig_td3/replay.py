"""Joint-step replay buffer for CIG-TD3: the "centralized-critic connector" that injects global state at sample time.

What a CIG-TD3 transition needs (``shared/papers/coin.md`` Eqs. 7-12, Algorithm 1 line 16): the
ego's ``o_i, s_i, a_i, r_i, r^G, d_i, o'_i, s'_i``, the states and actions ``s_{-i}, a_{-i}`` of
the other agents that acted at the same env step t, and the states and observations
``s'_{-i}, o'_{-i}`` of every other agent with an observation at t+1 (the learner computes
``a'_{-i}`` from ``o'_{-i}`` with the target actor).

Why a custom buffer (``shared/reference/rllib_2_60.md`` sections 0 and 4)
--------------------------------------------------------------------------
* RLlib's ``MultiAgentEpisodeReplayBuffer`` crashes when an agent spawns on the last step of a
  chunk (0.1), is unseeded (0.7), is not checkpointed on the new stack (0.8), and its
  ``env_t_to_agent_t`` is wrong for respawned agents (0.11). In independent mode it returns
  one-transition ``SingleAgentEpisode``\\ s, so cross-agent data must be looked up per item
  in Python (option (b) of section 4): slow and tied to the buffer's internals.
* Env-side augmentation (option (a)) stores ``N_max`` other-agent rows inside *every* agent's
  observation (``N_max x d`` floats per agent step, x2 for the next step), cannot show the
  others' actions at t in o_t, and misses agents that spawn at t+1.
* Here every observation (episode, agent, env step) is stored **once** in an observation pool;
  a step index per (episode, env step) lists the pool rows present at that step, and each pool
  row knows the transition that acts from it. Sampling gathers the others through padded index
  tables with a handful of vectorized numpy ``take``\\ s. Alignment is by the env's own
  ``infos["env_step"]`` stamp, so it is exact across respawns, terminations and chunk
  boundaries. Sampling uses the buffer's own seeded ``np.random.Generator``; ``get_state`` /
  ``set_state`` include that generator's state.

Storage (three FIFO rings, each with a watermark: write indices below it are evicted)
----------------------------------------------------------------------------------------
* observation pool, ``obs_capacity`` rows (default ``capacity + capacity // 4 + 64``): obs and
  state, the step entry and column the row sits in, the transition acting from it (o_t) and the
  one arriving in it (o_{t+1}). A transition adds ~1 row (o_{t+1} of step k is o_t of step k+1;
  a life adds one extra terminal row), so the pool does not bind before the transition ring
  unless lives are shorter than ~4 steps.
* transitions, ``capacity`` slots: pool write indices of o_t and o_{t+1}, step-entry write
  indices of t and t+1, action, rewards, flags, (episode, agent, env step).
* step entries, ``step_capacity`` (default ``capacity // 2 + 64``, enough for >= 2 agents per
  step): ``max_others + 1`` pool rows (int32) per (episode, env step). Pass
  ``step_capacity=capacity`` for scenarios with a single agent per step.

Memory per transition (float32 obs/state, ``O`` = obs_dim, ``S`` = state_dim, ``A`` = act_dim,
``M`` = max_others + 1), allocated up front with the default sizes: pool ``1.25 x (4 (O + S) + 24)``
bytes, transition ``4 A + 75`` bytes, step entries ``0.5 x (4 M + 20)`` bytes. With O=91, S=10, A=2,
M=48: 535 + 83 + 106 = ~725 bytes, ~140 MiB for 200k transitions (:attr:`JointStepReplayBuffer.nbytes`).
In use with 30 agents per step: ~520 bytes (one pool row, one transition, 1/29 of an entry).
Env-side augmentation would need ``2 x N x (O + S + A)`` floats, ~40 KB per agent step at N=47.

Completeness rule (why fresh transitions are not sampleable at once)
---------------------------------------------------------------------
The others at t+1 include agents that spawn at t+1. When a chunk is cut at env step t+1, a
spawned agent's first observation only arrives with the *next* chunk (RLlib puts a
``SingleAgentEpisode`` with one observation and no action in the first chunk, which carries
no transition). So a transition acting at env step t becomes sampleable only once data of
env step t+2 of its episode has been added (the chunk covering t+1 -> t+2 is in) or the
episode has ended (``MultiAgentEpisode.is_done``; the env adapter drops spawns in the last
step). ``len(buffer)`` counts only sampleable transitions. ``add`` expects whole chunks, as
``MultiAgentEnvRunner.sample()`` returns them (all agents of an episode for the same env steps
in one call), in env-step order per episode.

Eviction: a transition whose o_t / o_{t+1} pool row or whose step entry (t or t+1) was
overwritten is never sampled again; another agent whose row (or acting transition) was
evicted is masked out of ``others_*`` / ``next_others_*``.
"""

from __future__ import annotations

import hashlib
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

_I64_MASK = (1 << 63) - 1
_AGENT_RE = re.compile(r"^agent_?(\d+)$")
STATE_VERSION = 1


def episode_key(episode_id: str) -> int:
    """Stable non-negative int64 key of a multi-agent episode id string (same on every process)."""
    return int.from_bytes(hashlib.blake2b(str(episode_id).encode(), digest_size=8).digest(), "little") & _I64_MASK


def agent_key(agent_id: Any) -> int:
    """Int key of an agent id: ``N`` for ``"agentN"`` / ``"agent_N"`` / int ``N``, else a stable 63-bit hash."""
    if isinstance(agent_id, (int, np.integer)) and not isinstance(agent_id, bool):
        return int(agent_id)
    m = _AGENT_RE.match(str(agent_id))
    if m:
        return int(m.group(1))
    return int.from_bytes(hashlib.blake2b(str(agent_id).encode(), digest_size=8).digest(), "little") & _I64_MASK


@dataclass
class TransitionBatch:
    """Per-agent transitions (one row each) plus the keys of episodes that ended in this batch."""

    episode: np.ndarray  # (n,) int64 episode key (see episode_key)
    agent: np.ndarray  # (n,) int64 agent key (see agent_key)
    env_step: np.ndarray  # (n,) int64 env step of o_t (infos["env_step"])
    obs: np.ndarray  # (n, O) float32 o_t
    state: np.ndarray  # (n, S) float32 s_t (infos["state"])
    actions: np.ndarray  # (n, A) float32 a_t
    rewards: np.ndarray  # (n,) float32 r_t
    global_rewards: np.ndarray  # (n,) float32 r^G_t (infos["global_reward"] of o_{t+1})
    terminateds: np.ndarray  # (n,) bool
    truncateds: np.ndarray  # (n,) bool
    next_obs: np.ndarray  # (n, O) float32 o_{t+1}
    next_state: np.ndarray  # (n, S) float32 s_{t+1}
    ended_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (k,) int64

    def __len__(self) -> int:
        """Number of transitions."""
        return int(self.episode.shape[0])

    @classmethod
    def empty(cls, obs_dim: int, state_dim: int = 10, act_dim: int = 2) -> TransitionBatch:
        """A batch without transitions."""
        z = np.zeros(0, np.int64)
        f = np.zeros(0, np.float32)
        b = np.zeros(0, bool)
        return cls(
            episode=z,
            agent=z.copy(),
            env_step=z.copy(),
            obs=np.zeros((0, obs_dim), np.float32),
            state=np.zeros((0, state_dim), np.float32),
            actions=np.zeros((0, act_dim), np.float32),
            rewards=f,
            global_rewards=f.copy(),
            terminateds=b,
            truncateds=b.copy(),
            next_obs=np.zeros((0, obs_dim), np.float32),
            next_state=np.zeros((0, state_dim), np.float32),
        )

    @classmethod
    def concat(cls, batches: Iterable[TransitionBatch]) -> TransitionBatch:
        """Concatenate batches (row order kept; ended-episode keys deduplicated)."""
        batches = list(batches)
        if not batches:
            raise ValueError("TransitionBatch.concat needs at least one batch")
        out = {f.name: np.concatenate([getattr(b, f.name) for b in batches]) for f in fields(cls)}
        out["ended_episodes"] = np.unique(out["ended_episodes"]).astype(np.int64)
        return cls(**out)


def _info_values(infos: list[Mapping[str, Any]], key: str, agent_id: Any, episode_id: str) -> list[Any]:
    try:
        return [info[key] for info in infos]
    except (KeyError, TypeError) as err:
        raise KeyError(f"infos of agent {agent_id!r} in episode {episode_id} lack {key!r}; the env must put {key!r} in every info") from err


def episodes_to_transitions(episodes: Iterable[Any]) -> TransitionBatch:
    """Convert ``MultiAgentEpisode`` chunks from ``MultiAgentEnvRunner.sample()`` into per-agent transitions.

    Each agent's ``SingleAgentEpisode`` in a chunk holds ``len(sa)`` actions and ``len(sa) + 1``
    observations (the first one is the last observation of the previous chunk). Env steps come
    from ``infos["env_step"]`` (never from RLlib's env/agent time mapping), states from
    ``infos["state"]`` and the global reward of a transition from ``infos["global_reward"]`` of
    its next observation. Only an agent's last transition in a chunk can be done; RLlib marks
    agents alive at the end of an episode as terminated *and* truncated (reference 0.5) while the
    env never reports both, so ``terminated`` is stored as ``is_terminated and not is_truncated``.
    Agents with no action in a chunk (spawned on its last step, or done in an earlier chunk) give
    no transition. Episode ids are mapped to ints with :func:`episode_key`.
    """
    cols: dict[str, list[np.ndarray]] = {
        k: [] for k in ("episode", "agent", "env_step", "obs", "state", "actions", "rewards", "g", "term", "trunc")
    }
    ended: list[int] = []
    for ma in episodes:
        ekey = episode_key(ma.id_)
        if ma.is_done:
            ended.append(ekey)
        for aid, sa in ma.agent_episodes.items():
            n = len(sa)
            if n == 0:
                continue
            obs = np.asarray(sa.get_observations(), dtype=np.float32).reshape(n + 1, -1)
            infos = sa.get_infos()
            if len(infos) != n + 1:
                raise ValueError(f"agent {aid!r} of episode {ma.id_}: {len(infos)} infos for {n + 1} observations")
            steps = np.asarray(_info_values(infos, "env_step", aid, ma.id_), dtype=np.int64)
            if np.any(np.diff(steps) != 1):
                raise ValueError(
                    f"agent {aid!r} of episode {ma.id_}: env steps of consecutive observations are not consecutive: {steps.tolist()}"
                )
            states = np.asarray(_info_values(infos, "state", aid, ma.id_), dtype=np.float32).reshape(n + 1, -1)
            g = np.asarray(_info_values(infos[1:], "global_reward", aid, ma.id_), dtype=np.float32)
            acts = np.asarray(sa.get_actions(), dtype=np.float32).reshape(n, -1)
            rews = np.asarray(sa.get_rewards(), dtype=np.float32).reshape(n)
            trunc = np.zeros(n, bool)
            term = np.zeros(n, bool)
            trunc[-1] = bool(sa.is_truncated)
            term[-1] = bool(sa.is_terminated) and not trunc[-1]
            cols["episode"].append(np.full(n, ekey, np.int64))
            cols["agent"].append(np.full(n, agent_key(aid), np.int64))
            cols["env_step"].append(steps[:-1])
            cols["obs"].append(obs)
            cols["state"].append(states)
            cols["actions"].append(acts)
            cols["rewards"].append(rews)
            cols["g"].append(g)
            cols["term"].append(term)
            cols["trunc"].append(trunc)
    ended_arr = np.unique(np.asarray(ended, dtype=np.int64))
    if not cols["episode"]:
        batch = TransitionBatch.empty(0, 0, 0)
        batch.ended_episodes = ended_arr
        return batch
    obs_all = cols["obs"]
    st_all = cols["state"]
    return TransitionBatch(
        episode=np.concatenate(cols["episode"]),
        agent=np.concatenate(cols["agent"]),
        env_step=np.concatenate(cols["env_step"]),
        obs=np.concatenate([o[:-1] for o in obs_all]),
        state=np.concatenate([s[:-1] for s in st_all]),
        actions=np.concatenate(cols["actions"]),
        rewards=np.concatenate(cols["rewards"]),
        global_rewards=np.concatenate(cols["g"]),
        terminateds=np.concatenate(cols["term"]),
        truncateds=np.concatenate(cols["trunc"]),
        next_obs=np.concatenate([o[1:] for o in obs_all]),
        next_state=np.concatenate([s[1:] for s in st_all]),
        ended_episodes=ended_arr,
    )


class JointStepReplayBuffer:
    """FIFO replay of per-agent transitions whose samples carry the other agents at t and t+1 (see module doc).

    ``capacity`` counts transitions; ``max_others`` (N) is the most other agents with an
    observation at one env step (a step with more raises ``ValueError`` in :meth:`add`).
    ``obs_capacity`` (pool rows) and ``step_capacity`` (step entries) default to sizes that
    let the transition ring bind first (module doc). Sampling is uniform with replacement over
    the sampleable transitions, driven by ``np.random.default_rng(seed)``.
    """

    _ARRAYS = (
        "_pool_obs",
        "_pool_state",
        "_pool_owner",
        "_pool_tr_obs",
        "_pool_tr_next",
        "_tr_obs",
        "_tr_next",
        "_tr_entry_t",
        "_tr_entry_t1",
        "_tr_action",
        "_tr_reward",
        "_tr_greward",
        "_tr_term",
        "_tr_trunc",
        "_tr_step",
        "_tr_episode",
        "_tr_agent",
        "_ok",
        "_step_rows",
        "_step_count",
        "_step_episode",
        "_step_t",
    )
    _COUNTERS = ("_pool_written", "_pool_wm", "_tr_written", "_tr_wm", "_step_written", "_step_wm", "_num_ok")

    def __init__(
        self,
        capacity: int,
        obs_dim: int,
        state_dim: int = 10,
        act_dim: int = 2,
        max_others: int = 47,
        seed: int | None = 0,
        *,
        obs_capacity: int | None = None,
        step_capacity: int | None = None,
    ):
        for name, v in (
            ("capacity", capacity),
            ("obs_dim", obs_dim),
            ("state_dim", state_dim),
            ("act_dim", act_dim),
            ("max_others", max_others),
        ):
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v < (0 if name == "max_others" else 1):
                raise ValueError(f"{name} must be an integer >= {0 if name == 'max_others' else 1}, got {v!r}")
        self.capacity = C = int(capacity)
        self.obs_capacity = P = int(obs_capacity) if obs_capacity is not None else C + C // 4 + 64
        self.step_capacity = K = int(step_capacity) if step_capacity is not None else C // 2 + 64
        if P < 2 or K < 2:
            raise ValueError(f"obs_capacity and step_capacity must be >= 2, got {P} and {K}")
        self.obs_dim, self.state_dim, self.act_dim = int(obs_dim), int(state_dim), int(act_dim)
        self.max_others = N = int(max_others)
        self.seed = seed
        M = N + 1
        O, S, A = self.obs_dim, self.state_dim, self.act_dim
        self._rng = np.random.default_rng(seed)
        # observation pool; row P is an all-zero padding row that masked gathers read
        self._pool_obs = np.zeros((P + 1, O), np.float32)
        self._pool_state = np.zeros((P + 1, S), np.float32)
        self._pool_owner = np.full(P + 1, -1, np.int64)  # entry write index * (max_others + 1) + column of the row
        self._pool_tr_obs = np.full(P + 1, -1, np.int64)  # transition acting from this row (its o_t)
        self._pool_tr_next = np.full(P + 1, -1, np.int64)  # transition whose o_{t+1} is this row
        # transitions; action row C is an all-zero padding row
        self._tr_obs = np.zeros(C, np.int64)  # pool write index of o_t
        self._tr_next = np.zeros(C, np.int64)  # pool write index of o_{t+1}
        self._tr_entry_t = np.zeros(C, np.int64)  # step-entry write index of (episode, t)
        self._tr_entry_t1 = np.zeros(C, np.int64)  # step-entry write index of (episode, t+1)
        self._tr_action = np.zeros((C + 1, A), np.float32)
        self._tr_reward = np.zeros(C, np.float32)
        self._tr_greward = np.zeros(C, np.float32)
        self._tr_term = np.zeros(C, bool)
        self._tr_trunc = np.zeros(C, bool)
        self._tr_step = np.zeros(C, np.int64)
        self._tr_episode = np.zeros(C, np.int64)
        self._tr_agent = np.zeros(C, np.int64)
        self._ok = np.zeros(C, bool)  # slot holds a valid, complete (sampleable) transition
        # step entries: pool rows (physical) present at (episode, env step); P = empty column
        self._step_rows = np.full((K, M), P, np.int32)
        self._step_count = np.zeros(K, np.int32)
        self._step_episode = np.zeros(K, np.int64)
        self._step_t = np.zeros(K, np.int64)
        # write counters and eviction watermarks (write indices < watermark are evicted)
        self._pool_written = self._pool_wm = 0
        self._tr_written = self._tr_wm = 0
        self._step_written = self._step_wm = 0
        self._num_ok = 0
        self._pending = np.zeros(0, np.int64)  # valid transitions waiting for their step t+1 to be complete
        self._entry_of: dict[tuple[int, int], int] = {}  # (episode, env step) -> step-entry write index
        self._last_obs: dict[tuple[int, int], tuple[int, int]] = {}  # (episode, agent) -> (env step, pool write index)
        self._episodes: dict[int, list[int]] = {}  # episode -> [frontier env step, ended]
        self._last_obs_prune_at = 1024

    # ------------------------------------------------------------------ public API
    def __len__(self) -> int:
        """Number of sampleable transitions (stored, complete, not invalidated by eviction)."""
        return int(self._num_ok)

    @property
    def num_added(self) -> int:
        """Transitions added over the buffer's lifetime."""
        return int(self._tr_written)

    @property
    def num_obs_added(self) -> int:
        """Observation-pool rows written over the buffer's lifetime (one per distinct (episode, agent, env step))."""
        return int(self._pool_written)

    @property
    def num_pending(self) -> int:
        """Stored transitions waiting for their env step t+1 to be complete."""
        return int(self._pending.shape[0])

    @property
    def nbytes(self) -> int:
        """Bytes held by the buffer's arrays."""
        return int(sum(getattr(self, name).nbytes for name in self._ARRAYS))

    def add(self, batch: TransitionBatch) -> None:
        """Store a batch of whole chunks (see module doc); raises ``ValueError`` on inconsistent input, storing nothing."""
        n = len(batch)
        self._check_batch(batch)
        if n > self.capacity:
            raise ValueError(f"batch of {n} transitions exceeds the buffer capacity {self.capacity}; add it in parts of whole chunks")
        if n:
            self._add_transitions(batch)
        for key in np.asarray(batch.ended_episodes, dtype=np.int64).tolist():
            self._episodes.setdefault(key, [-1, 0])[1] = 1
        self._update_pending(np.arange(self._tr_written - n, self._tr_written, dtype=np.int64))

    def add_episodes(self, episodes: Iterable[Any]) -> TransitionBatch:
        """Convert ``MultiAgentEnvRunner.sample()`` output with :func:`episodes_to_transitions` and add it; returns the batch."""
        batch = episodes_to_transitions(episodes)
        self.add(batch)
        return batch

    def sample(self, batch_size: int) -> dict[str, np.ndarray]:
        """Uniformly sample ``batch_size`` transitions (with replacement) with the other agents at t and t+1 gathered."""
        if not isinstance(batch_size, (int, np.integer)) or isinstance(batch_size, bool) or batch_size < 1:
            raise ValueError(f"batch_size must be an integer >= 1, got {batch_size!r}")
        if batch_size > self._num_ok:
            raise ValueError(
                f"cannot sample {batch_size} transitions: only {self._num_ok} are sampleable "
                f"({self._tr_written - self._tr_wm} stored, {self.num_pending} waiting for env step t+2)"
            )
        slots = self._draw(int(batch_size))
        return self._gather(slots)

    def get_state(self) -> dict[str, Any]:
        """Full state (copies of all arrays, index maps, counters, RNG state) for checkpointing."""
        state: dict[str, Any] = {"version": STATE_VERSION, "config": self._config()}
        for name in self._ARRAYS:
            state[name] = getattr(self, name).copy()
        for name in self._COUNTERS:
            state[name] = int(getattr(self, name))
        state["_pending"] = self._pending.copy()
        state["_entry_of"] = np.array([[e, t, w] for (e, t), w in self._entry_of.items()], np.int64).reshape(-1, 3)
        state["_last_obs"] = np.array([[e, a, t, w] for (e, a), (t, w) in self._last_obs.items()], np.int64).reshape(-1, 4)
        state["_episodes"] = np.array([[e, f, d] for e, (f, d) in self._episodes.items()], np.int64).reshape(-1, 3)
        state["_last_obs_prune_at"] = int(self._last_obs_prune_at)
        state["rng"] = self._rng.bit_generator.state
        return state

    def set_state(self, state: Mapping[str, Any]) -> None:
        """Restore a state from :meth:`get_state` (the buffer's configuration must match)."""
        if state.get("version") != STATE_VERSION:
            raise ValueError(f"replay state version {state.get('version')!r} != {STATE_VERSION}")
        if dict(state["config"]) != self._config():
            raise ValueError(f"replay state was saved with config {dict(state['config'])}, this buffer has {self._config()}")
        for name in self._ARRAYS:
            arr = np.asarray(state[name])
            cur = getattr(self, name)
            if arr.shape != cur.shape:
                raise ValueError(f"replay state array {name} has shape {arr.shape}, expected {cur.shape}")
            cur[...] = arr
        for name in self._COUNTERS:
            setattr(self, name, int(state[name]))
        self._pending = np.asarray(state["_pending"], np.int64).copy()
        self._entry_of = {(int(e), int(t)): int(w) for e, t, w in np.asarray(state["_entry_of"]).reshape(-1, 3)}
        self._last_obs = {(int(e), int(a)): (int(t), int(w)) for e, a, t, w in np.asarray(state["_last_obs"]).reshape(-1, 4)}
        self._episodes = {int(e): [int(f), int(d)] for e, f, d in np.asarray(state["_episodes"]).reshape(-1, 3)}
        self._last_obs_prune_at = int(state["_last_obs_prune_at"])
        self._rng = np.random.default_rng()
        self._rng.bit_generator.state = state["rng"]

    # ------------------------------------------------------------------ adding
    def _config(self) -> dict[str, int]:
        return {
            "capacity": self.capacity,
            "obs_capacity": self.obs_capacity,
            "step_capacity": self.step_capacity,
            "obs_dim": self.obs_dim,
            "state_dim": self.state_dim,
            "act_dim": self.act_dim,
            "max_others": self.max_others,
        }

    def _check_batch(self, b: TransitionBatch) -> None:
        n = len(b)
        if n == 0:  # e.g. only episodes that ended without a new transition; column widths are unknown then
            return
        want = {
            "episode": (n,),
            "agent": (n,),
            "env_step": (n,),
            "obs": (n, self.obs_dim),
            "state": (n, self.state_dim),
            "actions": (n, self.act_dim),
            "rewards": (n,),
            "global_rewards": (n,),
            "terminateds": (n,),
            "truncateds": (n,),
            "next_obs": (n, self.obs_dim),
            "next_state": (n, self.state_dim),
        }
        for name, shape in want.items():
            got = np.shape(getattr(b, name))
            if got != shape:
                raise ValueError(
                    f"TransitionBatch.{name} has shape {got}, expected {shape} "
                    f"(obs_dim={self.obs_dim}, state_dim={self.state_dim}, act_dim={self.act_dim})"
                )
        if n and np.min(b.env_step) < 0:
            raise ValueError(f"env_step must be >= 0, got min {int(np.min(b.env_step))}")

    def _add_transitions(self, b: TransitionBatch) -> None:
        C, P, K, M = self.capacity, self.obs_capacity, self.step_capacity, self.max_others + 1
        # Layout order: episodes by first appearance in the batch (not by key: keys hash RLlib's random
        # uuids, and a key-dependent layout would make same-seed runs sample differently), agent, step.
        ep_raw = np.asarray(b.episode, np.int64)
        _, first_idx, ep_inv = np.unique(ep_raw, return_index=True, return_inverse=True)
        rank_key = ep_raw[np.sort(first_idx)]  # episode key of each rank
        ep_rank_raw = np.argsort(np.argsort(first_idx))[ep_inv]
        order = np.lexsort((b.env_step, b.agent, ep_rank_raw))
        ep_rank = ep_rank_raw[order]
        ep = ep_raw[order]
        ag = np.asarray(b.agent, np.int64)[order]
        t = np.asarray(b.env_step, np.int64)[order]
        term = np.asarray(b.terminateds, bool)[order]
        trunc = np.asarray(b.truncateds, bool)[order]
        done = term | trunc
        n = ep.shape[0]
        same = np.zeros(n, bool)
        same[1:] = (ep[1:] == ep[:-1]) & (ag[1:] == ag[:-1])
        dup = same[1:] & (t[1:] == t[:-1])
        if dup.any():
            k = int(np.flatnonzero(dup)[0])
            raise ValueError(f"duplicate transition: episode {ep[k]}, agent {ag[k]}, env step {t[k]} appears twice in the batch")
        after_done = same[1:] & done[:-1]
        if after_done.any():
            k = int(np.flatnonzero(after_done)[0])
            raise ValueError(f"agent {ag[k]} of episode {ep[k]} acts at env step {t[k + 1]} after its done transition at env step {t[k]}")
        chain_prev = np.zeros(n, bool)  # o_t of k is o_{t+1} of k-1 (same agent, consecutive steps)
        chain_prev[1:] = same[1:] & (t[1:] == t[:-1] + 1)
        chain_next = np.zeros(n, bool)
        chain_next[:-1] = chain_prev[1:]
        # o_t of a chunk's first transition is normally the o_{t+1} stored with the previous chunk
        reuse_w = np.full(n, -1, np.int64)
        for k in np.flatnonzero(~chain_prev).tolist():
            hit = self._last_obs.get((int(ep[k]), int(ag[k])))
            if hit is not None and hit[0] == t[k] and hit[1] >= self._pool_wm and self._pool_owner[hit[1] % P] // M >= self._step_wm:
                reuse_w[k] = hit[1]
        # plan rows and step entries; drop reuses of rows / entries that this very add evicts (tiny capacities)
        new_n_idx = np.flatnonzero(~chain_next)
        while True:
            new_t_idx = np.flatnonzero(reuse_w < 0)
            R = new_t_idx.shape[0] + new_n_idx.shape[0]
            if R > P:
                raise ValueError(f"batch needs {R} new observation rows > obs_capacity {P}; add it in smaller parts")
            pool_wm_after = max(self._pool_wm, self._pool_written + R - P)
            row_rank = np.concatenate([ep_rank[new_t_idx], ep_rank[new_n_idx]])
            row_t = np.concatenate([t[new_t_idx], t[new_n_idx] + 1])
            pairs, inv = _unique_pairs(row_rank, row_t)
            pairs[:, 0] = rank_key[pairs[:, 0]]  # (episode key, env step), in layout order
            existing = np.array([self._entry_of.get((int(e), int(s)), -1) for e, s in pairs.tolist()], np.int64).reshape(-1)
            is_new = existing < self._step_wm
            while True:  # entries that this add's allocations would evict count as new as well
                step_wm_after = max(self._step_wm, self._step_written + int(is_new.sum()) - K)
                more = ~is_new & (existing < step_wm_after)
                if not more.any():
                    break
                is_new |= more
            if int(is_new.sum()) > K:
                raise ValueError(f"batch needs {int(is_new.sum())} new step entries > step_capacity {K}; add it in smaller parts")
            reused = reuse_w >= 0
            bad = reused & ((reuse_w < pool_wm_after) | (self._pool_owner[reuse_w % P] // M < step_wm_after))
            if not bad.any():
                break
            reuse_w[bad] = -1
        # columns of the new rows in their entries; overflow check before any mutation
        entry_w = existing.copy()
        entry_w[is_new] = self._step_written + np.arange(int(is_new.sum()), dtype=np.int64)
        base = np.where(is_new, 0, self._step_count[np.maximum(existing, 0) % K]).astype(np.int64)
        counts = np.bincount(inv, minlength=pairs.shape[0])
        total = base + counts
        if (total > M).any():
            j = int(np.argmax(total))
            raise ValueError(
                f"env step {int(pairs[j, 1])} of episode {int(pairs[j, 0])} has {int(total[j])} agents with an observation "
                f"(ego + {int(total[j]) - 1} others) but max_others={self.max_others}; raise max_others to at least {int(total[j]) - 1}"
            )
        row_order = np.argsort(inv, kind="stable")
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        rank = np.empty(R, np.int64)
        rank[row_order] = np.arange(R) - np.repeat(starts, counts)
        row_col = base[inv] + rank
        row_entry = entry_w[inv]

        # ---- mutation starts here: evictions
        if pool_wm_after > self._pool_wm:
            ev = np.arange(self._pool_wm, pool_wm_after, dtype=np.int64) % P
            self._invalidate(np.concatenate([self._pool_tr_obs[ev], self._pool_tr_next[ev]]))
            self._pool_wm = pool_wm_after
        if step_wm_after > self._step_wm:
            ev_w = np.arange(self._step_wm, step_wm_after, dtype=np.int64)
            ev_s = ev_w % K
            rows = self._step_rows[ev_s]
            live = self._pool_owner[rows] == ev_w[:, None] * M + np.arange(M)[None, :]
            rows = rows[live]
            self._invalidate(np.concatenate([self._pool_tr_obs[rows], self._pool_tr_next[rows]]))
            for e, s in zip(self._step_episode[ev_s].tolist(), self._step_t[ev_s].tolist()):
                if self._entry_of.get((e, s), -2) < step_wm_after:
                    self._entry_of.pop((e, s), None)
            self._step_wm = step_wm_after
        # transitions are laid out step-major (episode, env step, agent) so that the ones acting at one
        # step are adjacent in the ring (sampling gathers them together)
        tr_w = np.empty(n, np.int64)
        tr_w[np.lexsort((ag, t, ep_rank))] = self._tr_written + np.arange(n, dtype=np.int64)
        tr_wm_after = max(self._tr_wm, self._tr_written + n - C)
        if tr_wm_after > self._tr_wm:
            self._invalidate(np.arange(self._tr_wm, tr_wm_after, dtype=np.int64))
            self._tr_wm = tr_wm_after
        # ---- step entries
        new_slots = entry_w[is_new] % K
        self._step_rows[new_slots] = P
        self._step_count[new_slots] = 0
        self._step_episode[new_slots] = pairs[is_new, 0]
        self._step_t[new_slots] = pairs[is_new, 1]
        for (e, s), w in zip(pairs[is_new].tolist(), entry_w[is_new].tolist()):
            self._entry_of[(e, s)] = w
        self._step_written += int(is_new.sum())
        # ---- pool rows
        row_w = np.empty(R, np.int64)  # rows of one step are adjacent in the pool (locality when sampling)
        row_w[row_order] = self._pool_written + np.arange(R, dtype=np.int64)
        phys = row_w % P
        self._pool_obs[phys[: new_t_idx.shape[0]]] = np.asarray(b.obs, np.float32)[order][new_t_idx]
        self._pool_obs[phys[new_t_idx.shape[0] :]] = np.asarray(b.next_obs, np.float32)[order][new_n_idx]
        self._pool_state[phys[: new_t_idx.shape[0]]] = np.asarray(b.state, np.float32)[order][new_t_idx]
        self._pool_state[phys[new_t_idx.shape[0] :]] = np.asarray(b.next_state, np.float32)[order][new_n_idx]
        self._pool_owner[phys] = row_entry * M + row_col
        self._pool_tr_obs[phys] = -1
        self._pool_tr_next[phys] = -1
        self._pool_written += R
        self._step_rows[row_entry % K, row_col] = phys
        ent_slots = entry_w % K
        self._step_count[ent_slots] = total
        # ---- transitions
        obs_w = reuse_w.copy()
        obs_w[new_t_idx] = row_w[: new_t_idx.shape[0]]
        next_w = np.empty(n, np.int64)
        next_w[new_n_idx] = row_w[new_t_idx.shape[0] :]
        cn = np.flatnonzero(chain_next)
        next_w[cn] = obs_w[cn + 1]
        slots = tr_w % C
        self._tr_obs[slots] = obs_w
        self._tr_next[slots] = next_w
        self._tr_entry_t[slots] = self._pool_owner[obs_w % P] // M
        self._tr_entry_t1[slots] = self._pool_owner[next_w % P] // M
        self._tr_action[slots] = np.asarray(b.actions, np.float32)[order]
        self._tr_reward[slots] = np.asarray(b.rewards, np.float32)[order]
        self._tr_greward[slots] = np.asarray(b.global_rewards, np.float32)[order]
        self._tr_term[slots] = term
        self._tr_trunc[slots] = trunc
        self._tr_step[slots] = t
        self._tr_episode[slots] = ep
        self._tr_agent[slots] = ag
        self._ok[slots] = False
        self._pool_tr_obs[obs_w % P] = tr_w
        self._pool_tr_next[next_w % P] = tr_w
        self._tr_written += n
        # ---- per-agent last observation (the next chunk's first o_t) and episode frontiers
        last = np.flatnonzero(~np.concatenate([same[1:], [False]]))
        for e, a, s, w, d in zip(ep[last].tolist(), ag[last].tolist(), t[last].tolist(), next_w[last].tolist(), done[last].tolist()):
            if d:
                self._last_obs.pop((e, a), None)
            else:
                self._last_obs[(e, a)] = (s + 1, w)
        ep_start = np.flatnonzero(np.concatenate([[True], ep[1:] != ep[:-1]]))  # episodes are contiguous
        ep_max = np.maximum.reduceat(t, ep_start) + 1
        for e, f in zip(ep[ep_start].tolist(), ep_max.tolist()):
            rec = self._episodes.setdefault(e, [-1, 0])
            rec[0] = max(rec[0], f)
        if len(self._last_obs) > self._last_obs_prune_at:
            self._last_obs = {k: v for k, v in self._last_obs.items() if v[1] >= self._pool_wm}
            self._last_obs_prune_at = max(1024, 2 * len(self._last_obs))

    def _valid(self, tw: np.ndarray) -> np.ndarray:
        """Whether transitions (write indices) and all rows / entries they reference are still stored."""
        s = tw % self.capacity
        return (
            (tw >= self._tr_wm)
            & (tw < self._tr_written)
            & (self._tr_obs[s] >= self._pool_wm)
            & (self._tr_next[s] >= self._pool_wm)
            & (self._tr_entry_t[s] >= self._step_wm)
            & (self._tr_entry_t1[s] >= self._step_wm)
        )

    def _invalidate(self, tw: np.ndarray) -> None:
        """Make transitions (write indices; -1 and already evicted ones ignored) unsampleable."""
        tw = tw[tw >= max(self._tr_wm, 0)]
        if tw.shape[0]:
            slots = np.unique(tw % self.capacity)
            self._num_ok -= int(self._ok[slots].sum())
            self._ok[slots] = False

    def _update_pending(self, new_tw: np.ndarray) -> None:
        """Mark pending transitions whose env step t+1 is complete as sampleable; keep the rest pending."""
        cand = np.concatenate([self._pending, new_tw])
        cand = cand[self._valid(cand)]
        if cand.shape[0]:
            s = cand % self.capacity
            eps = self._tr_episode[s]
            u, inv = np.unique(eps, return_inverse=True)
            recs = [self._episodes.get(e, [-1, 0]) for e in u.tolist()]
            frontier = np.array([r[0] for r in recs], np.int64)[inv]
            ended = np.array([r[1] for r in recs], bool)[inv]
            complete = ended | (self._tr_step[s] + 2 <= frontier)
            done_slots = s[complete]
            self._num_ok += int((~self._ok[done_slots]).sum())
            self._ok[done_slots] = True
            cand = cand[~complete]
        self._pending = cand.astype(np.int64)
        for e in [e for e, r in self._episodes.items() if r[1]]:
            del self._episodes[e]  # every transition of an ended episode is complete now

    # ------------------------------------------------------------------ sampling
    def _draw(self, B: int) -> np.ndarray:
        """``B`` ring slots drawn uniformly (with replacement) from the sampleable ones."""
        filled = min(self._tr_written, self.capacity)
        frac = self._num_ok / filled
        if frac >= 0.5:  # rejection sampling: exact uniform over ok slots, O(B)
            parts, got = [], 0
            while got < B:
                cand = self._rng.integers(0, filled, size=int((B - got) / frac * 1.1) + 16)
                cand = cand[self._ok[cand]][: B - got]
                parts.append(cand)
                got += cand.shape[0]
            return np.concatenate(parts)
        ok = np.flatnonzero(self._ok[:filled])
        return ok[self._rng.integers(0, ok.shape[0], size=B)]

    def _gather(self, slots: np.ndarray) -> dict[str, np.ndarray]:
        """Columns of the transitions in ``slots`` with the others at t and t+1 (padded to max_others, masked)."""
        C, P, K, N, M = self.capacity, self.obs_capacity, self.step_capacity, self.max_others, self.max_others + 1
        tw = self._tr_written - 1 - (self._tr_written - 1 - slots) % C  # write index held by each slot
        if not self._valid(tw).all():  # cheap guard against internal inconsistencies
            raise RuntimeError("internal error: a sampled transition references evicted data")
        r0 = self._tr_obs[slots] % P
        r1 = self._tr_next[slots] % P
        e0 = self._tr_entry_t[slots]
        e1 = self._tr_entry_t1[slots]
        shift = np.arange(N)[None, :]
        out: dict[str, np.ndarray] = {
            "obs": self._pool_obs[r0],
            "state": self._pool_state[r0],
            "actions": self._tr_action[slots],
            "rewards": self._tr_reward[slots],
            "global_rewards": self._tr_greward[slots],
            "terminateds": self._tr_term[slots],
            "truncateds": self._tr_trunc[slots],
            "new_obs": self._pool_obs[r1],
            "new_state": self._pool_state[r1],
        }
        # others acting at t: rows of entry (episode, t) without the ego's column
        cols0 = shift + (shift >= (self._pool_owner[r0] % M)[:, None])
        rows0 = np.take_along_axis(self._step_rows[e0 % K], cols0, axis=1)
        ok0 = self._pool_owner[rows0] == e0[:, None] * M + cols0
        tr0 = self._pool_tr_obs[rows0]
        ok0 &= tr0 >= self._tr_wm
        ok0 &= tr0 >= 0
        out["others_state"] = self._pool_state[np.where(ok0, rows0, P)]
        out["others_actions"] = self._tr_action[np.where(ok0, tr0 % C, C)]
        out["others_mask"] = ok0
        # every other agent with an observation at t+1
        cols1 = shift + (shift >= (self._pool_owner[r1] % M)[:, None])
        rows1 = np.take_along_axis(self._step_rows[e1 % K], cols1, axis=1)
        ok1 = self._pool_owner[rows1] == e1[:, None] * M + cols1
        rows1 = np.where(ok1, rows1, P)
        out["next_others_state"] = self._pool_state[rows1]
        out["next_others_obs"] = self._pool_obs[rows1]
        out["next_others_mask"] = ok1
        out["env_step"] = self._tr_step[slots].copy()
        out["episode"] = self._tr_episode[slots].copy()
        out["agent"] = self._tr_agent[slots].copy()
        return out


def _unique_pairs(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lexicographically sorted unique (a, b) int64 pairs, shape (U, 2), and the index of every input pair in them."""
    n = a.shape[0]
    if n == 0:
        return np.zeros((0, 2), np.int64), np.zeros(0, np.int64)
    order = np.lexsort((b, a))
    sa, sb = a[order], b[order]
    first = np.ones(n, bool)
    first[1:] = (sa[1:] != sa[:-1]) | (sb[1:] != sb[:-1])
    group = np.cumsum(first) - 1
    inv = np.empty(n, np.int64)
    inv[order] = group
    return np.stack([sa[first], sb[first]], axis=1), inv
