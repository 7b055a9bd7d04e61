"""CIG-TD3 Learner: the TD3 learner (``td3/learner.py``: critics, delayed actor, targets) with the centralized critic.

What CIG-TD3 adds to a TD3 update: a third optimizer for the centralized critic (twin global Q,
baseline V and CVAE, one loss: Eqs. 9, 10, 3) stepped with the local critics in step 1, the global
target y^G next to y^l (Eq. 11), and the global term of the actor loss (Eq. 12). Without the
centralized critic (``global_critic=False``) it is the TD3 learner.
"""

from __future__ import annotations

from typing import Any

import torch

from coin_app.algorithms.cig_td3.losses import CigTd3LossConfig, actor_loss, central_critic_loss, td_targets
from coin_app.algorithms.td3.learner import Losses, Td3TorchLearner, autocast, loss_fields
from coin_app.algorithms.td3.losses import local_critic_loss


def loss_config(config: Any) -> CigTd3LossConfig:
    """The loss constants of a ``CigTd3Config``."""
    return CigTd3LossConfig(
        **loss_fields(config),
        global_critic=config.global_critic,
        counterfactual_baseline=config.counterfactual_baseline,
        global_weight=config.global_weight,
        vae_weight=config.vae_weight,
        kl_beta=config.kl_beta,
    )


class CigTd3TorchLearner(Td3TorchLearner):
    """Torch learner of CIG-TD3."""

    def optimizer_groups(self, module: Any, config: Any) -> list[tuple[str, torch.nn.Module, float]]:
        """TD3's actor and local critics, and the centralized critic (when the module has one)."""
        groups = super().optimizer_groups(module, config)
        if module.central is not None:
            groups.append(("central_critic", module.central, config.central_critic_lr))
        return groups

    def loss_config(self, module: Any, config: Any) -> CigTd3LossConfig:
        """The loss constants of ``config``."""
        return loss_config(config)

    def critic_losses(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[Losses, dict[str, Any]]:
        """The local critics' and the centralized critic's losses and their stats (Eqs. 7-11, 3)."""
        cfg = self.loss_config(module, config)
        with autocast(module, config.precision):
            y_local, y_global = td_targets(batch, module.actor_target, module.local_q_target, module.central_target, cfg)
            loss_l, stats = local_critic_loss(module.local_q, batch, y_local)
        losses: Losses = {"local_critic": (loss_l, module.local_q)}
        if module.central is not None:
            with autocast(module, config.precision):
                loss_g, g_stats = central_critic_loss(module.central, batch, y_global, cfg)
            losses["central_critic"] = (loss_g, module.central)
            stats.update(g_stats)
        return losses, stats

    def actor_loss(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        """CIG-TD3's actor loss (Eq. 12) and its stats."""
        return actor_loss(module.actor, module.local_q, module.central, batch, self.loss_config(module, config))
