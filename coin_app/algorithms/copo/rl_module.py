"""CoPO's RLModule: RLlib's default PPO module plus a neighbour and a global value head and the LCF parameters.

All three value functions are separate tanh MLPs on the agent's own observation (which ends
with its LCF feature): CoPO's paper configuration has decentralized critics. The LCF
distribution parameters ``(atanh mean, log std)`` are a buffer, so checkpoints and the weights
sent to env runners carry them; the learner's meta-gradient step writes them.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule

from coin_app.algorithms.copo.coordination import lcf_distribution, lcf_parameters
from coin_app.algorithms.ppo_family.centralized import value_mlp


class CoPOModule(DefaultPPOTorchRLModule):
    """PPO policy with ego, neighbour and global value functions and the LCF distribution parameters."""

    def setup(self) -> None:
        """Build the default module, the LCF buffer and (learner copies) the two extra value heads."""
        super().setup()
        self.register_buffer("lcf_params", lcf_parameters(*self.model_config["initial_lcf"]))
        if not self.inference_only:
            obs_dim = int(self.observation_space.shape[0])
            self.nei_vf = value_mlp(obs_dim, self.model_config["fcnet_hiddens"])
            self.global_vf = value_mlp(obs_dim, self.model_config["fcnet_hiddens"])

    def get_non_inference_attributes(self) -> list[str]:
        """Value networks are not needed to act."""
        return [*super().get_non_inference_attributes(), "nei_vf", "global_vf"]

    def compute_all_values(self, batch: dict[str, Any], embeddings: Any = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(ego, neighbour, global) values of the batch's observations, each of shape (B,) (``embeddings``: the critic encoder's)."""
        obs = batch["obs"]
        return self.compute_values(batch, embeddings), self.nei_vf(obs).squeeze(-1), self.global_vf(obs).squeeze(-1)

    def lcf_distribution(self) -> tuple[float, float]:
        """The current LCF (mean, std)."""
        mean, std = lcf_distribution(self.lcf_params)
        return float(mean), float(std)
