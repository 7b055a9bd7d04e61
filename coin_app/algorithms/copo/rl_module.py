"""CoPO's RLModule: the PPO family's module plus a neighbour and a global value head and the LCF parameters.

All three value functions are separate tanh MLPs on the agent's own observation (which ends
with its LCF feature): CoPO's paper configuration has decentralized critics. The LCF
distribution parameters ``(atanh mean, log std)`` are a buffer, so checkpoints and the weights
sent to env runners carry them; the learner's meta-gradient step writes them.

The policy reads the agent's LCF as its last observation feature. Evaluation gives every vehicle
an LCF (``evaluation_lcf()``, the ``eval_lcf`` key of ``copo.py``): ``"sampled"`` (the default,
as CoPO's evaluation did) draws one per vehicle from the learned distribution and runs
``lcf_actor()`` on ``[obs | LCF feature]`` (``coin_app.adapters.lcf.SampledLCFPolicy``, through
``coin_app.algorithms.checkpoints.actor_policy``); ``"mean"`` gives every vehicle the learned
mean. ``deterministic_actor()``, the ``ActorModule`` contract's network on the plain
observation, is the mean-LCF actor: the mean's feature is a constant folded into its first
layer's bias, so it runs in any evaluation env.
"""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from coin_app.adapters.lcf import encode
from coin_app.algorithms.copo.coordination import lcf_distribution, lcf_parameters
from coin_app.algorithms.ppo_family.centralized import value_mlp
from coin_app.algorithms.ppo_family.precision import full_precision
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule


def fold_lcf(first: nn.Module, lcf: float) -> nn.Linear:
    """A copy of ``first`` (Linear on [obs, LCF feature]) acting on obs alone with the LCF feature fixed."""
    if not isinstance(first, nn.Linear):
        raise ValueError(f"cannot fold the LCF into {first!r}; expected a Linear first layer")
    folded = nn.Linear(first.in_features - 1, first.out_features)
    with torch.no_grad():
        folded.weight.copy_(first.weight[:, :-1])
        folded.bias.copy_(first.bias + first.weight[:, -1] * float(encode(lcf)))
    return folded


class CoPOModule(PPOActorModule):
    """PPO policy with ego, neighbour and global value functions and the LCF distribution parameters."""

    def setup_heads(self) -> None:
        """The LCF buffer and (learner copies) the neighbour and global value heads."""
        self.register_buffer("lcf_params", lcf_parameters(*self.model_config["initial_lcf"]))
        if not self.inference_only:
            obs_dim = int(self.observation_space.shape[0])
            self.nei_vf = value_mlp(obs_dim, self.model_config["fcnet_hiddens"])
            self.global_vf = value_mlp(obs_dim, self.model_config["fcnet_hiddens"])

    def get_non_inference_attributes(self) -> list[str]:
        """Value networks are not needed to act."""
        return [*super().get_non_inference_attributes(), "nei_vf", "global_vf"]

    def compute_all_values(self, batch: dict[str, Any], embeddings: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(ego, neighbour, global) fp32 values of the batch's observations, each (B,) (``embeddings``: the critic encoder's)."""
        obs = batch["obs"]
        ego = self.compute_values(batch, embeddings)
        return ego, full_precision(self.nei_vf(obs).squeeze(-1)), full_precision(self.global_vf(obs).squeeze(-1))

    def lcf_distribution(self) -> tuple[float, float]:
        """The current LCF (mean, std)."""
        mean, std = lcf_distribution(self.lcf_params)
        return float(mean), float(std)

    def evaluation_lcf(self) -> str:
        """How evaluation gives vehicles their LCF: ``"sampled"`` (one draw per vehicle) or ``"mean"`` (the learned mean)."""
        return str(self.model_config.get("eval_lcf", "sampled"))

    def lcf_actor(self) -> nn.Sequential:
        """The family's clipped Gaussian-mean actor on ``[obs | LCF feature]`` (N, obs_dim + 1): the policy as trained."""
        return super().deterministic_actor()

    def lcf_inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The family's inference actions on ``[obs | LCF feature]`` (the export parity reference of ``lcf_actor``)."""
        return super().inference_actions(obs)

    def deterministic_actor(self) -> nn.Sequential:
        """The family's clipped Gaussian-mean actor on the plain observation, with the learned mean LCF folded in."""
        actor = super().deterministic_actor()
        actor[0] = fold_lcf(actor[0], self.lcf_distribution()[0])
        return actor.eval()

    def inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The family's inference actions on ``obs`` with the learned mean LCF's feature appended."""
        feature = torch.full((len(obs), 1), float(encode(self.lcf_distribution()[0])), dtype=obs.dtype, device=obs.device)
        return super().inference_actions(torch.cat([obs, feature], dim=1))
