"""How the TD3 family acts while collecting: the warm-up, the Gaussian noise schedule, and a canonical row order.

    t < warmup_steps:  a ~ U(-1, 1)                                  (the warm-up: uniform random actions)
    else:              a = clip(mu(o) + N(0, sigma(t)), -1, 1)
    sigma(t) = sigma_0 + f(t) (sigma_1 - sigma_0),   f(t) = clip((t - t_0) / T, 0, 1)

``t`` is the lifetime env-step count, sigma_1 = ``exploration_noise`` (0.05, COIN §5.1), sigma_0 =
``exploration_noise_initial`` (default sigma_1: constant noise), t_0 = ``exploration_noise_decay_start``
(default: the end of the warm-up) and T = ``exploration_noise_decay_steps`` (0: constant). Random
numbers come from torch's default generator (RLlib seeds it), drawn in :func:`canonical_order`, so a
seeded run acts the same in every process. Plain torch; nothing here imports Ray.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch


@dataclass(frozen=True)
class Exploration:
    """The warm-up length and the noise schedule sigma(t) of the module doc."""

    warmup_steps: int
    noise: float  # sigma_1
    noise_initial: float  # sigma_0
    decay_start: int  # t_0
    decay_steps: int  # T

    @classmethod
    def from_model_config(cls, mc: dict[str, Any]) -> Exploration:
        """The schedule of a TD3-family module's ``model_config`` (the config's exploration keys)."""
        noise = float(mc.get("exploration_noise", 0.05))
        noise0 = mc.get("exploration_noise_initial")
        warmup = int(mc.get("warmup_steps", 0))
        start = mc.get("exploration_noise_decay_start")
        return cls(
            warmup_steps=warmup,
            noise=noise,
            noise_initial=noise if noise0 is None else float(noise0),
            decay_start=warmup if start is None else int(start),
            decay_steps=int(mc.get("exploration_noise_decay_steps", 0)),
        )

    def noise_std(self, t: int | None) -> float:
        """sigma(t): ``noise_initial`` until the decay starts, then linear to ``noise``; ``noise`` when ``t`` is None or T = 0."""
        if t is None or self.decay_steps <= 0:
            return self.noise
        frac = min(1.0, max(0.0, (t - self.decay_start) / self.decay_steps))
        return self.noise_initial + frac * (self.noise - self.noise_initial)

    def actions(self, mu: torch.Tensor, t: int | None) -> torch.Tensor:
        """The exploring actions for the deterministic ones ``mu`` at env step ``t`` (uniform during the warm-up), on ``mu``'s device."""
        if t is not None and t < self.warmup_steps:
            return torch.rand(mu.shape, device=mu.device) * 2.0 - 1.0  # on the CPU: the seeded default generator
        return (mu + torch.randn(mu.shape, device=mu.device) * self.noise_std(t)).clamp(-1.0, 1.0)


def canonical_order(obs: torch.Tensor) -> torch.Tensor:
    """A canonical order of a batch of observations (ranks of a fixed projection of each row).

    RLlib batches the acting agents in the iteration order of a set of agent ids, which
    changes with Python's hash seed. Running the actor and drawing the noise in this order
    instead makes every agent's action independent of that order (bit for bit: BLAS results
    can depend on a row's position), so a seeded run gives the same result in every process.
    """
    n, dim = obs.shape[0], obs.shape[-1]
    weights = torch.cos(torch.arange(dim, dtype=torch.float64, device=obs.device) * 0.731) + 1.618
    return torch.argsort(obs.reshape(n, dim).to(torch.float64) @ weights, stable=True)


def unsort(rows: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Put rows computed in ``order`` back in the batch's original order."""
    out = torch.empty_like(rows)
    out[order] = rows
    return out
