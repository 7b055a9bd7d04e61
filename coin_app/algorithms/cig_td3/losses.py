"""CIG-TD3 losses (COIN paper Eqs. 3, 8-12): what CIG-TD3 adds to the TD3 losses (``td3/losses.py``), free of RLlib.

Notation (one row per sampled agent transition i at env step t; TD3's o, a, r, o', d, a', y^l, L_l, as ``td3/losses.py``):
    s, r^G, s'              ego local state, global reward, next local state
    S, A, M                 other agents acting at t: states, actions, mask   (B, N, .)
    S', O', M'              agents with an observation at t+1: states, observations, mask

    A'    = clip(mu_targ(O')  + clip(eps, -c, c), -1, 1)          every other agent's smoothed target action
    y^G   = r^G + gamma (1 - d) min_k Q^g_targ,k(o', a', s', S', A', M')              (Eq. 11)
    L_g   = sum_k mean (Q^g_k(o, a, s, S, A, M) - y^G)^2                              (Eq. 9)
    L_V   = mean (V(o, s, S, A, M) - y^G)^2                                           (Eq. 10)
    L_vae = recon([o', s', r]) + kl_beta * KL                                          (Eq. 3)
    L_pi  = -mean[ Q^l_1(o, mu(o)) + w (Q^g_1(o, mu(o), s, S, A, M) - V(o, s, S, A, M)) ]  (Eq. 12)
            + p mean[ max(|u(o)| - u0, 0)^2 ]     (TD3's optional pre-tanh guard)

V does not depend on the ego action, so with a deterministic policy it leaves the actor's
gradient unchanged (``docs/decisions.md`` §2.2); it is still trained and logged, as Eq. 12 is written.
Without the centralized critic (``global_critic=False``) every loss is TD3's.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.losses import LossConfig, actor_objective_loss, bootstrap, not_done, policy, smoothed_target_action
from coin_app.algorithms.td3.networks import full_precision


@dataclass(frozen=True)
class CigTd3LossConfig(LossConfig):
    """The constants the CIG-TD3 losses need: TD3's and the centralized critic's (a view of ``CigTd3Config``)."""

    global_critic: bool = True
    counterfactual_baseline: bool = True
    global_weight: float = 1.0
    vae_weight: float = 1.0
    kl_beta: float = 1.0


@torch.no_grad()
def td_targets(
    batch: dict[str, torch.Tensor],
    actor_target: nn.Module,
    local_q_target: nn.Module,
    central_target: nn.Module | None,
    cfg: LossConfig,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Individual and global TD targets y^l (Eq. 8) and y^G (Eq. 11); y^G is None without a global critic."""
    nd = not_done(batch, cfg.timeout_bootstrap)
    next_a = smoothed_target_action(actor_target, batch[col.NEXT_OBS], cfg.target_noise, cfg.target_noise_clip)
    y_local = bootstrap(batch[col.REWARDS], nd, *local_q_target(batch[col.NEXT_OBS], next_a), cfg.gamma)
    if central_target is None:
        return y_local, None
    mask_next = batch[col.NEXT_OTHERS_MASK].bool()
    others_next_a = smoothed_target_action(actor_target, batch[col.NEXT_OTHERS_OBS], cfg.target_noise, cfg.target_noise_clip)
    others_next_a = others_next_a * mask_next.unsqueeze(-1)
    g1_t, g2_t = central_target.q_values(
        batch[col.NEXT_OBS], batch[col.NEXT_STATE], next_a, batch[col.NEXT_OTHERS_STATE], others_next_a, mask_next
    )
    return y_local, bootstrap(batch[col.GLOBAL_REWARDS], nd, g1_t, g2_t, cfg.gamma)


def central_critic_loss(
    central: nn.Module, batch: dict[str, torch.Tensor], y_global: torch.Tensor, cfg: CigTd3LossConfig
) -> tuple[torch.Tensor, dict]:
    """Eqs. 9, 10 and 3: twin global Q losses, the counterfactual baseline loss and the CVAE loss (one critic pass)."""
    mask = batch[col.OTHERS_MASK].bool()
    target_y = None
    if cfg.vae_weight > 0:
        target_y = torch.cat([batch[col.NEXT_OBS], batch[col.NEXT_STATE], batch[col.REWARDS].unsqueeze(-1)], dim=-1)
    out = central(batch[col.OBS], batch[col.STATE], batch[col.ACTIONS], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], mask, target_y)
    q1, q2, v = full_precision(out.q1), full_precision(out.q2), full_precision(out.v)
    loss_q = ((q1 - y_global) ** 2).mean() + ((q2 - y_global) ** 2).mean()
    stats = {"global_q1_mean": q1.mean().detach(), "global_q_target_mean": y_global.mean(), "global_q_loss": loss_q.detach()}
    loss = loss_q
    if cfg.counterfactual_baseline:
        loss_v = ((v - y_global) ** 2).mean()
        loss = loss + loss_v
        stats.update(baseline_mean=v.mean().detach(), baseline_loss=loss_v.detach())
    if cfg.vae_weight > 0:
        loss = loss + cfg.vae_weight * (out.recon_mse + cfg.kl_beta * out.kl)
        stats.update(vae_recon=out.recon_mse.detach(), vae_kl=out.kl.detach())
    return loss, stats


def actor_loss(
    actor: nn.Module,
    local_q: nn.Module,
    central: nn.Module | None,
    batch: dict[str, torch.Tensor],
    cfg: CigTd3LossConfig,
) -> tuple[torch.Tensor, dict]:
    """Eq. 12 (without a centralized critic: TD3's individual term only), plus the optional pre-tanh penalty.

    Gradients reach critic parameters too: take only the actor's. The stats include the share of
    saturated outputs (``actor_saturation``: |tanh(u)| > 0.99) and the mean |u|.
    """
    pre, a = policy(actor, batch[col.OBS])
    q_local = full_precision(local_q.q1_only(batch[col.OBS], a))
    objective = q_local
    stats = {"actor_q_local": q_local.mean().detach()}
    if central is not None and cfg.global_weight > 0:
        mask = batch[col.OTHERS_MASK].bool()
        q_global = full_precision(central.q1(batch[col.OBS], batch[col.STATE], a, batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], mask))
        advantage = q_global
        if cfg.counterfactual_baseline:
            # V has no ego action, so it carries no actor gradient: evaluate it without a graph
            with torch.no_grad():
                v = full_precision(
                    central.baseline(batch[col.OBS], batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], mask)
                )
            advantage = q_global - v
            stats["actor_counterfactual_advantage"] = advantage.mean().detach()
        objective = objective + cfg.global_weight * advantage
        stats["actor_q_global"] = q_global.mean().detach()
    return actor_objective_loss(objective, pre, stats, cfg.preact_penalty, cfg.preact_threshold)
