"""RLlib episode chunks -> per-agent TD3-family transitions, stamped with the env step that aligns the agents.

What a CIG-TD3 transition needs (COIN §4.2, Eqs. 7-12, Algorithm 1 line 16): the ego's
``o_i, s_i, a_i, r_i, r^G, d_i, o'_i, s'_i``, the states and actions ``s_{-i}, a_{-i}`` of the
other agents that acted at the same env step t, and the states and observations
``s'_{-i}, o'_{-i}`` of every other agent with an observation at t+1 (the learner computes
``a'_{-i}`` from ``o'_{-i}`` with the target actor). TraCo reads the others too (and their
rewards); ITD3 reads only the ego's columns.

This module produces the per-agent part, one row per (episode, agent, env step), keyed by the
env's own ``infos[schema.ENV_STEP]`` stamp (never RLlib's env/agent time mapping, which is wrong
for respawned agents, ``docs/decisions.md`` §6.2 item 11): the joint-step replay buffer (``buffer.py``) uses those keys to attach
the other agents at sample time, exactly across respawns, terminations and chunk boundaries.
"""

from __future__ import annotations

import hashlib
import re
from collections import defaultdict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from coin_app.algorithms.td3 import columns as col
from coin_app.sim import schema

_I64_MASK = (1 << 63) - 1
_AGENT_RE = re.compile(r"^agent_?(\d+)$")


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
    """Per-agent transitions (one row each) plus the keys of episodes that ended in this batch.

    Field names are the replay columns of ``columns.py`` (``new_obs`` = ``columns.NEXT_OBS``).
    """

    episode: np.ndarray  # (n,) int64 episode key (see episode_key)
    agent: np.ndarray  # (n,) int64 agent key (see agent_key)
    env_step: np.ndarray  # (n,) int64 env step of o_t (infos[schema.ENV_STEP])
    obs: np.ndarray  # (n, O) float32 o_t
    state: np.ndarray  # (n, S) float32 s_t (infos[schema.STATE])
    actions: np.ndarray  # (n, A) float32 a_t
    rewards: np.ndarray  # (n,) float32 r_t
    global_rewards: np.ndarray  # (n,) float32 r^G_t (infos[schema.GLOBAL_REWARD] of o_{t+1})
    terminateds: np.ndarray  # (n,) bool
    truncateds: np.ndarray  # (n,) bool
    new_obs: np.ndarray  # (n, O) float32 o_{t+1}
    new_state: np.ndarray  # (n, S) float32 s_{t+1}
    ended_episodes: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # (k,) int64

    def __len__(self) -> int:
        """Number of transitions."""
        return int(self.episode.shape[0])

    @classmethod
    def empty(cls, obs_dim: int, state_dim: int = schema.STATE_DIM, act_dim: int = schema.ACT_DIM) -> TransitionBatch:
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
            new_obs=np.zeros((0, obs_dim), np.float32),
            new_state=np.zeros((0, state_dim), np.float32),
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
    """``info[key]`` of every info, or a ``KeyError`` naming the agent, the episode and the missing key."""
    try:
        return [info[key] for info in infos]
    except (KeyError, TypeError) as err:
        raise KeyError(f"infos of agent {agent_id!r} in episode {episode_id} lack {key!r}; the env must put {key!r} in every info") from err


def episodes_to_transitions(episodes: Iterable[Any]) -> TransitionBatch:
    """Convert ``MultiAgentEpisode`` chunks from ``MultiAgentEnvRunner.sample()`` into per-agent transitions.

    Each agent's ``SingleAgentEpisode`` in a chunk holds ``len(sa)`` actions and ``len(sa) + 1``
    observations (the first one is the last observation of the previous chunk). Env steps come
    from ``infos[schema.ENV_STEP]`` (never from RLlib's env/agent time mapping), states from
    ``infos[schema.STATE]`` and the global reward of a transition from ``infos[schema.GLOBAL_REWARD]``
    of its next observation. Only an agent's last transition in a chunk can be done; RLlib marks
    agents alive at the end of an episode as terminated *and* truncated (``docs/decisions.md`` §6.2
    item 5) while the env never reports both, so ``terminated`` is stored as
    ``is_terminated and not is_truncated``. Agents with no action in a chunk (spawned on its last step, or done in an earlier chunk) give
    no transition. Episode ids are mapped to ints with :func:`episode_key`.
    """
    # per (episode, agent): one array per column; obs and state hold all n + 1 rows (o_t and the last o_{t+1})
    parts: defaultdict[str, list[np.ndarray]] = defaultdict(list)
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
            steps = np.asarray(_info_values(infos, schema.ENV_STEP, aid, ma.id_), dtype=np.int64)
            if np.any(np.diff(steps) != 1):
                raise ValueError(
                    f"agent {aid!r} of episode {ma.id_}: env steps of consecutive observations are not consecutive: {steps.tolist()}"
                )
            states = np.asarray(_info_values(infos, schema.STATE, aid, ma.id_), dtype=np.float32).reshape(n + 1, -1)
            g = np.asarray(_info_values(infos[1:], schema.GLOBAL_REWARD, aid, ma.id_), dtype=np.float32)
            acts = np.asarray(sa.get_actions(), dtype=np.float32).reshape(n, -1)
            rews = np.asarray(sa.get_rewards(), dtype=np.float32).reshape(n)
            trunc = np.zeros(n, bool)
            term = np.zeros(n, bool)
            trunc[-1] = bool(sa.is_truncated)
            term[-1] = bool(sa.is_terminated) and not trunc[-1]
            parts[col.EPISODE].append(np.full(n, ekey, np.int64))
            parts[col.AGENT].append(np.full(n, agent_key(aid), np.int64))
            parts[col.ENV_STEP].append(steps[:-1])
            parts[col.OBS].append(obs)
            parts[col.STATE].append(states)
            parts[col.ACTIONS].append(acts)
            parts[col.REWARDS].append(rews)
            parts[col.GLOBAL_REWARDS].append(g)
            parts[col.TERMINATEDS].append(term)
            parts[col.TRUNCATEDS].append(trunc)
    ended_arr = np.unique(np.asarray(ended, dtype=np.int64))
    if not parts[col.EPISODE]:
        batch = TransitionBatch.empty(0, 0, 0)
        batch.ended_episodes = ended_arr
        return batch
    obs_all, st_all = parts[col.OBS], parts[col.STATE]
    return TransitionBatch(
        episode=np.concatenate(parts[col.EPISODE]),
        agent=np.concatenate(parts[col.AGENT]),
        env_step=np.concatenate(parts[col.ENV_STEP]),
        obs=np.concatenate([o[:-1] for o in obs_all]),
        state=np.concatenate([s[:-1] for s in st_all]),
        actions=np.concatenate(parts[col.ACTIONS]),
        rewards=np.concatenate(parts[col.REWARDS]),
        global_rewards=np.concatenate(parts[col.GLOBAL_REWARDS]),
        terminateds=np.concatenate(parts[col.TERMINATEDS]),
        truncateds=np.concatenate(parts[col.TRUNCATEDS]),
        new_obs=np.concatenate([o[1:] for o in obs_all]),
        new_state=np.concatenate([s[1:] for s in st_all]),
        ended_episodes=ended_arr,
    )
