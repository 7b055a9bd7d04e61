"""The centralized critic against a dense reference of its equations: outputs, TD targets, losses and gradients.

The reference computes COIN's critic (Eqs. 1-6, 9-11) the plain way, as the critic did before its
speed work (issue 55, part 4): every one of the N padded slots is a graph node, the CVAE runs on the
concatenation ``[o_i, s_i, a_i, s_j, a_j]`` of every slot, each GAT head is a dense masked softmax,
and both GAT layers run for every receiver. It reads the critic's own parameters, so the two must
agree to float round-off in fp32, and within bf16 rounding under bf16 autocast, on batches whose
padding is everywhere: inside rows, in trailing columns no row fills, and rows with no other agent.
"""

import copy
import math
from types import SimpleNamespace

import pytest
import torch
import torch.nn.functional as F

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig, CriticOutputs
from coin_app.algorithms.cig_td3.losses import CigTd3LossConfig, actor_loss, central_critic_loss, td_targets
from coin_app.algorithms.cig_td3.pairwise import PairAttention, PairCVAE
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.networks import Actor, TwinQ, full_precision, q_head

torch.set_num_threads(1)

B, N, O, S, A, L = 12, 7, 9, 10, 2, 4
SMALL = dict(obs_dim=O, state_dim=S, act_dim=A, latent_dim=L, hidden=24, node_width=16)
# relative loss error and gradient cosine of two bf16 computations (as tests/test_cig_td3_precision.py for bf16 vs fp32)
BF16_RTOL, BF16_COSINE = 0.02, 0.99


# ---------------------------------------------------------------- the dense reference
def lin(layer, x):
    return F.linear(x, layer.weight, layer.bias)


def dense_graph(state, action, others_state, others_action, others_mask, radius, scale):
    """(state_all, action_all, valid, adj) over all N + 1 slots; padded contents zeroed, self-loops everywhere."""
    m = others_mask.bool()
    state_all = torch.cat([state[:, None], torch.where(m[..., None], others_state, 0.0)], 1)
    action_all = torch.cat([action[:, None], torch.where(m[..., None], others_action, 0.0)], 1)
    valid = torch.cat([torch.ones(len(m), 1, dtype=torch.bool), m], 1)
    adj = valid[:, :, None] & valid[:, None, :]
    if radius is not None:
        pos = state_all[..., :2] * scale
        adj &= (pos[:, :, None] - pos[:, None, :]).square().sum(-1) <= radius * radius
    return state_all, action_all, valid, adj | torch.eye(valid.shape[1], dtype=torch.bool)


def dense_gat_layer(layer, h, adj, valid):
    """One GAT layer for every receiver: per head, masked softmax of LeakyReLU(a_recv . W h_i + a_nbr . W h_j); heads concatenated."""
    outs = []
    for k, w_k in enumerate(layer.W.weight.split(layer.out_dim)):
        wh = h @ w_k.T
        e = F.leaky_relu((wh @ layer.a_recv[k])[:, :, None] + (wh @ layer.a_nbr[k])[:, None, :], layer.leaky_slope)
        alpha = torch.softmax(e.masked_fill(~adj, float("-inf")), -1)
        outs.append(F.relu(alpha @ wh) * valid[..., None])
    return torch.cat(outs, -1)


def dense_branch(branch, node_x, obs_x, adj, valid):
    h = branch.node_mlp(node_x) * valid[..., None]
    gat = branch.graph
    assert gat.kind == "gat"
    g = dense_gat_layer(gat.layers[1], dense_gat_layer(gat.layers[0], h, adj, valid), adj, valid)[:, 0]
    return q_head(torch.cat([g, branch.obs_mlp(obs_x)], -1), branch.head, branch.feature_norm).squeeze(-1)


def dense_cvae_encode(cvae, ego_x, pair):
    x = torch.cat([ego_x[:, None].expand(-1, pair.shape[1], -1), pair], -1)
    h = cvae.enc_body(F.relu(lin(cvae.enc_in.linear, x)))
    return lin(cvae.mu_head, h), lin(cvae.logvar_head, h)


