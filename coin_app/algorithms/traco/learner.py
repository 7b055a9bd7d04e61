"""TraCo-TD3 Learner: the TD3 learner (``td3/learner.py``: critics, delayed actor, targets, exact resume) with TraCo's losses.

TraCo's critic step (step 1 of a TD3 update): the ego's domain at t and t+1 and the domain reward,
the targets with the target networks (no grad), the domain critic loss -> grads of ``domain_q``
only, the baseline loss -> grads of ``baseline`` only, the individual critic loss (if any) ->
grads of ``local_q`` only. Its actor loss follows the domain critic (and the individual critic, if any).
"""

from __future__ import annotations

from typing import Any

import torch

from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.learner import Losses, Td3TorchLearner, autocast, loss_fields
from coin_app.algorithms.td3.losses import local_critic_loss
from coin_app.algorithms.traco.losses import (
    TracoLossConfig,
    actor_loss,
    baseline_loss,
    domain_batch,
    domain_critic_loss,
    domain_rewards,
    domains,
    td_targets,
)


def loss_config(config: Any, position_scale: float) -> TracoLossConfig:
    """The loss constants of a ``TracoConfig`` on a map of ``position_scale``."""
    return TracoLossConfig(
        **loss_fields(config),
        domain_radius=float(config.domain_radius),
        position_scale=position_scale,
        domain_reward=config.domain_reward,
        counterfactual_baseline=config.counterfactual_baseline,
        individual_critic=config.individual_critic,
        domain_weight=config.domain_weight,
    )


class TracoTorchLearner(Td3TorchLearner):
    """Torch learner of TraCo-TD3."""

    def optimizer_groups(self, module: Any, config: Any) -> list[tuple[str, torch.nn.Module, float]]:
        """The actor, the domain critic, the baseline and the individual critic (those present)."""
        groups = [("actor", module.actor, config.actor_lr), ("domain_critic", module.domain_q, config.critic_lr)]
        if module.baseline is not None:
            groups.append(("baseline", module.baseline, config.baseline_lr))
        if module.local_q is not None:
            groups.append(("local_critic", module.local_q, config.critic_lr))
        return groups

    def loss_config(self, module: Any, config: Any) -> TracoLossConfig:
        """The loss constants, with the map scale the module was built with."""
        return loss_config(config, float(module.model_config.get("position_scale", 1.0)))

    def critic_losses(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[Losses, dict[str, Any]]:
        """Domain critic, baseline and individual critic losses as {optimizer name: (loss, network)} and their stats."""
        cfg = self.loss_config(module, config)
        r_domain = domain_rewards(batch[col.REWARDS], batch[col.OTHERS_REWARDS], domains(batch, cfg)[0], cfg.domain_reward)
        batch, d0, d1 = domain_batch(batch, cfg)  # the others cut to the largest domain: the attention's cost
        losses: Losses = {}
        with autocast(module, config.precision):
            y_domain, y_local = td_targets(batch, d1, r_domain, module.actor_target, module.domain_q_target, module.local_q_target, cfg)
            loss_q, stats, q1 = domain_critic_loss(module.domain_q, batch, d0, y_domain)
        losses["domain_critic"] = (loss_q, module.domain_q)
        stats["domain_reward_mean"] = r_domain.mean()
        if module.baseline is not None:
            with autocast(module, config.precision):
                loss_b, b_stats = baseline_loss(module.baseline, batch, d0, y_domain, q1=q1)
            losses["baseline"] = (loss_b, module.baseline)
            stats.update(b_stats)
        if module.local_q is not None:
            with autocast(module, config.precision):
                loss_l, l_stats = local_critic_loss(module.local_q, batch, y_local)
            losses["local_critic"] = (loss_l, module.local_q)
            stats.update(l_stats)
        return losses, stats

    def actor_loss(self, module: Any, config: Any, batch: dict[str, Any]) -> tuple[torch.Tensor, dict[str, Any]]:
        """The actor loss on the domain critic (and the individual critic, if any) and its stats."""
        cfg = self.loss_config(module, config)
        batch, d0, _ = domain_batch(batch, cfg)
        return actor_loss(module.actor, module.domain_q, module.baseline, module.local_q, batch, d0, cfg)
