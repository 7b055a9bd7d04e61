"""CIG-TD3 losses (COIN paper Eqs. 3, 7-12), readable top to bottom, free of RLlib.

Notation (one row per sampled agent transition i at env step t):
    o, s, a, r, r^G         ego observation, local state, action, reward, global reward
    o', s'                  ego next observation / state
    S, A, M                 other agents acting at t: states, actions, mask   (B, N, .)
    S', O', M'              agents with an observation at t+1: states, observations, mask
    d = terminated and not truncated (time-outs bootstrap)

    a'    = clip(mu_targ(o')  + clip(eps, -c, c), -1, 1)          eps ~ N(0, sigma)   (Eq. 8)
    A'    = clip(mu_targ(O')  + clip(eps, -c, c), -1, 1)          same for every other agent
    y^l   = r   + gamma (1 - d) min_k Q^l_targ,k(o', a')                              (Eq. 8)
    y^G   = r^G + gamma (1 - d) min_k Q^g_targ,k(o', a', s', S', A', M')              (Eq. 11)
    L_l   = sum_k mean (Q^l_k(o, a) - y^l)^2                                          (Eq. 7)
    L_g   = sum_k mean (Q^g_k(o, a, s, S, A, M) - y^G)^2                              (Eq. 9)
    L_V   = mean (V(o, s, S, A, M) - y^G)^2                                           (Eq. 10)
    L_vae = recon([o', s', r]) + kl_beta * KL                                          (Eq. 3)
    L_pi  = -mean[ Q^l_1(o, mu(o)) + w (Q^g_1(o, mu(o), s, S, A, M) - V(o, s, S, A, M)) ]  (Eq. 12)
            + p mean[ max(|u(o)| - u0, 0)^2 ]     u = the actor's pre-tanh output, mu = tanh(u)
                                                  (optional guard against saturation; p = 0 in the paper)

V does not depend on the ego action, so with a deterministic policy it leaves the actor's
gradient unchanged (``docs/decisions.md`` §2.2); it is still trained and logged, as Eq. 12 is written.

Every network output is widened to fp32 (``full_precision``) before it enters a target, a
difference or a mean, so under bf16 autocast (``precision="bf16"``) only the networks' own
layers run in bf16; with fp32 networks this changes nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from coin_app.algorithms.cig_td3.individual import full_precision
from coin_app.algorithms.td3 import columns as col


@dataclass(frozen=True)
class LossConfig:
    """The constants the losses need (a view of ``CigTd3Config``)."""

    gamma: float = 0.99
    target_noise: float = 0.1
    target_noise_clip: float = 0.5
    global_critic: bool = True
    counterfactual_baseline: bool = True
    global_weight: float = 1.0
    vae_weight: float = 1.0
    kl_beta: float = 1.0
    preact_penalty: float = 0.0  # p: weight of the actor's pre-tanh penalty (0 = off, the paper)
    preact_threshold: float = 0.0  # u0: the pre-tanh magnitude the penalty starts at
    timeout_bootstrap: bool = True  # a truncated transition (time-out) bootstraps; False: every done is terminal (the paper)


SATURATED_PREACT = math.atanh(0.99)  # |u| above this: |tanh(u)| > 0.99, tanh's gradient < 0.02


def smoothed_target_action(actor_target: nn.Module, obs: torch.Tensor, noise_std: float, noise_clip: float) -> torch.Tensor:
    """Target policy smoothing: clip(mu_targ(o) + clip(N(0, std), -c, c), -1, 1), any leading shape."""
    mu = full_precision(actor_target(obs))
    eps = (torch.randn_like(mu) * noise_std).clamp(-noise_clip, noise_clip)
    return (mu + eps).clamp(-1.0, 1.0)


def not_done(batch: dict[str, torch.Tensor], timeout_bootstrap: bool = True) -> torch.Tensor:
    """1 - d: d = terminated and not truncated (a time-out bootstraps), or with ``timeout_bootstrap=False`` terminated or truncated."""
    terminated, truncated = batch[col.TERMINATEDS].bool(), batch[col.TRUNCATEDS].bool()
    done = terminated & ~truncated if timeout_bootstrap else terminated | truncated
    return 1.0 - done.float()


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
    q1_t, q2_t = local_q_target(batch[col.NEXT_OBS], next_a)
    y_local = batch[col.REWARDS] + cfg.gamma * nd * torch.minimum(full_precision(q1_t), full_precision(q2_t))
    if central_target is None:
        return y_local, None
    mask_next = batch[col.NEXT_OTHERS_MASK].bool()
    others_next_a = smoothed_target_action(actor_target, batch[col.NEXT_OTHERS_OBS], cfg.target_noise, cfg.target_noise_clip)
    others_next_a = others_next_a * mask_next.unsqueeze(-1)
    g1_t, g2_t = central_target.q_values(
        batch[col.NEXT_OBS], batch[col.NEXT_STATE], next_a, batch[col.NEXT_OTHERS_STATE], others_next_a, mask_next
    )
    y_global = batch[col.GLOBAL_REWARDS] + cfg.gamma * nd * torch.minimum(full_precision(g1_t), full_precision(g2_t))
    return y_local, y_global


def local_critic_loss(local_q: nn.Module, batch: dict[str, torch.Tensor], y_local: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """Eq. 7: sum over the twin local critics of the mean squared TD error."""
    q1, q2 = map(full_precision, local_q(batch[col.OBS], batch[col.ACTIONS]))
    loss = ((q1 - y_local) ** 2).mean() + ((q2 - y_local) ** 2).mean()
    return loss, {"local_q1_mean": q1.mean().detach(), "local_q_target_mean": y_local.mean()}


def central_critic_loss(
    central: nn.Module, batch: dict[str, torch.Tensor], y_global: torch.Tensor, cfg: LossConfig
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
    cfg: LossConfig,
) -> tuple[torch.Tensor, dict]:
    """Eq. 12 (ITD3: the individual term only), plus the optional pre-tanh penalty.

    Gradients reach critic parameters too: take only the actor's. ``actor`` exposes
    ``preactivation(obs)`` (its output before the tanh); the stats include the share of saturated
    outputs (``actor_saturation``: |tanh(u)| > 0.99) and the mean |u|.
    """
    pre = full_precision(actor.preactivation(batch[col.OBS]))
    a = torch.tanh(pre)
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


def actor_objective_loss(
    objective: torch.Tensor, pre: torch.Tensor, stats: dict, penalty_weight: float, penalty_threshold: float
) -> tuple[torch.Tensor, dict]:
    """The actor loss -mean(objective) plus the optional pre-tanh penalty.

    ``stats`` gains the saturation share, the mean |u| and ``actor_action_std``: the std over the
    batch of the action that varies least (NaN for a one-row batch); near 0, the actor gives that
    action whatever it observes (a collapsed actor, e.g. always braking).
    """
    loss = -objective.mean()
    u = pre.detach().abs()
    spread = torch.tanh(pre.detach()).std(0).min() if pre.shape[0] > 1 else torch.full((), float("nan"), device=pre.device)
    stats.update(actor_saturation=(u > SATURATED_PREACT).float().mean(), actor_preact_abs=u.mean(), actor_action_std=spread)
    if penalty_weight > 0:
        penalty = preact_penalty(pre, penalty_weight, penalty_threshold)
        loss = loss + penalty
        stats["actor_preact_penalty"] = penalty.detach()
    return loss, stats


def preact_penalty(pre: torch.Tensor, weight: float, threshold: float = 0.0) -> torch.Tensor:
    """``weight * mean(max(|u| - threshold, 0)^2)`` over pre-tanh outputs u (threshold 0: the plain ``weight * mean(u^2)``)."""
    return weight * torch.relu(pre.abs() - threshold).square().mean()
