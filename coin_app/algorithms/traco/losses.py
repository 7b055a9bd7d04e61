"""TraCo-TD3 losses (TraCo as COIN §5.2 ran it), readable top to bottom, free of RLlib.

Notation (one row per sampled agent transition i at env step t; columns of ``td3/columns.py``):
    o, s, a, r, d           ego observation, local state, action, reward, done (terminated, not truncated)
    S, A, R, M              other agents acting at t: states, actions, rewards, mask      (B, N, .)
    S', O', M'              other agents with an observation at t+1
    D  = M  & |p_j - p_i| < rho            the ego's domain at t   (rho = domain_radius, 40 m)
    D' = M' & |p'_j - p'_i| < rho          the ego's domain at t+1

    r^D  = domain reward: mean of r over {i} and D ("mean"); over D only, 0 if empty ("neighbours",
           CoPO's nei_rewards); r itself ("own")
    a'   = clip(mu_targ(o') + clip(eps, -c, c), -1, 1),  A' = the same for O'      eps ~ N(0, sigma)
    y^D  = r^D + gamma (1 - d) min_k Q^D_targ,k(o', a', s', S', A', D')
    L_Q  = sum_k mean (Q^D_k(o, a, s, S, A, D) - y^D)^2                      twin domain critic
    L_b  = mean (b(o, s, S, A, D) - y^D)^2                                  counterfactual baseline
    A^cf = Q^D_1(o, a, .) - b(o, .)                                        (logged)
    L_pi = -mean[ Q^l_1(o, mu(o)) (individual critic only) + w (Q^D_1(o, mu(o), s, S, A, D) - b(o, .)) ]
           + p mean[ max(|u(o)| - u0, 0)^2 ]          (TD3's optional pre-tanh guard)
    with the individual critic: y^l, L_l as TD3's (``td3/losses.py``, COIN Eqs. 7-8) on r.

mu(o) enters the ego token and hence the attention query, so the actor's gradient flows through
the attention. b has no ego action, so it carries no actor gradient (as COIN's Eq. 12); it is
still trained and subtracted as the spec writes it. Every network output is widened to fp32
before it enters a target, a difference or a mean (bf16 autocast, as TD3's losses).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from coin_app.algorithms.choices import DOMAIN_REWARDS
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.losses import LossConfig, actor_objective_loss, bootstrap, not_done, policy, smoothed_target_action
from coin_app.algorithms.td3.networks import full_precision
from coin_app.algorithms.traco.networks import compact_domain, counterfactual_advantage, neighbourhood_mask


@dataclass(frozen=True)
class TracoLossConfig(LossConfig):
    """The constants the TraCo losses need: TD3's and the domain critic's (a view of ``TracoConfig``)."""

    domain_radius: float = 40.0
    position_scale: float = 1.0  # local-state positions x this = metres (the map's scale)
    domain_reward: str = "mean"
    counterfactual_baseline: bool = True
    individual_critic: bool = False
    domain_weight: float = 1.0


def domains(batch: dict[str, torch.Tensor], cfg: TracoLossConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """The ego's domain at t and at t+1, (B, N) bool each: valid others strictly within ``domain_radius`` metres."""
    d0 = neighbourhood_mask(batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_MASK], cfg.domain_radius, cfg.position_scale)
    d1 = neighbourhood_mask(
        batch[col.NEXT_STATE], batch[col.NEXT_OTHERS_STATE], batch[col.NEXT_OTHERS_MASK], cfg.domain_radius, cfg.position_scale
    )
    return d0, d1


def domain_batch(batch: dict[str, torch.Tensor], cfg: TracoLossConfig) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor]:
    """(``batch`` with the others' columns cut to the largest domain at t and at t+1, the domain at t, the domain at t+1).

    The domain rewards must be taken before (they read the others' rewards at full width); the
    losses below then run their attention on the compacted slots only (``compact_domain``).
    """
    d0, d1 = domains(batch, cfg)
    out = dict(batch)
    d0, out[col.OTHERS_STATE], out[col.OTHERS_ACTIONS] = compact_domain(d0, batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS])
    d1, out[col.NEXT_OTHERS_STATE], out[col.NEXT_OTHERS_OBS] = compact_domain(d1, batch[col.NEXT_OTHERS_STATE], batch[col.NEXT_OTHERS_OBS])
    return out, d0, d1


