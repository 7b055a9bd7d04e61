"""CIG-TD3 losses against hand-written references on tiny tensors (fake, linear networks)."""

from types import SimpleNamespace

import torch
from torch import nn

from coin_app.algorithms.cig_td3.losses import CigTd3LossConfig as LossConfig
from coin_app.algorithms.cig_td3.losses import actor_loss, central_critic_loss, td_targets
from coin_app.algorithms.td3 import losses as td3_losses
from coin_app.algorithms.td3.losses import local_critic_loss, smoothed_target_action

torch.manual_seed(0)
B, N, O, S, A = 5, 3, 4, 10, 2


class FakeActor(nn.Module):
    def __init__(self):
        super().__init__()
        self.lin = nn.Linear(O, A)

    def forward(self, obs):
        return torch.tanh(self.lin(obs))

    def preactivation(self, obs):
        return self.lin(obs)


class FakeTwinQ(nn.Module):
    def __init__(self):
        super().__init__()
        self.q1n, self.q2n = nn.Linear(O + A, 1), nn.Linear(O + A, 1)

    def forward(self, obs, act):
        x = torch.cat([obs, act], -1)
        return self.q1n(x).squeeze(-1), self.q2n(x).squeeze(-1)

    def q1_only(self, obs, act):
        return self.q1n(torch.cat([obs, act], -1)).squeeze(-1)


class FakeCentral(nn.Module):
    """Q^g_k = w_k . [o, s, a, sum_j m_j (s_j, a_j)]; V = u . [o, s, sum_j m_j (s_j, a_j)]."""

    def __init__(self):
        super().__init__()
        self.w1, self.w2 = nn.Linear(O + S + A + S + A, 1), nn.Linear(O + S + A + S + A, 1)
        self.u = nn.Linear(O + S + S + A, 1)

    @staticmethod
    def pool(others_state, others_action, mask):
        return (torch.cat([others_state, others_action], -1) * mask.unsqueeze(-1)).sum(1)

    def q_values(self, obs, state, action, others_state, others_action, mask):
        x = torch.cat([obs, state, action, self.pool(others_state, others_action, mask)], -1)
        return self.w1(x).squeeze(-1), self.w2(x).squeeze(-1)

    def q1(self, *args):
        return self.q_values(*args)[0]

    def baseline(self, obs, state, others_state, others_action, mask):
        return self.u(torch.cat([obs, state, self.pool(others_state, others_action, mask)], -1)).squeeze(-1)

    def cvae_loss(self, obs, state, action, others_state, others_action, mask, target_y):
        recon = ((self.w1.weight.sum() - target_y.mean()) ** 2).reshape(())
        return recon, torch.tensor(0.25)

    def forward(self, obs, state, action, others_state, others_action, mask, target_y=None):
        q1, q2 = self.q_values(obs, state, action, others_state, others_action, mask)
        v = self.baseline(obs, state, others_state, others_action, mask)
        recon, kl = (
            (torch.tensor(0.0), torch.tensor(0.0))
            if target_y is None
            else self.cvae_loss(obs, state, action, others_state, others_action, mask, target_y)
        )
        return SimpleNamespace(q1=q1, q2=q2, v=v, recon_mse=recon, kl=kl)


def make_batch():
    g = torch.Generator().manual_seed(1)

    def r(*shape):
        return torch.randn(*shape, generator=g)

    return {
        "obs": r(B, O),
        "state": r(B, S),
        "actions": r(B, A).clamp(-1, 1),
        "rewards": r(B),
        "global_rewards": r(B),
        "terminateds": torch.tensor([False, True, True, False, False]),
        "truncateds": torch.tensor([False, False, True, True, False]),
        "new_obs": r(B, O),
        "new_state": r(B, S),
        "others_state": r(B, N, S),
        "others_actions": r(B, N, A),
        "others_mask": torch.tensor([[1, 1, 0], [1, 0, 0], [0, 0, 0], [1, 1, 1], [1, 0, 1]], dtype=torch.bool),
        "next_others_state": r(B, N, S),
        "next_others_obs": r(B, N, O),
        "next_others_mask": torch.tensor([[1, 0, 0], [1, 1, 0], [0, 0, 0], [1, 1, 1], [0, 0, 1]], dtype=torch.bool),
    }


NO_NOISE = LossConfig(gamma=0.9, target_noise=0.0, target_noise_clip=0.5)


def test_td_targets_match_hand_computation_and_timeouts_bootstrap():
    batch = make_batch()
    actor, local_q, central = FakeActor(), FakeTwinQ(), FakeCentral()
    y_l, y_g = td_targets(batch, actor, local_q, central, NO_NOISE)
    # by hand: d = terminated and not truncated -> only row 1 stops bootstrapping
    not_done = torch.tensor([1.0, 0.0, 1.0, 1.0, 1.0])
    a_next = actor(batch["new_obs"])
    q1, q2 = local_q(batch["new_obs"], a_next)
    expect_l = batch["rewards"] + 0.9 * not_done * torch.minimum(q1, q2)
    assert torch.allclose(y_l, expect_l)
    m = batch["next_others_mask"]
    a_others = actor(batch["next_others_obs"]) * m.unsqueeze(-1)
    g1, g2 = central.q_values(batch["new_obs"], batch["new_state"], a_next, batch["next_others_state"], a_others, m)
    assert torch.allclose(y_g, batch["global_rewards"] + 0.9 * not_done * torch.minimum(g1, g2))
    # without a centralized critic: no global target, and y^l is TD3's (ITD3's) target
    assert td_targets(batch, actor, local_q, None, NO_NOISE)[1] is None
    assert torch.equal(td3_losses.td_target(batch, actor, local_q, NO_NOISE), y_l)