class DenseCritic:
    """The critic's methods (``forward``, ``q_values``, ``q1``, ``baseline``) computed densely from ``critic``'s parameters."""

    def __init__(self, critic: CentralCritic) -> None:
        self.critic, self.cfg = critic, critic.cfg

    def _setup(self, obs, state, action, others_state, others_action, others_mask):
        state_all, action_all, valid, adj = dense_graph(
            state, action, others_state, others_action, others_mask, self.cfg.graph_radius, self.cfg.position_scale
        )
        return torch.cat([obs, state, action], -1), torch.cat([state_all, action_all], -1), state_all, action_all, valid, adj

    def _q_nodes(self, ego_x, pair, mu):
        local = self.critic.local
        if local is None:
            return pair
        if isinstance(local, PairAttention):
            gate = torch.sigmoid((lin(local.query, ego_x)[:, None] * lin(local.key, pair)).sum(-1, keepdim=True) * local.scale)
            return torch.cat([pair, gate * lin(local.value, pair)], -1)
        if mu is None:
            mu = dense_cvae_encode(local, ego_x, pair)[0]
        return torch.cat([pair, mu.detach() if self.cfg.detach_latent else mu], -1)

    def forward(self, obs, state, action, others_state, others_action, others_mask, target_y=None, generator=None):
        ego_x, pair, state_all, action_all, valid, adj = self._setup(obs, state, action, others_state, others_action, others_mask)
        recon = kl = obs.new_zeros(())
        mu = None
        if isinstance(self.critic.local, PairCVAE) and target_y is not None:
            cvae = self.critic.local
            mu, logvar = map(full_precision, dense_cvae_encode(cvae, ego_x, pair))
            eps = torch.zeros_like(mu)  # drawn for the valid pairs in row-major (b, j) order, as the critic does
            eps[valid] = torch.randn(int(valid.sum()), mu.shape[-1], generator=generator, dtype=mu.dtype)
            z = mu + eps * torch.exp(0.5 * logvar)
            d = torch.cat([ego_x[:, None].expand(-1, pair.shape[1], -1), z, pair], -1)
            y_hat = full_precision(cvae.dec_body(F.relu(lin(cvae.dec_in.linear, d))))
            y = target_y[:, None].expand_as(y_hat) if target_y.dim() == 2 else target_y
            recon = (y_hat - y)[valid].square().mean()
            kl = -0.5 * (1.0 + logvar - mu.square() - logvar.exp())[valid].mean()
        node_x, obs_x = self._q_nodes(ego_x, pair, mu), torch.cat([obs, action], -1)
        q1 = dense_branch(self.critic.q1_branch, node_x, obs_x, adj, valid)
        q2 = dense_branch(self.critic.q2_branch, node_x, obs_x, adj, valid)
        return CriticOutputs(q1, q2, self._v(obs, state_all, action_all, adj, valid), recon, kl)

    __call__ = forward

    def _v(self, obs, state_all, action_all, adj, valid):
        action_v = torch.cat([torch.zeros_like(action_all[:, :1]), action_all[:, 1:]], 1)
        return dense_branch(self.critic.v_branch, torch.cat([state_all, action_v], -1), obs, adj, valid)

    def q_values(self, obs, state, action, others_state, others_action, others_mask):
        ego_x, pair, _, _, valid, adj = self._setup(obs, state, action, others_state, others_action, others_mask)
        node_x, obs_x = self._q_nodes(ego_x, pair, None), torch.cat([obs, action], -1)
        return dense_branch(self.critic.q1_branch, node_x, obs_x, adj, valid), dense_branch(
            self.critic.q2_branch, node_x, obs_x, adj, valid
        )

    def q1(self, obs, state, action, others_state, others_action, others_mask):
        ego_x, pair, _, _, valid, adj = self._setup(obs, state, action, others_state, others_action, others_mask)
        return dense_branch(self.critic.q1_branch, self._q_nodes(ego_x, pair, None), torch.cat([obs, action], -1), adj, valid)

    def baseline(self, obs, state, others_state, others_action, others_mask):
        dummy = state.new_zeros(len(state), self.cfg.act_dim)
        _, _, state_all, action_all, valid, adj = self._setup(obs, state, dummy, others_state, others_action, others_mask)
        return self._v(obs, state_all, action_all, adj, valid)


