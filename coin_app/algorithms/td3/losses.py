"""TD3 losses (Fujimoto et al., 2018; COIN Eqs. 7, 8 and 12's individual term), readable top to bottom, free of RLlib.

Notation (one row per sampled agent transition i at env step t; columns of ``columns.py``):
    o, a, r, o'       ego observation, action, reward, next observation
    d = terminated and not truncated (a time-out bootstraps; ``timeout_bootstrap=False``: terminated or truncated)

    a'   = clip(mu_targ(o') + clip(eps, -c, c), -1, 1)          eps ~ N(0, sigma)   target policy smoothing (Eq. 8)
    y    = r + gamma (1 - d) min_k Q_targ,k(o', a')                                 clipped double Q (Eq. 8)
    L_Q  = sum_k mean (Q_k(o, a) - y)^2                                             twin critic (Eq. 7)
    L_pi = -mean Q_1(o, mu(o)) + p mean[ max(|u(o)| - u0, 0)^2 ]                    (Eq. 12, individual term)
           u = the actor's pre-tanh output, mu = tanh(u); the penalty is an optional guard against
           saturation (p = 0 in the paper)

The TD3 family's children add to these (CIG-TD3's global target and centralized-critic losses,
TraCo's domain critic) and reuse the pieces: :func:`smoothed_target_action`, :func:`not_done`,
:func:`bootstrap`, :func:`actor_objective_loss`. Every network output is widened to fp32
(``full_precision``) before it enters a target, a difference or a mean, so under bf16 autocast
(``precision="bf16"``) only the networks' own layers run in bf16; with fp32 networks this changes nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.networks import full_precision


@dataclass(frozen=True)
class LossConfig:
    """The constants the TD3 losses need (a view of ``Td3Config``; the children's configs extend it)."""

    gamma: float = 0.99
    target_noise: float = 0.1  # sigma
    target_noise_clip: float = 0.5  # c
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


def bootstrap(reward: torch.Tensor, not_done: torch.Tensor, q1: torch.Tensor, q2: torch.Tensor, gamma: float) -> torch.Tensor:
    """The clipped double-Q target r + gamma (1 - d) min(q1, q2) from the target critics' two values."""
    return reward + gamma * not_done * torch.minimum(full_precision(q1), full_precision(q2))


@torch.no_grad()
def td_target(batch: dict[str, torch.Tensor], actor_target: nn.Module, q_target: nn.Module, cfg: LossConfig) -> torch.Tensor:
    """y (Eq. 8) with the target actor and the target twin critic."""
    next_a = smoothed_target_action(actor_target, batch[col.NEXT_OBS], cfg.target_noise, cfg.target_noise_clip)
    q1_t, q2_t = q_target(batch[col.NEXT_OBS], next_a)
    return bootstrap(batch[col.REWARDS], not_done(batch, cfg.timeout_bootstrap), q1_t, q2_t, cfg.gamma)


def local_critic_loss(local_q: nn.Module, batch: dict[str, torch.Tensor], y_local: torch.Tensor) -> tuple[torch.Tensor, dict]:
    """L_Q (Eq. 7): sum over the twin (individual, local) critics of the mean squared TD error, and its stats."""
    q1, q2 = map(full_precision, local_q(batch[col.OBS], batch[col.ACTIONS]))
    loss = ((q1 - y_local) ** 2).mean() + ((q2 - y_local) ** 2).mean()
    return loss, {"local_q1_mean": q1.mean().detach(), "local_q_target_mean": y_local.mean()}


def policy(actor: nn.Module, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(u, mu): the actor's pre-tanh output and its action tanh(u), in fp32 (``actor`` exposes ``preactivation(obs)``)."""
    pre = full_precision(actor.preactivation(obs))
    return pre, torch.tanh(pre)


def actor_loss(actor: nn.Module, local_q: nn.Module, batch: dict[str, torch.Tensor], cfg: LossConfig) -> tuple[torch.Tensor, dict]:
    """L_pi: -mean Q_1(o, mu(o)) plus the optional pre-tanh penalty, and its stats.

    Gradients reach the critic's parameters too: take only the actor's.
    """
    pre, a = policy(actor, batch[col.OBS])
    q_local = full_precision(local_q.q1_only(batch[col.OBS], a))
    return actor_objective_loss(q_local, pre, {"actor_q_local": q_local.mean().detach()}, cfg.preact_penalty, cfg.preact_threshold)


def actor_objective_loss(
    objective: torch.Tensor, pre: torch.Tensor, stats: dict, penalty_weight: float, penalty_threshold: float
) -> tuple[torch.Tensor, dict]:
    """The actor loss -mean(objective) plus the optional pre-tanh penalty.

    ``stats`` gains the saturation share (``actor_saturation``: |tanh(u)| > 0.99), the mean |u| and
    ``actor_action_std``: the std over the batch of the action that varies least (NaN for a one-row
    batch); near 0, the actor gives that action whatever it observes (a collapsed actor, e.g. always braking).
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