def test_timeouts_end_the_targets_without_timeout_bootstrap():
    """timeout_bootstrap=False (the paper's d_i): every done row is terminal, truncated ones too; the others bootstrap as before."""
    batch = make_batch()
    actor, local_q, central = FakeActor(), FakeTwinQ(), FakeCentral()
    cfg = LossConfig(gamma=0.9, target_noise=0.0, target_noise_clip=0.5, timeout_bootstrap=False)
    y_l, y_g = td_targets(batch, actor, local_q, central, cfg)
    # by hand: rows 1 (terminated), 2 (both flags) and 3 (truncated) stop bootstrapping; rows 0 and 4 bootstrap
    not_done = torch.tensor([1.0, 0.0, 0.0, 0.0, 1.0])
    a_next = actor(batch["new_obs"])
    q1, q2 = local_q(batch["new_obs"], a_next)
    assert torch.allclose(y_l, batch["rewards"] + 0.9 * not_done * torch.minimum(q1, q2))
    assert torch.equal(y_l[1:4], batch["rewards"][1:4])
    m = batch["next_others_mask"]
    a_others = actor(batch["next_others_obs"]) * m.unsqueeze(-1)
    g1, g2 = central.q_values(batch["new_obs"], batch["new_state"], a_next, batch["next_others_state"], a_others, m)
    assert torch.allclose(y_g, batch["global_rewards"] + 0.9 * not_done * torch.minimum(g1, g2))
    y_default, _ = td_targets(batch, actor, local_q, central, NO_NOISE)
    assert torch.equal(y_default[[0, 4]], y_l[[0, 4]]) and not torch.allclose(y_default[2:4], y_l[2:4])


def test_target_smoothing_noise_is_clipped():
    actor = FakeActor()
    obs = torch.randn(2000, O)
    a = smoothed_target_action(actor, obs, noise_std=10.0, noise_clip=0.2)
    mu = actor(obs)
    assert ((a - mu).abs() <= 0.2 + 1e-6).all() and a.abs().max() <= 1.0
    assert ((a - mu).abs() > 0.19).float().mean() > 0.5  # big noise saturates at the clip


def test_local_and_central_losses_equal_reference():
    batch = make_batch()
    local_q, central = FakeTwinQ(), FakeCentral()
    y = torch.randn(B)
    loss, _ = local_critic_loss(local_q, batch, y)
    q1, q2 = local_q(batch["obs"], batch["actions"])
    assert torch.allclose(loss, ((q1 - y) ** 2).mean() + ((q2 - y) ** 2).mean())
    cfg = LossConfig(vae_weight=0.5, kl_beta=2.0)
    loss_g, stats = central_critic_loss(central, batch, y, cfg)
    args = (batch["obs"], batch["state"], batch["actions"], batch["others_state"], batch["others_actions"], batch["others_mask"])
    g1, g2 = central.q_values(*args)
    v = central.baseline(batch["obs"], batch["state"], batch["others_state"], batch["others_actions"], batch["others_mask"])
    target_y = torch.cat([batch["new_obs"], batch["new_state"], batch["rewards"][:, None]], -1)
    recon, kl = central.cvae_loss(*args, target_y)
    expect = ((g1 - y) ** 2).mean() + ((g2 - y) ** 2).mean() + ((v - y) ** 2).mean() + 0.5 * (recon + 2.0 * kl)
    assert torch.allclose(loss_g, expect)
    # without the baseline and the CVAE only the twin global Q terms remain
    loss_q, _ = central_critic_loss(central, batch, y, LossConfig(counterfactual_baseline=False, vae_weight=0.0))
    assert torch.allclose(loss_q, ((g1 - y) ** 2).mean() + ((g2 - y) ** 2).mean())


def test_actor_loss_reference_and_baseline_leaves_actor_gradient_unchanged():
    batch = make_batch()
    actor, local_q, central = FakeActor(), FakeTwinQ(), FakeCentral()
    cfg = LossConfig(global_weight=0.7)
    loss, _ = actor_loss(actor, local_q, central, batch, cfg)
    a = actor(batch["obs"])
    m = batch["others_mask"]
    qg = central.q1(batch["obs"], batch["state"], a, batch["others_state"], batch["others_actions"], m)
    v = central.baseline(batch["obs"], batch["state"], batch["others_state"], batch["others_actions"], m)
    expect = -(local_q.q1_only(batch["obs"], a) + 0.7 * (qg - v)).mean()
    assert torch.allclose(loss, expect)
    # Eq. 12's V does not depend on the actor: actor gradients are equal with and without it
    params = list(actor.parameters())
    g_with = torch.autograd.grad(actor_loss(actor, local_q, central, batch, cfg)[0], params)
    g_without = torch.autograd.grad(
        actor_loss(actor, local_q, central, batch, LossConfig(global_weight=0.7, counterfactual_baseline=False))[0], params
    )
    for x, y in zip(g_with, g_without):
        assert torch.allclose(x, y, atol=1e-7)
    # without a centralized critic: the individual term only, TD3's (ITD3's) actor loss
    loss_itd3, _ = actor_loss(actor, local_q, None, batch, cfg)
    assert torch.allclose(loss_itd3, -local_q.q1_only(batch["obs"], actor(batch["obs"])).mean())
    assert torch.equal(td3_losses.actor_loss(actor, local_q, batch, cfg)[0], loss_itd3)