# ---------------------------------------------------------------- batches and networks
def masks(g):
    """(B, N) masks with gaps inside rows, a row with no other agent, and the last two columns empty in every row."""
    m = torch.rand(B, N, generator=g) < 0.6
    m[:, -2:] = False
    m[0] = False
    m[1, : N - 2] = True
    return m


def make_batch(seed=0):
    g = torch.Generator().manual_seed(seed)
    mask, next_mask = masks(g), masks(g)
    next_mask[2, -1] = True  # at t+1 one row fills the last slot: nothing to drop there
    rnd = lambda *shape: torch.randn(*shape, generator=g)  # noqa: E731
    act = lambda *shape: torch.rand(*shape, generator=g) * 2 - 1  # noqa: E731
    return {
        col.OBS: rnd(B, O),
        col.STATE: rnd(B, S) * 0.5,
        col.ACTIONS: act(B, A),
        col.REWARDS: rnd(B),
        col.GLOBAL_REWARDS: rnd(B),
        col.TERMINATEDS: torch.arange(B) % 5 == 0,
        col.TRUNCATEDS: torch.arange(B) % 7 == 0,
        col.NEXT_OBS: rnd(B, O),
        col.NEXT_STATE: rnd(B, S) * 0.5,
        col.OTHERS_STATE: rnd(B, N, S) * 0.5 * mask[..., None],
        col.OTHERS_ACTIONS: act(B, N, A) * mask[..., None],
        col.OTHERS_MASK: mask,
        col.NEXT_OTHERS_STATE: rnd(B, N, S) * 0.5 * next_mask[..., None],
        col.NEXT_OTHERS_OBS: rnd(B, N, O) * next_mask[..., None],
        col.NEXT_OTHERS_MASK: next_mask,
    }


def critic_inputs(batch):
    return (
        batch[col.OBS],
        batch[col.STATE],
        batch[col.ACTIONS],
        batch[col.OTHERS_STATE],
        batch[col.OTHERS_ACTIONS],
        batch[col.OTHERS_MASK],
    )


def make_nets(seed=0, **critic_kw):
    torch.manual_seed(seed)
    critic = CentralCritic(CentralCriticConfig(**{**SMALL, **critic_kw}))
    target = copy.deepcopy(critic)
    with torch.no_grad():
        for p in target.parameters():
            p.add_(0.05 * torch.randn_like(p))
    return SimpleNamespace(
        central=critic,
        central_target=target,
        actor=Actor(O, A, (24, 24)),
        actor_target=Actor(O, A, (24, 24)),
        local_q=TwinQ(O, A, (24, 24)),
        local_q_target=TwinQ(O, A, (24, 24)),
    )


CASES = {
    "default (cvae, 2-head gat)": {},
    "radius graph": dict(graph_radius=1.0, position_scale=1.0),
    "1 head, default init": dict(gat_heads=1, gat_init="default"),
    "3 heads, feature norm": dict(gat_heads=3, feature_norm=True),
    "detached latent": dict(detach_latent=True),
    "attention local module": dict(local_module="attention"),
    "no local module": dict(local_module="none"),
}


def close(a, b, rtol, atol):
    torch.testing.assert_close(a, b, rtol=rtol, atol=atol)


