"""The RLModule of the PPO family: RLlib's default PPO module with the ``ActorModule`` contract of ``spec.py``.

The policy is a Gaussian whose ``pi`` head outputs (mean, log std) per action dimension. The
deterministic policy is its mean, clipped to the action bounds [-1, 1] as the env clips
actions; ``deterministic_actor`` gives it as a plain torch network (actor encoder, then the
``pi`` head cut to the mean outputs, then ``Hardtanh``) for evaluation and export, and
``inference_actions`` gives the same actions from RLlib's own ``forward_inference``, the
reference the export's parity check compares against.
"""

from __future__ import annotations

import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.core.columns import Columns
from torch import nn


def gaussian_mean(head: nn.Linear) -> nn.Linear:
    """A copy of the first half of ``head``'s outputs (the Gaussian mean of (mean, log std) inputs)."""
    act_dim = head.out_features // 2
    mean = nn.Linear(head.in_features, act_dim)
    with torch.no_grad():
        mean.weight.copy_(head.weight[:act_dim])
        mean.bias.copy_(head.bias[:act_dim])
    return mean


class PPOActorModule(DefaultPPOTorchRLModule):
    """RLlib's default PPO module whose deterministic policy is the Gaussian mean clipped to [-1, 1]."""

    def deterministic_actor(self) -> nn.Sequential:
        """The actor encoder and the ``pi`` head's mean outputs, then ``Hardtanh(-1, 1)``, as an ``nn.Sequential``."""
        encoder = getattr(self.encoder, "actor_encoder", self.encoder)
        layers = [*encoder.net.mlp, *self.pi.net.mlp]
        head = layers[-1]
        if not isinstance(head, nn.Linear):
            raise ValueError(f"cannot extract a deterministic actor: the policy head ends in {head!r}")
        return nn.Sequential(*layers[:-1], gaussian_mean(head), nn.Hardtanh(-1.0, 1.0)).eval()

    def inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The mean of ``forward_inference``'s Gaussian inputs on ``obs``, clamped to [-1, 1]."""
        with torch.no_grad():
            inputs = self.forward_inference({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
        return inputs[:, : inputs.shape[1] // 2].clamp(-1.0, 1.0)
