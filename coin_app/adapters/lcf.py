"""Local coordination factors (LCF) of CoPO, env side (CoPO paper; ``docs/decisions.md`` §7.4).

Each agent gets one LCF ``lcf ~ N(mean, std)`` clipped to [-1, 1] when its id first appears
(spawn or respawn) and keeps it for its whole life; the agent's observation gets one more
feature ``(lcf + 1) / 2`` in [0, 1]. The draws come from this object's own generator, seeded
at ``reset(seed)`` (CoPO drew them from ``os.urandom``: not reproducible). The trainer moves
the distribution with ``set_distribution``; agents alive at that moment keep their value.

At evaluation CoPO drew every vehicle's LCF from the learned distribution the same way
(``SampledLCFPolicy``): one draw per vehicle, N(mean, std) clipped to [-1, 1], appended to its
observation as ``(lcf + 1) / 2`` for the actor. The draw is a function of (policy seed, episode
seed, agent id) alone (``vehicle_lcf``), so an evaluation is reproducible and a vehicle's LCF
does not depend on which other episodes run in the same batch or on the backend.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Sequence
from typing import Any

import gymnasium as gym
import numpy as np

_STREAM = 0x4C4346  # separates the LCF draws from the simulator's draws of the same seed
_EVAL_STREAM = 0x4C434645  # separates the evaluation draws from the training env's


def check_distribution(mean: float, std: float) -> tuple[float, float]:
    """``(mean, std)`` as floats; a ValueError naming the bad value otherwise."""
    if not (isinstance(mean, (int, float)) and not isinstance(mean, bool) and -1.0 <= mean <= 1.0):
        raise ValueError(f"bad LCF mean {mean!r}; allowed: a number in [-1, 1]")
    if not (isinstance(std, (int, float)) and not isinstance(std, bool) and std >= 0.0 and np.isfinite(std)):
        raise ValueError(f"bad LCF std {std!r}; allowed: a finite number >= 0")
    return float(mean), float(std)


def lcf_stream(seed: int) -> np.random.Generator:
    """The generator of the training LCF draws of an env reset with ``seed`` (apart from the simulator's draws)."""
    return np.random.default_rng([int(seed), _STREAM])


def encode(lcf: np.ndarray | float) -> np.ndarray:
    """The observation feature of an LCF: ``(lcf + 1) / 2``."""
    return (np.asarray(lcf, np.float32) + 1.0) / 2.0


def decode(feature: np.ndarray) -> np.ndarray:
    """The LCF of an observation feature (inverse of ``encode``)."""
    return np.asarray(feature, np.float32) * 2.0 - 1.0


class LocalCoordination:
    """Per-agent LCFs drawn at spawn and appended to observations (see module doc)."""

    def __init__(self, mean: float = 0.0, std: float = 0.1):
        self.mean, self.std = check_distribution(mean, std)
        self.values: dict[str, float] = {}
        self._rng = lcf_stream(0)

    def set_distribution(self, mean: float, std: float) -> None:
        """Draw the LCFs of agents spawned from now on from N(mean, std)."""
        self.mean, self.std = check_distribution(mean, std)

    def observation_space(self, space: gym.spaces.Box) -> gym.spaces.Box:
        """``space`` with the LCF feature (in [0, 1]) appended."""
        low = np.append(space.low, np.float32(0.0)).astype(np.float32)
        high = np.append(space.high, np.float32(1.0)).astype(np.float32)
        return gym.spaces.Box(low, high, dtype=np.float32)

    def reset(self, seed: int | None) -> None:
        """Forget all agents; reseed the draws when ``seed`` is given (else the stream continues)."""
        if seed is not None:
            self._rng = lcf_stream(seed)
        self.values = {}

    def augment(self, obs: dict[str, np.ndarray], infos: dict[str, dict]) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Append each agent's LCF feature to its observation (drawing it for new agents) and put ``lcf`` in its info."""
        new = [aid for aid in obs if aid not in self.values]
        if new:
            draws = np.clip(self._rng.normal(self.mean, self.std, len(new)), -1.0, 1.0)
            self.values.update(zip(new, draws.tolist()))
        out = {aid: np.append(o, encode(self.values[aid])).astype(np.float32) for aid, o in obs.items()}
        infos = {aid: {**info, "lcf": self.values[aid]} if aid in self.values else info for aid, info in infos.items()}
        return out, infos


def vehicle_lcf(mean: float, std: float, seed: int, episode_seed: int, agent_id: str) -> float:
    """The evaluation LCF of vehicle ``agent_id`` of the episode seeded ``episode_seed``: N(mean, std) clipped to [-1, 1]."""
    rng = np.random.default_rng([int(seed), int(episode_seed), zlib.crc32(agent_id.encode()), _EVAL_STREAM])
    return float(np.clip(rng.normal(mean, std), -1.0, 1.0))


class SampledLCFPolicy:
    """CoPO at evaluation: each vehicle gets its own LCF from N(mean, std), and the actor acts on ``[obs | (lcf + 1) / 2]``.

    ``actor`` maps ``(N, obs_dim + 1)`` to actions ``(N, 2)``. The policy needs to know which
    vehicle each row is, so it is an agent-aware policy of :mod:`coin_app.sim.rollout`:
    ``act(obs, agents)`` with ``agents[i] = (episode seed, agent id)`` of row ``i``.
    """

    def __init__(
        self, actor: Callable[[np.ndarray], np.ndarray], mean: float, std: float, seed: int = 0, meta: dict[str, Any] | None = None
    ):
        self.actor = actor
        self.mean, self.std = check_distribution(mean, std)
        self.seed = int(seed)
        self.meta = dict(meta or {})
        self._values: dict[tuple[int, str], float] = {}  # (episode seed, agent id) -> LCF, a cache of vehicle_lcf

    def lcf(self, agents: Sequence[tuple[int, str]]) -> np.ndarray:
        """The LCF (N,) of each ``(episode seed, agent id)``: the same value for a vehicle every time it is asked."""
        for key in agents:
            if key not in self._values:
                self._values[key] = vehicle_lcf(self.mean, self.std, self.seed, *key)
        return np.array([self._values[key] for key in agents], np.float32)

    def act(self, obs: np.ndarray, agents: Sequence[tuple[int, str]]) -> np.ndarray:
        """Actions (N, 2) of the actor on each row's observation with its vehicle's LCF feature appended."""
        obs = np.asarray(obs, np.float32)
        if obs.ndim != 2 or len(agents) != len(obs):
            raise ValueError(f"need one (episode seed, agent id) per observation row: {obs.shape} observations, {len(agents)} agents")
        return np.asarray(self.actor(np.concatenate([obs, encode(self.lcf(agents))[:, None]], axis=1)))

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Refused: a sampled-LCF policy needs each row's vehicle (``act``; ``coin_app.sim.rollout`` passes it)."""
        raise ValueError(
            "this CoPO policy draws one LCF per vehicle and needs each row's vehicle: call act(obs, agents) (as the rollout does)"
        )

    def __repr__(self) -> str:
        return f"SampledLCFPolicy(mean={self.mean:.4f}, std={self.std:.4f}, seed={self.seed})"


def with_lcf(policy: Any) -> Any:
    """An exported policy as evaluation runs it: wrapped in per-vehicle LCF draws if its metadata holds CoPO's ``lcf``."""
    lcf = getattr(policy, "meta", {}).get("lcf")
    if lcf is None:
        return policy
    return SampledLCFPolicy(policy, lcf["mean"], lcf["std"], lcf.get("seed", 0), meta=policy.meta)