# ---------------------------------------------------------------- outputs
@pytest.mark.parametrize("case", CASES)
def test_critic_outputs_equal_the_dense_reference_in_fp32(case):
    nets = make_nets(**CASES[case])
    critic, ref = nets.central, DenseCritic(nets.central)
    batch = make_batch()
    x = critic_inputs(batch)
    per_pair_y = torch.randn(B, N + 1, O + S + 1, generator=torch.Generator().manual_seed(3))
    for target_y in (None, torch.cat([batch[col.NEXT_OBS], batch[col.NEXT_STATE], batch[col.REWARDS][:, None]], -1), per_pair_y):
        out = critic(*x, target_y=target_y, generator=torch.Generator().manual_seed(9))
        want = ref.forward(*x, target_y=target_y, generator=torch.Generator().manual_seed(9))
        for name in CriticOutputs._fields:
            close(getattr(out, name), getattr(want, name), 1e-5, 1e-6)
    for a, b in zip(critic.q_values(*x), ref.q_values(*x), strict=True):
        close(a, b, 1e-5, 1e-6)
    close(critic.q1(*x), ref.q1(*x), 1e-5, 1e-6)
    close(critic.baseline(*x[:2], *x[3:]), ref.baseline(*x[:2], *x[3:]), 1e-5, 1e-6)
    assert not torch.allclose(out.q1, out.q2)  # the twin heads really differ (the comparison is not vacuous)


# ---------------------------------------------------------------- losses and gradients
def losses_and_grads(nets, central, central_target, batch, precision):
    """(loss, flat gradient of its network) for the centralized-critic and actor losses, the global TD target, as the learner takes them."""
    cfg = CigTd3LossConfig()
    ctx = torch.autocast("cpu", dtype=torch.bfloat16) if precision == "bf16" else torch.autocast("cpu", enabled=False)
    torch.manual_seed(5)  # the same target-smoothing noise and CVAE samples on both sides
    with ctx:
        _, y_global = td_targets(batch, nets.actor_target, nets.local_q_target, central_target, cfg)
        loss_c, stats_c = central_critic_loss(central, batch, y_global, cfg)
        loss_a, stats_a = actor_loss(nets.actor, nets.local_q, central, batch, cfg)
    params_c, params_a = list(nets.central.parameters()), list(nets.actor.parameters())
    grad_c = torch.cat([g.flatten() for g in torch.autograd.grad(loss_c, params_c)])
    grad_a = torch.cat([g.flatten() for g in torch.autograd.grad(loss_a, params_a)])
    stats = {k: float(v) for k, v in {**stats_c, **stats_a}.items()}
    return {"y_global": y_global, "central": (float(loss_c.detach()), grad_c), "actor": (float(loss_a.detach()), grad_a), "stats": stats}


@pytest.mark.parametrize("case", ["default (cvae, 2-head gat)", "radius graph", "attention local module"])
@pytest.mark.parametrize("precision", ["fp32", "bf16"])
def test_td_targets_losses_and_gradients_equal_the_dense_reference(case, precision):
    nets = make_nets(**CASES[case])
    batch = make_batch(seed=1)
    new = losses_and_grads(nets, nets.central, nets.central_target, batch, precision)
    ref = losses_and_grads(nets, DenseCritic(nets.central), DenseCritic(nets.central_target), batch, precision)
    if precision == "fp32":
        close(new["y_global"], ref["y_global"], 1e-5, 1e-6)
        for name in ("central", "actor"):
            assert new[name][0] == pytest.approx(ref[name][0], rel=1e-5), name
            close(new[name][1], ref[name][1], 1e-4, 1e-6)
        assert new["stats"] == pytest.approx(ref["stats"], rel=1e-4, abs=1e-6)
        return
    close(new["y_global"], ref["y_global"], BF16_RTOL, 0.05)
    for name in ("central", "actor"):
        assert new[name][0] == pytest.approx(ref[name][0], rel=BF16_RTOL), name
        assert float(F.cosine_similarity(new[name][1], ref[name][1], dim=0)) > BF16_COSINE, name


def test_bf16_really_rounds_in_this_comparison():
    """The bf16 case is not an fp32 comparison in disguise: bf16 moves the losses away from fp32's."""
    nets = make_nets()
    batch = make_batch(seed=1)
    fp32 = losses_and_grads(nets, nets.central, nets.central_target, batch, "fp32")
    bf16 = losses_and_grads(nets, nets.central, nets.central_target, batch, "bf16")
    assert not math.isclose(fp32["central"][0], bf16["central"][0], rel_tol=1e-6)
