"""Local coordination factors (LCF) of CoPO, env side (CoPO paper; ``docs/decisions.md`` §7.4).

Each agent gets one LCF ``lcf ~ N(mean, std)`` clipped to [-1, 1] when its id first appears
(spawn or respawn) and keeps it for its whole life; the agent's observation gets one more
feature ``(lcf + 1) / 2`` in [0, 1]. The draws come from this object's own generator, seeded
at ``reset(seed)`` (CoPO drew them from ``os.urandom``: not reproducible). The trainer moves
the distribution with ``set_distribution``; agents alive at that moment keep their value.
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np

_STREAM = 0x4C4346  # separates the LCF draws from the simulator's draws of the same seed


def check_distribution(mean: float, std: float) -> tuple[float, float]:
    """``(mean, std)`` as floats; a ValueError naming the bad value otherwise."""
    if not (isinstance(mean, (int, float)) and not isinstance(mean, bool) and -1.0 <= mean <= 1.0):
        raise ValueError(f"bad LCF mean {mean!r}; allowed: a number in [-1, 1]")
    if not (isinstance(std, (int, float)) and not isinstance(std, bool) and std >= 0.0 and np.isfinite(std)):
        raise ValueError(f"bad LCF std {std!r}; allowed: a finite number >= 0")
    return float(mean), float(std)


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
        self._rng = np.random.default_rng([0, _STREAM])

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
            self._rng = np.random.default_rng([int(seed), _STREAM])
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
