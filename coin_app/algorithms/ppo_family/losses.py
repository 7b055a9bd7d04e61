"""PPO losses as plain functions on tensors, readable top to bottom (Ray 1.x PPO, as CoPO's paper runs used).

* clipped surrogate: ``L_pi = -mean(min(A r, A clip(r, 1 - eps, 1 + eps)))`` with
  ``r = exp(logp_new - logp_old)``;
* PPO2-style clipped value loss around the values predicted when the batch was collected:
  ``L_V = mean(max((V - R)^2, (V_old + clip(V - V_old, -c, c) - R)^2))`` (Ray 1.x; RLlib 2.x
  instead clamps the squared error at ``c``, a different objective);
* adaptive KL penalty ``beta * mean(KL(pi_old || pi_new))`` and an entropy bonus; beta moves x1.5
  when the KL is above 2 x target and x0.5 below target / 2, where Ray 1.x's KL is the mean over
  the minibatches of the last SGD epoch (``last_epoch_mean``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor


def surrogate_loss(logp_new: Tensor, logp_old: Tensor, advantages: Tensor, clip: float) -> Tensor:
    """Negative clipped surrogate objective (a scalar)."""
    ratio = torch.exp(logp_new - logp_old)
    return -torch.min(advantages * ratio, advantages * torch.clamp(ratio, 1.0 - clip, 1.0 + clip)).mean()


def clipped_value_loss(values: Tensor, old_values: Tensor, targets: Tensor, clip: float) -> Tensor:
    """PPO2 value loss: the larger of the plain and the clipped squared errors, averaged."""
    clipped = old_values + torch.clamp(values - old_values, -clip, clip)
    return torch.max((values - targets) ** 2, (clipped - targets) ** 2).mean()


def last_epoch_mean(values: Sequence[float], num_epochs: int) -> float:
    """Mean of the last epoch's share of per-minibatch values: the last ``ceil(len / num_epochs)`` of them."""
    if not values:
        raise ValueError("last_epoch_mean needs at least one value")
    per_epoch = math.ceil(len(values) / max(1, int(num_epochs)))
    tail = list(values)[-per_epoch:]
    return float(sum(tail) / len(tail))