def domain_rewards(rewards: torch.Tensor, others_rewards: torch.Tensor, domain: torch.Tensor, mode: str) -> torch.Tensor:
    """r^D (B,) from the ego's rewards (B,), the others' rewards (B, N) and the domain (B, N): see the module doc."""
    if mode not in DOMAIN_REWARDS:
        raise ValueError(f"bad value for 'domain_reward': {mode!r}; allowed: {', '.join(map(repr, DOMAIN_REWARDS))}")
    if mode == "own":
        return rewards
    m = domain.to(rewards.dtype)
    total = (others_rewards * m).sum(-1)
    count = m.sum(-1)
    if mode == "mean":
        return (rewards + total) / (1.0 + count)
    return total / count.clamp(min=1.0)


@torch.no_grad()
def td_targets(
    batch: dict[str, torch.Tensor],
    next_domain: torch.Tensor,
    domain_reward: torch.Tensor,
    actor_target: nn.Module,
    domain_q_target: nn.Module,
    local_q_target: nn.Module | None,
    cfg: TracoLossConfig,
) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The domain target y^D and, with the individual critic, y^l (else None)."""
    nd = not_done(batch, cfg.timeout_bootstrap)
    next_a = smoothed_target_action(actor_target, batch[col.NEXT_OBS], cfg.target_noise, cfg.target_noise_clip)
    others_next_a = smoothed_target_action(actor_target, batch[col.NEXT_OTHERS_OBS], cfg.target_noise, cfg.target_noise_clip)
    others_next_a = others_next_a * next_domain.unsqueeze(-1)
    q1_t, q2_t = domain_q_target(
        batch[col.NEXT_OBS], next_a, batch[col.NEXT_STATE], batch[col.NEXT_OTHERS_STATE], others_next_a, next_domain
    )
    y_domain = bootstrap(domain_reward, nd, q1_t, q2_t, cfg.gamma)
    if local_q_target is None:
        return y_domain, None
    return y_domain, bootstrap(batch[col.REWARDS], nd, *local_q_target(batch[col.NEXT_OBS], next_a), cfg.gamma)


def domain_critic_loss(
    domain_q: nn.Module, batch: dict[str, torch.Tensor], domain: torch.Tensor, y_domain: torch.Tensor
) -> tuple[torch.Tensor, dict[str, torch.Tensor], torch.Tensor]:
    """L_Q: the twin domain critics' summed mean squared TD errors, their stats and Q^D_1 on the buffer actions (detached)."""
    q1, q2 = map(
        full_precision,
        domain_q(batch[col.OBS], batch[col.ACTIONS], batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], domain),
    )
    loss = ((q1 - y_domain) ** 2).mean() + ((q2 - y_domain) ** 2).mean()
    stats = {
        "domain_q1_mean": q1.mean().detach(),
        "domain_q_target_mean": y_domain.mean(),
        "domain_size_mean": domain.float().sum(-1).mean(),
    }
    return loss, stats, q1.detach()


def baseline_loss(
    baseline: nn.Module, batch: dict[str, torch.Tensor], domain: torch.Tensor, y_domain: torch.Tensor, q1: torch.Tensor | None = None
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """L_b: the counterfactual baseline regressed on y^D; with ``q1`` (Q^D_1 on the buffer action) the advantage is logged too."""
    b = full_precision(baseline(batch[col.OBS], batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], domain))
    loss = ((b - y_domain) ** 2).mean()
    stats = {"baseline_mean": b.mean().detach()}
    if q1 is not None:
        stats["counterfactual_advantage"] = counterfactual_advantage(q1, b.detach()).mean()
    return loss, stats


def actor_loss(
    actor: nn.Module,
    domain_q: nn.Module,
    baseline: nn.Module | None,
    local_q: nn.Module | None,
    batch: dict[str, torch.Tensor],
    domain: torch.Tensor,
    cfg: TracoLossConfig,
) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    """L_pi (see the module doc); gradients reach critic parameters too: take only the actor's."""
    pre, a = policy(actor, batch[col.OBS])
    q_domain = full_precision(
        domain_q.q1_only(batch[col.OBS], a, batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], domain)
    )
    advantage = q_domain
    stats = {"actor_q_domain": q_domain.mean().detach()}
    if baseline is not None:
        with torch.no_grad():  # b has no ego action: no actor gradient
            b = full_precision(baseline(batch[col.OBS], batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], domain))
        advantage = counterfactual_advantage(q_domain, b)
        stats["actor_counterfactual_advantage"] = advantage.mean().detach()
    objective = cfg.domain_weight * advantage
    if local_q is not None:
        q_local = full_precision(local_q.q1_only(batch[col.OBS], a))
        objective = objective + q_local
        stats["actor_q_local"] = q_local.mean().detach()
    return actor_objective_loss(objective, pre, stats, cfg.preact_penalty, cfg.preact_threshold)
