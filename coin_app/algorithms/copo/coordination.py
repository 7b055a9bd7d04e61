"""CoPO's coordination math as plain functions, readable top to bottom (CoPO paper, Peng et al. 2021).

* LCF distribution: ``mean = tanh(p0)`` (kept inside (-1, 1)), ``std = exp(clip(p1, -20, 2))``.
* Neighbour reward of an agent at an env step: the mean reward of the other agents within the
  radius (40 m) at that step, 0 with none; global reward: the mean reward of all agents present.
* Coordinated advantage: ``cos(phi) A_ego + sin(phi) A_nei`` with ``phi = lcf * pi / 2``.
* Meta-gradient of the LCF parameters (first-order chain rule through one policy step):
  ``(g_new . g_old) * grad_p L_lcf`` with ``g_new`` the gradient of the PPO-clip loss of the
  updated policy on the (standardized) global advantage, ``g_old`` the gradient of the mean
  log-probability under the pre-update policy, and ``L_lcf`` the mean standardized coordinated
  advantage with ``phi`` a reparameterized sample of N(mean, std) times pi/2. Minimizing
  ``(g_new . g_old) * L_lcf`` over p ascends the global objective (``g_new`` is a loss gradient).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from coin_app.algorithms.ppo_family.neighbours import neighbour_indices


def lcf_distribution(params: Tensor) -> tuple[Tensor, Tensor]:
    """(mean, std) of the LCF distribution from its two parameters."""
    mean = torch.clamp(torch.tanh(params[0]), -1.0 + 1e-6, 1.0 - 1e-6)
    return mean, torch.exp(torch.clamp(params[1], -20.0, 2.0))


def lcf_parameters(mean: float, std: float) -> Tensor:
    """The two parameters (atanh mean, log std) of an LCF distribution (on the CPU: a module's buffer moves with the module)."""
    if not (-1.0 < mean < 1.0 and std > 0.0):
        raise ValueError(f"bad LCF distribution mean={mean!r}, std={std!r}; allowed: -1 < mean < 1 and std > 0")
    return torch.tensor([math.atanh(mean), math.log(std)], dtype=torch.float32)


def coordinated_advantage(a_ego: Any, a_nei: Any, lcf: Any) -> Any:
    """``cos(lcf pi/2) A_ego + sin(lcf pi/2) A_nei`` (numpy arrays or tensors)."""
    lib: Any = torch if isinstance(a_ego, Tensor) else np
    phi = lcf * (math.pi / 2.0)
    return lib.cos(phi) * a_ego + lib.sin(phi) * a_nei


def neighbour_and_global_rewards(
    rewards: np.ndarray, positions: np.ndarray, group: np.ndarray, radius: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per row: the mean reward of its neighbours within ``radius`` in its group (0 if none), and its group's mean reward."""
    rewards = np.asarray(rewards, np.float64)
    nbr = neighbour_indices(positions, group, radius, None)
    valid = nbr >= 0
    nei = np.where(valid, rewards[np.where(valid, nbr, 0)], 0.0).sum(1) / np.maximum(valid.sum(1), 1)
    _, inverse = np.unique(group, return_inverse=True)
    glob = (np.bincount(inverse, rewards) / np.bincount(inverse))[inverse]
    return nei.astype(np.float32), glob.astype(np.float32)


def standardized(x: np.ndarray, real: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``(x - mean) / max(1e-4, std)`` with mean and std over the ``real`` rows; also returns them."""
    mean, std = float(x[real].mean()), max(1e-4, float(x[real].std()))
    return ((x - mean) / std).astype(np.float32), mean, std


def gradient_dot(loss_a: Tensor, params_a: Sequence[Tensor], loss_b: Tensor, params_b: Sequence[Tensor]) -> Tensor:
    """``grad(loss_a, params_a) . grad(loss_b, params_b)`` summed over matching parameters (a detached scalar)."""
    if len(params_a) != len(params_b):
        raise ValueError(f"parameter lists differ in length ({len(params_a)} vs {len(params_b)})")
    ga = torch.autograd.grad(loss_a, list(params_a), allow_unused=True)
    gb = torch.autograd.grad(loss_b, list(params_b), allow_unused=True)
    total = torch.zeros((), device=loss_a.device)
    for a, b in zip(ga, gb):
        if a is not None and b is not None:
            total = total + (a * b).sum()
    return total.detach()


def lcf_objective(params: Tensor, a_ego: Tensor, a_nei: Tensor, mean: float, std: float, noise: Tensor) -> Tensor:
    """Mean of the coordinated advantage standardized by the batch's ``mean``/``std``, LCF sampled as mean + std * noise."""
    lcf_mean, lcf_std = lcf_distribution(params)
    lcf = lcf_mean + lcf_std * noise
    return ((coordinated_advantage(a_ego, a_nei, lcf) - mean) / std).mean()
