"""CIG-TD3 networks: masking, invariances, radius graph, baseline independence, CVAE loss against hand formulas."""

import itertools
import math

import pytest
import torch
import torch.nn.functional as F

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig
from coin_app.algorithms.cig_td3.graph import GAT_INITS, GLOBAL_MODULES, GATLayer, GraphModule, build_graph
from coin_app.algorithms.cig_td3.pairwise import LOCAL_MODULES
from coin_app.algorithms.td3.networks import Actor, TwinQ, mlp

torch.set_num_threads(1)

B, N, O, S, A, L = 3, 4, 6, 4, 2, 3
SMALL = dict(obs_dim=O, state_dim=S, act_dim=A, latent_dim=L, hidden=16, node_width=8)
MASK = torch.tensor([[True, False, True, True], [True, True, True, True], [False, False, False, False]])


def make_critic(seed=0, **kw):
    torch.manual_seed(seed)
    return CentralCritic(CentralCriticConfig(**{**SMALL, **kw}))


def make_inputs(seed=1, mask=MASK):
    g = torch.Generator().manual_seed(seed)
    return dict(
        obs=torch.randn(B, O, generator=g),
        state=torch.randn(B, S, generator=g),
        action=torch.rand(B, A, generator=g) * 2 - 1,
        others_state=torch.randn(B, N, S, generator=g),
        others_action=torch.rand(B, N, A, generator=g) * 2 - 1,
        others_mask=mask.clone(),
    )


def target_for(seed=2, per_pair=False):
    g = torch.Generator().manual_seed(seed)
    shape = (B, N + 1, O + S + 1) if per_pair else (B, O + S + 1)
    return torch.randn(*shape, generator=g)


def run_all(critic, x, target_y=None, seed=7):
    out = critic(**x, target_y=target_y, generator=torch.Generator().manual_seed(seed))
    return out


# ---------------------------------------------------------------- small networks
def test_mlp_actor_twinq_shapes_and_ranges():
    net = mlp([5, 7, 3], torch.nn.ReLU, torch.nn.Tanh)
    assert [type(m).__name__ for m in net] == ["Linear", "ReLU", "Linear", "Tanh"]
    with pytest.raises(ValueError, match="sizes"):
        mlp([5], torch.nn.ReLU)
    torch.manual_seed(0)
    actor = Actor(O, A, (16, 16))
    a = actor(torch.randn(32, O) * 100)
    assert a.shape == (32, A) and a.abs().max() <= 1.0
    q = TwinQ(O, A, (16, 16))
    obs, act = torch.randn(5, O), torch.rand(5, A)
    q1, q2 = q(obs, act)
    assert q1.shape == q2.shape == (5,)
    assert not torch.equal(q1, q2)  # separate weights
    assert torch.equal(q.q1_only(obs, act), q1)


def test_critic_feature_norm_divides_the_last_hidden_features_by_their_norm():
    """Penultimate normalization by hand: the same weights, features / ||features||, then the output layer."""
    torch.manual_seed(0)
    plain = TwinQ(O, A, (16, 16))
    normed = TwinQ(O, A, (16, 16), feature_norm=True)
    normed.load_state_dict(plain.state_dict())  # the option adds no parameter
    obs, act = torch.randn(5, O) * 3, torch.rand(5, A)
    x = torch.cat([obs, act], -1)
    for net, q in zip((plain.q1_net, plain.q2_net), normed(obs, act)):
        h = torch.relu(net[2](torch.relu(net[0](x))))
        expected = (h / h.norm(dim=-1, keepdim=True)) @ net[4].weight[0] + net[4].bias[0]
        assert torch.allclose(q, expected, atol=1e-6)
    assert torch.equal(normed.q1_only(obs, act), normed(obs, act)[0])
    # scaling the last hidden layer's weights and biases leaves a normalized critic unchanged, not a plain one
    for net in (plain.q1_net, normed.q1_net):
        with torch.no_grad():
            net[2].weight.mul_(4.0)
            net[2].bias.mul_(4.0)
    assert torch.allclose(normed.q1_only(obs, act), normed(obs, act)[0])
    q_before = TwinQ(O, A, (16, 16), feature_norm=True)
    q_before.load_state_dict(plain.state_dict())
    with torch.no_grad():
        q_before.q1_net[2].weight.div_(4.0)
        q_before.q1_net[2].bias.div_(4.0)
    assert torch.allclose(normed.q1_only(obs, act), q_before.q1_only(obs, act), atol=1e-5)
    torch.manual_seed(0)
    unscaled_plain = TwinQ(O, A, (16, 16))
    assert not torch.allclose(plain.q1_only(obs, act), unscaled_plain.q1_only(obs, act))
    # the central critic's branches: every value head sees unit-norm features
    critic = make_critic(feature_norm=True)
    base = make_critic()
    base.load_state_dict(critic.state_dict())
    x = make_inputs()
    seen = []
    hook = critic.q1_branch.head.register_forward_hook(lambda m, inp, out: seen.append(inp[0]))
    q1 = critic.q1(**x)
    hook.remove()
    assert torch.allclose(seen[0].norm(dim=-1), torch.ones(B), atol=1e-5)
    assert torch.allclose(q1, seen[0] @ critic.q1_branch.head.weight[0] + critic.q1_branch.head.bias[0], atol=1e-6)
    assert not torch.allclose(q1, base.q1(**x))
    with pytest.raises(ValueError, match="feature_norm"):
        make_critic(feature_norm=1)


# ---------------------------------------------------------------- GAT attention
def expected_adjacency(x, radius=None, scale=1.0):
    """Independent adjacency: valid receivers see valid nodes (within the radius); nothing else."""
    valid = torch.cat([torch.ones(B, 1, dtype=torch.bool), x["others_mask"]], 1)
    pos = torch.cat([x["state"][:, None, :2], x["others_state"][..., :2]], 1) * scale
    m = N + 1
    adj = torch.zeros(B, m, m, dtype=torch.bool)
    for b, i, j in itertools.product(range(B), range(m), range(m)):
        if valid[b, i] and valid[b, j]:
            adj[b, i, j] = radius is None or math.dist(pos[b, i].tolist(), pos[b, j].tolist()) <= radius
    return valid, adj


@pytest.mark.parametrize("radius,heads", [(None, 2), (1.5, 2), (1.5, 1), (1.5, 3)])
def test_gat_attention_rows_sum_to_one_over_valid_neighbours(radius, heads):
    critic = make_critic(graph_radius=radius, position_scale=1.0, gat_heads=heads)
    x = make_inputs()
    x["others_state"][..., :2] *= 1.5  # spread the agents so that some pairs are beyond the radius
    critic.q_values(**x)
    valid, adj = expected_adjacency(x, radius)
    if radius is not None:
        assert (~adj[valid[:, :, None] & valid[:, None, :]]).any()  # the radius really cuts edges
    for branch in (critic.q1_branch, critic.q2_branch):
        a1, a2 = branch.graph.last_attention
        assert a1.shape == (B, heads, N + 1, N + 1) and a2.shape == (B, 1, 1, N + 1)  # (batch, head, receiver i, neighbour j)
        for alpha, rows in [(a1[:, k], slice(None)) for k in range(heads)] + [(a2[:, 0], slice(0, 1))]:
            r_valid, r_adj = valid[:, rows], adj[:, rows]
            sums = alpha.sum(-1)
            assert torch.allclose(sums[r_valid], torch.ones(()), atol=1e-6)
            assert (alpha[~r_adj] == 0).all()  # padded / out-of-radius neighbours, padded receivers: exactly 0
            assert (alpha[r_adj] > 0).all()
            assert (sums[~r_valid] == 0).all()


# ---------------------------------------------------------------- invariances
@pytest.mark.parametrize(
    "local_module,gat", [(m, {}) for m in LOCAL_MODULES] + [("cvae", dict(gat_heads=1, gat_init="default")), ("cvae", dict(gat_heads=3))]
)
def test_padded_slot_contents_change_nothing(local_module, gat):
    critic = make_critic(local_module=local_module, graph_radius=2.0, **gat)
    x = make_inputs()
    y = target_for(per_pair=True)
    ref = run_all(critic, x, y)
    x2 = {k: v.clone() for k, v in x.items()}
    y2 = y.clone()
    pad = ~x["others_mask"]
    x2["others_state"][pad] = torch.randn(int(pad.sum()), S) * 1e3
    x2["others_state"][2, 0, 0] = float("nan")
    x2["others_action"][pad] = float("inf")
    y2[:, 1:][pad] = float("nan")
    out = run_all(critic, x2, y2)
    for name in ("q1", "q2", "v", "recon_mse", "kl"):
        assert torch.equal(getattr(ref, name), getattr(out, name)), name
    # gradients stay finite although the padded contents are not
    loss = sum(t.sum() for t in out)
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in critic.parameters() if p.grad is not None)


@pytest.mark.parametrize("local_module,global_module", [("cvae", g) for g in GLOBAL_MODULES] + [("attention", "gat"), ("none", "gat")])
def test_permuting_other_agents_leaves_q_and_v_unchanged(local_module, global_module):
    critic = make_critic(local_module=local_module, global_module=global_module, graph_radius=2.5)
    x = make_inputs()
    perm = torch.tensor([2, 0, 3, 1])
    xp = dict(x)
    for k in ("others_state", "others_action", "others_mask"):
        xp[k] = x[k][:, perm]
    q1, q2 = critic.q_values(**x)
    q1p, q2p = critic.q_values(**xp)
    v = critic.baseline(x["obs"], x["state"], x["others_state"], x["others_action"], x["others_mask"])
    vp = critic.baseline(xp["obs"], xp["state"], xp["others_state"], xp["others_action"], xp["others_mask"])
    for a, b in ((q1, q1p), (q2, q2p), (v, vp)):
        assert torch.allclose(a, b, atol=1e-5, rtol=0)


def test_all_valid_fast_path_equals_packed_path():
    critic = make_critic()
    full = torch.ones(B, N, dtype=torch.bool)
    x = make_inputs(mask=full)
    xe = dict(x)  # same agents plus one padded slot: goes through the packing path
    xe["others_state"] = torch.cat([x["others_state"], torch.randn(B, 1, S)], 1)
    xe["others_action"] = torch.cat([x["others_action"], torch.randn(B, 1, A)], 1)
    xe["others_mask"] = torch.cat([full, torch.zeros(B, 1, dtype=torch.bool)], 1)
    a, b = run_all(critic, x, target_for()), run_all(critic, xe, target_for())
    for name in ("q1", "q2", "v", "recon_mse", "kl"):
        assert torch.allclose(getattr(a, name), getattr(b, name), atol=1e-6, rtol=1e-6), name


# ---------------------------------------------------------------- radius graph
@pytest.mark.parametrize("global_module", GLOBAL_MODULES)
def test_radius_graph_masks_far_agents(global_module):
    scale = 100.0  # metres per state unit
    critic = make_critic(global_module=global_module, graph_radius=40.0, position_scale=scale)
    x = make_inputs(mask=torch.ones(B, N, dtype=torch.bool))
    x["state"][:, :2] = 0.0
    x["others_state"][:, 0, :2] = torch.tensor([0.10, 0.00])  # 10 m
    x["others_state"][:, 1, :2] = torch.tensor([0.20, 0.15])  # 25 m
    x["others_state"][:, 2, :2] = torch.tensor([-0.1, 0.30])  # 32 m
    x["others_state"][:, 3, :2] = torch.tensor([5.00, 5.00])  # ~700 m from everyone
    ref_q, ref_v = critic.q_values(**x), critic.baseline(x["obs"], x["state"], x["others_state"], x["others_action"], x["others_mask"])

    far = {k: v.clone() for k, v in x.items()}
    far["others_state"][:, 3] = torch.randn(B, S)
    far["others_state"][:, 3, :2] = torch.tensor([-4.0, 6.0])  # still far away
    far["others_action"][:, 3] = -far["others_action"][:, 3]
    q, v = critic.q_values(**far), critic.baseline(far["obs"], far["state"], far["others_state"], far["others_action"], far["others_mask"])
    assert torch.equal(q[0], ref_q[0]) and torch.equal(q[1], ref_q[1]) and torch.equal(v, ref_v)

    near = {k: v.clone() for k, v in x.items()}
    near["others_state"][:, 3, :2] = torch.tensor([0.0, -0.35])  # 35 m: inside the radius
    q, v = (
        critic.q_values(**near),
        critic.baseline(near["obs"], near["state"], near["others_state"], near["others_action"], near["others_mask"]),
    )
    assert (q[0] != ref_q[0]).all() and (q[1] != ref_q[1]).all() and (v != ref_v).all()

    full_graph = make_critic(global_module=global_module, graph_radius=None)
    q_full = full_graph.q_values(**x)[0]
    assert (full_graph.q_values(**far)[0] != q_full).all()  # without the radius the far agent matters


# ---------------------------------------------------------------- counterfactual baseline
@pytest.mark.parametrize("local_module", LOCAL_MODULES)
def test_baseline_does_not_depend_on_ego_action_but_q_does(local_module):
    critic = make_critic(local_module=local_module)
    x = make_inputs()
    x["action"].requires_grad_(True)
    out = run_all(critic, x, target_for())
    (gv,) = torch.autograd.grad(out.v.sum(), x["action"], allow_unused=True, retain_graph=True)
    assert gv is None or (gv == 0).all()
    for q in (out.q1, out.q2):
        (gq,) = torch.autograd.grad(q.sum(), x["action"], retain_graph=True)
        assert (gq.abs().sum(-1) > 0).all()
    v_method = critic.baseline(x["obs"], x["state"], x["others_state"], x["others_action"], x["others_mask"])
    assert torch.allclose(v_method, out.v, atol=1e-6)
    x2 = dict(x, action=torch.rand(B, A) * 2 - 1)
    assert torch.equal(run_all(critic, x2).v, out.v)


def test_forward_equals_separate_methods():
    critic = make_critic()
    x, y = make_inputs(), target_for()
    out = run_all(critic, x, y, seed=3)
    q1, q2 = critic.q_values(**x)
    recon, kl = critic.cvae_loss(**x, target_y=y, generator=torch.Generator().manual_seed(3))
    assert torch.allclose(out.q1, q1, atol=1e-6) and torch.allclose(out.q2, q2, atol=1e-6)
    assert torch.allclose(out.q1, critic.q1(**x), atol=1e-6)
    assert torch.allclose(out.recon_mse, recon) and torch.allclose(out.kl, kl)


def test_detach_latent_stops_q_gradients_into_the_encoder():
    x = make_inputs()
    for detach in (False, True):
        critic = make_critic(detach_latent=detach)
        critic.q_values(**x)[0].sum().backward()
        enc_grad = critic.local.enc_in.linear.weight.grad
        assert (enc_grad is None) == detach
    x["action"].requires_grad_(True)
    critic.q1(**x).sum().backward()  # the ego action still gets a gradient through its node and the obs branch
    assert (x["action"].grad.abs() > 0).any()


# ---------------------------------------------------------------- module switches
@pytest.mark.parametrize("local_module,global_module", list(itertools.product(LOCAL_MODULES, GLOBAL_MODULES)))
def test_every_module_switch_builds_runs_and_backpropagates(local_module, global_module):
    critic = make_critic(local_module=local_module, global_module=global_module, graph_radius=3.0)
    out = run_all(critic, make_inputs(), target_for())
    for t in (out.q1, out.q2, out.v):
        assert t.shape == (B,) and torch.isfinite(t).all()
    if local_module == "cvae":
        assert out.recon_mse > 0 and out.kl >= 0
    else:
        assert out.recon_mse == 0 and out.kl == 0
        assert critic.cvae_loss(**make_inputs(), target_y=target_for()) == (0, 0)
    sum(t.sum() for t in out).backward()
    assert critic.q1_branch.head.weight.grad is not None and critic.v_branch.head.weight.grad is not None


def shapes(module, prefixes):
    return {k: tuple(v.shape) for k, v in module.state_dict().items() if k.startswith(prefixes)}


def test_switching_a_module_keeps_unrelated_parameter_shapes():
    base = make_critic()
    branch_parts = tuple(f"{b}_branch.{p}" for b in ("q1", "q2") for p in ("obs_mlp", "head", "graph"))
    for local_module in ("attention", "none"):
        other = make_critic(local_module=local_module)
        assert shapes(other, branch_parts) == shapes(base, branch_parts)
        assert shapes(other, ("v_branch",)) == shapes(base, ("v_branch",))
        same_width = local_module == "attention"  # L-dim pair feature as the CVAE's; "none" drops the slot
        assert (shapes(other, ("q1_branch.node_mlp",)) == shapes(base, ("q1_branch.node_mlp",))) == same_width
    not_graph = ("local", "q1_branch.node_mlp", "q1_branch.obs_mlp", "q1_branch.head", "v_branch.node_mlp", "v_branch.obs_mlp")
    for global_module in ("gcn", "graphsage", "none"):
        other = make_critic(global_module=global_module)
        assert shapes(other, not_graph) == shapes(base, not_graph)
        assert shapes(other, ("q1_branch.graph",)) != shapes(base, ("q1_branch.graph",))
    other = make_critic(graph_radius=40.0, position_scale=150.0, detach_latent=True, gat_init="default")
    assert shapes(other, ("",)) == shapes(base, ("",))
    other = make_critic(gat_heads=3)  # only the GAT's shapes change
    graphs = tuple(f"{b}_branch.graph" for b in ("q1", "q2", "v"))
    assert {k: v for k, v in shapes(other, ("",)).items() if not k.startswith(graphs)} == {
        k: v for k, v in shapes(base, ("",)).items() if not k.startswith(graphs)
    }
    assert shapes(other, graphs) != shapes(base, graphs)


# ---------------------------------------------------------------- graph modules against dense references
def dense_reference(module, h, adj, valid):
    """Eqs. 4-6 (and the GCN / GraphSAGE / pool variants) written out with full matrices."""
    m = h.shape[1]
    if module.kind == "none":
        w = adj[:, 0].float()
        return F.relu(module.pool((w[:, :, None] * h).sum(1) / w.sum(1, keepdim=True)))
    for layer in module.layers:
        if module.kind == "gat":  # every head on every node (no ego-only shortcut), heads concatenated
            heads = []
            for k in range(layer.a_recv.shape[0]):
                w_k = layer.W.weight[k * layer.out_dim : (k + 1) * layer.out_dim]  # head k's W_k (F, F_in)
                wh = h @ w_k.T
                pair = torch.cat([wh[:, :, None, :].expand(-1, m, m, -1), wh[:, None, :, :].expand(-1, m, m, -1)], -1)  # [Wh_i || Wh_j]
                e = F.leaky_relu(pair @ torch.cat([layer.a_recv[k], layer.a_nbr[k]]), 0.2)
                alpha = torch.softmax(e.masked_fill(~adj, float("-inf")), -1)
                heads.append(F.relu(alpha @ wh))
            h = torch.cat(heads, -1)
        else:
            nb = adj & ~torch.eye(m, dtype=torch.bool) if module.kind == "graphsage" else adj
            mean = (nb.float() @ h) / nb.float().sum(-1, keepdim=True).clamp_min(1)
            h = F.relu(layer.lin(torch.cat([h, mean], -1) if module.kind == "graphsage" else mean))
        h = h * valid[..., None]
    return h[:, 0]


@pytest.mark.parametrize("kind,heads", [(k, 2) for k in GLOBAL_MODULES] + [("gat", 1), ("gat", 3)])
def test_graph_modules_equal_dense_reference(kind, heads):
    torch.manual_seed(0)
    module = GraphModule(kind, 8, 0.2, heads=heads)
    x = make_inputs()
    graph = build_graph(x["state"], x["action"], x["others_state"], x["others_action"], x["others_mask"], radius=2.0)
    h = torch.randn(B, N + 1, 8) * graph.valid[..., None]
    out = module(graph.packer.pack(h), graph)
    assert torch.allclose(out, dense_reference(module, h, graph.adj, graph.valid), atol=1e-5)


# ---------------------------------------------------------------- GAT heads and initialization
def small_graph(radius=2.0):
    x = make_inputs()
    return build_graph(x["state"], x["action"], x["others_state"], x["others_action"], x["others_mask"], radius=radius)


def brute_force_gat_head(h, adj, valid, w, a_recv, a_nbr, slope=0.2):
    """One GAT head by scalar loops in float64 (Eqs. 4-6): alpha_ij over the neighbours j of i, out_i = ReLU(sum_j alpha_ij W h_j)."""
    nb, m, _ = h.shape
    h, w, a_recv, a_nbr = (t.detach().double() for t in (h, w, a_recv, a_nbr))
    out, alpha = torch.zeros(nb, m, w.shape[0], dtype=torch.float64), torch.zeros(nb, m, m, dtype=torch.float64)
    for b in range(nb):
        wh = [w @ h[b, j] for j in range(m)]
        for i in range(m):
            if not valid[b, i]:
                continue  # padded receiver: zero row, zero attention
            nbrs = [j for j in range(m) if adj[b, i, j]]
            ex = [math.exp(float(F.leaky_relu(a_recv @ wh[i] + a_nbr @ wh[j], slope))) for j in nbrs]
            for j, v in zip(nbrs, ex):
                alpha[b, i, j] = v / sum(ex)
            out[b, i] = torch.relu(sum(alpha[b, i, j] * wh[j] for j in nbrs))
    return out, alpha


@pytest.mark.parametrize("init", GAT_INITS)
def test_gat_first_layer_concatenates_its_heads(init):
    torch.manual_seed(0)
    width, heads = 8, 2
    layer = GATLayer(width, width, 0.2, heads=heads, init=init)
    graph = small_graph()
    h = torch.randn(B, N + 1, width) * graph.valid[..., None]
    out, alpha = layer(graph.packer.pack(h), graph)
    assert out.shape == (B, N + 1, heads * width) and alpha.shape == (B, heads, N + 1, N + 1)
    for k in range(heads):
        w_k = layer.W.weight[k * width : (k + 1) * width]
        half = out[..., k * width : (k + 1) * width]
        ref, ref_alpha = brute_force_gat_head(h, graph.adj, graph.valid, w_k, layer.a_recv[k], layer.a_nbr[k])
        assert torch.allclose(half.double(), ref, atol=1e-5) and torch.allclose(alpha[:, k].double(), ref_alpha, atol=1e-6)
        single = GATLayer(width, width, 0.2, heads=1)  # a one-head layer holding head k's weights gives the same half
        with torch.no_grad():
            single.W.weight.copy_(w_k)
            single.a_recv.copy_(layer.a_recv[k : k + 1])
            single.a_nbr.copy_(layer.a_nbr[k : k + 1])
        s_out, s_alpha = single(graph.packer.pack(h), graph)
        assert torch.allclose(half, s_out, atol=1e-6) and torch.allclose(alpha[:, k], s_alpha[:, 0], atol=1e-7)
    assert not torch.allclose(out[..., :width], out[..., width:])  # the heads have their own weights
    ego, ego_alpha = layer.forward_ego(h, graph)  # the ego-only path equals row 0 of the full layer
    assert ego.shape == (B, heads * width) and ego_alpha.shape == (B, heads, 1, N + 1)
    assert torch.allclose(ego, out[:, 0], atol=1e-6) and torch.allclose(ego_alpha[:, :, 0], alpha[:, :, 0], atol=1e-7)


class SingleHeadGATBefore27(torch.nn.Module):
    """The single-head GAT layer as it was before issue #27 (nn.Linear default W, Glorot a, gain 1.414): the regression reference."""

    def __init__(self, in_dim, out_dim):
        super().__init__()
        self.W = torch.nn.Linear(in_dim, out_dim, bias=False)
        bound = 1.414 * math.sqrt(6.0 / (2 * out_dim + 1))
        self.a_recv = torch.nn.Parameter(torch.empty(out_dim).uniform_(-bound, bound))
        self.a_nbr = torch.nn.Parameter(torch.empty(out_dim).uniform_(-bound, bound))

    def alpha(self, s_recv, s_nbr, adj):
        e = F.leaky_relu(s_recv.unsqueeze(-1) + s_nbr.unsqueeze(1), 0.2)
        return torch.softmax(e.masked_fill(~adj, float("-inf")), dim=-1)

    def forward(self, h, graph):
        u = torch.stack([self.a_recv @ self.W.weight, self.a_nbr @ self.W.weight])
        wh, s = graph.packer.unpack(self.W(h)), graph.packer.unpack(F.linear(h, u))
        alpha = self.alpha(s[..., 0], s[..., 1], graph.adj).masked_fill(~graph.valid.unsqueeze(-1), 0.0)
        return F.relu(alpha @ wh), alpha

    def forward_ego(self, h, graph):
        alpha = self.alpha(h[:, :1] @ (self.a_recv @ self.W.weight), h @ (self.a_nbr @ self.W.weight), graph.adj[:, :1])
        return F.relu(self.W((alpha @ h).squeeze(1))), alpha


def test_one_head_default_init_reproduces_the_layer_before_issue_27():
    """The same initial weights bit for bit; outputs and gradients up to the padded softmax's float rounding (masked_softmax)."""
    width = 128
    torch.manual_seed(4)
    old = [SingleHeadGATBefore27(width, width), SingleHeadGATBefore27(width, width)]
    torch.manual_seed(4)
    module = GraphModule("gat", width, 0.2, heads=1, init="default")
    for o, n in zip(old, module.layers):
        assert torch.equal(n.W.weight, o.W.weight) and torch.equal(n.a_recv, o.a_recv[None]) and torch.equal(n.a_nbr, o.a_nbr[None])
    graph = small_graph()
    h = torch.randn(B, N + 1, width) * graph.valid[..., None]
    h1, a1 = old[0](graph.packer.pack(h), graph)
    ref, a2 = old[1].forward_ego(h1, graph)
    out = module(graph.packer.pack(h), graph)
    close = {"atol": 1e-6, "rtol": 1e-5}
    torch.testing.assert_close(out, ref, **close)
    torch.testing.assert_close(module.last_attention[0], a1[:, None], **close)
    torch.testing.assert_close(module.last_attention[1], a2[:, None], **close)
    out.square().sum().backward()
    ref.square().sum().backward()
    for o, n in zip(old, module.layers):
        torch.testing.assert_close(n.W.weight.grad, o.W.weight.grad, **close)
        torch.testing.assert_close(n.a_recv.grad, o.a_recv.grad[None], **close)
        torch.testing.assert_close(n.a_nbr.grad, o.a_nbr.grad[None], **close)


def test_gat_xavier_init_has_pygat_bound_and_std():
    torch.manual_seed(0)
    f_in, f, heads, gain = 512, 256, 2, 1.414
    layer = GATLayer(f_in, f, heads=heads, init="xavier")
    for w_k in layer.W.weight.detach().split(f):  # per head W_k: fan_in + fan_out = F_in + F (not the stacked heads * F)
        bound = gain * math.sqrt(6 / (f_in + f))  # uniform(-bound, bound) has std bound / sqrt(3) = gain * sqrt(2 / (F_in + F))
        assert bound * 0.999 < w_k.abs().max() <= bound
        assert abs(w_k.std().item() / (gain * math.sqrt(2 / (f_in + f))) - 1) < 0.01
        assert abs(w_k.mean().item()) < 0.01 * bound
    a = torch.cat([layer.a_recv, layer.a_nbr], 1).detach()  # head k's (2F, 1) vector a_k: fans 2F and 1
    bound = gain * math.sqrt(6 / (2 * f + 1))
    assert a.abs().max() <= bound and abs(a.std().item() / (bound / math.sqrt(3)) - 1) < 0.1
    # at the critic's width (F_in = F = 128) Xavier with gain 1.414 is sqrt(3) * 1.414 = 2.45 times nn.Linear's default std
    w_x = GATLayer(128, 128, heads=8, init="xavier").W.weight.detach()
    w_d = GATLayer(128, 128, heads=8, init="default").W.weight.detach()
    assert w_d.abs().max() <= 1 / math.sqrt(128)  # kaiming_uniform(a=sqrt(5)) bound 1 / sqrt(fan_in)
    assert abs(w_x.std().item() / w_d.std().item() / (1.414 * math.sqrt(3)) - 1) < 0.03


def n_params(module):
    return sum(p.numel() for p in module.parameters())


def test_gat_module_structure_and_parameter_counts():
    f = 128
    module = GraphModule("gat", f)  # defaults: 2 heads, Xavier
    l1, l2 = module.layers
    assert (l1.heads, l2.heads) == (2, 1)
    assert l1.W.weight.shape == (2 * f, f) and l2.W.weight.shape == (f, 2 * f)
    assert l1.a_recv.shape == l1.a_nbr.shape == (2, f) and l2.a_recv.shape == l2.a_nbr.shape == (1, f)
    assert n_params(module) == 2 * (f * f + 2 * f) + (2 * f * f + 2 * f) == 66304  # layer 1: 2 x (W_k, a_k); layer 2: W (F, 2F), a
    assert n_params(GraphModule("gat", f, heads=1, init="default")) == 2 * (f * f + 2 * f) == 33280
    # the critic passes gat_heads / gat_init to its three graph modules (Q1, Q2, V): +3 x (66304 - 33280) parameters
    before = CentralCritic(CentralCriticConfig(obs_dim=91, gat_heads=1, gat_init="default"))
    after = CentralCritic(CentralCriticConfig(obs_dim=91))
    assert n_params(after) - n_params(before) == 3 * (66304 - 33280)
    torch.manual_seed(0)
    critic = make_critic(gat_heads=3, gat_init="default")
    for branch in (critic.q1_branch, critic.q2_branch, critic.v_branch):
        assert branch.graph.layers[0].heads == 3 and branch.graph.layers[1].W.weight.shape == (8, 24)
        assert branch.graph.layers[0].W.weight.abs().max() <= 1 / math.sqrt(8)  # nn.Linear default bound
    xav = make_critic().q1_branch.graph.layers[0].W.weight
    assert xav.abs().max() > 1 / math.sqrt(8)  # Xavier's bound 1.414 * sqrt(6 / 16) = 0.87 is wider


@pytest.mark.parametrize("kw", [dict(heads=0), dict(heads=2.0), dict(heads=True), dict(init="kaiming")])
def test_bad_gat_arguments_raise(kw):
    for kind in GLOBAL_MODULES:
        with pytest.raises(ValueError, match="gat_heads|gat_init"):
            GraphModule(kind, 8, **kw)
    with pytest.raises(ValueError, match="gat_heads|gat_init"):
        GATLayer(8, 8, **kw)


# ---------------------------------------------------------------- CVAE loss
def test_cvae_loss_ignores_padded_pairs():
    critic = make_critic()
    x, y = make_inputs(), target_for(per_pair=True)
    ref = critic.cvae_loss(**x, target_y=y, generator=torch.Generator().manual_seed(5))
    x2, y2 = {k: v.clone() for k, v in x.items()}, y.clone()
    pad = ~x["others_mask"]
    x2["others_state"][pad] = 123.0
    x2["others_action"][pad] = -7.0
    y2[:, 1:][pad] = 1e6
    out = critic.cvae_loss(**x2, target_y=y2, generator=torch.Generator().manual_seed(5))
    assert torch.equal(ref[0], out[0]) and torch.equal(ref[1], out[1])
    y3 = y.clone()
    y3[1, 2] += 1.0  # a valid pair's target does matter
    assert critic.cvae_loss(**x, target_y=y3, generator=torch.Generator().manual_seed(5))[0] != ref[0]


def linear(layer, v):
    return v @ layer.weight.T + layer.bias


def test_cvae_loss_equals_hand_written_reference():
    critic = make_critic()
    cvae = critic.local
    x, y = make_inputs(), target_for()
    recon, kl = critic.cvae_loss(**x, target_y=y, generator=torch.Generator().manual_seed(11))

    valid_pairs = [(b, j) for b in range(B) for j in range(N + 1) if j == 0 or x["others_mask"][b, j - 1]]
    eps = torch.randn(len(valid_pairs), L, generator=torch.Generator().manual_seed(11))  # row-major (b, j) order
    sq_err, kl_terms = [], []
    with torch.no_grad():
        for k, (b, j) in enumerate(valid_pairs):
            s_j = x["state"][b] if j == 0 else x["others_state"][b, j - 1]
            a_j = x["action"][b] if j == 0 else x["others_action"][b, j - 1]
            cond = torch.cat([x["obs"][b], x["state"][b], x["action"][b]])
            h = torch.relu(linear(cvae.enc_in.linear, torch.cat([cond, s_j, a_j])))
            h = torch.relu(linear(cvae.enc_body[0], h))
            h = torch.relu(linear(cvae.enc_body[2], h))
            mu, logvar = linear(cvae.mu_head, h), linear(cvae.logvar_head, h)
            z = mu + eps[k] * torch.exp(0.5 * logvar)
            d = torch.relu(linear(cvae.dec_in.linear, torch.cat([cond, z, s_j, a_j])))
            d = torch.relu(linear(cvae.dec_body[0], d))
            y_hat = linear(cvae.dec_body[2], d)
            assert y_hat.shape == (O + S + 1,)
            sq_err.append((y_hat - y[b]) ** 2)
            kl_terms.append(1 + logvar - mu**2 - torch.exp(logvar))
    recon_ref = torch.stack(sq_err).mean()  # MSE over valid pairs and output dims
    kl_ref = -0.5 * torch.stack(kl_terms).mean()  # over valid pairs and latent dims
    assert len(valid_pairs) == 4 + 5 + 1
    assert torch.allclose(recon, recon_ref, atol=1e-6, rtol=1e-5)
    assert torch.allclose(kl, kl_ref, atol=1e-6, rtol=1e-5)  # unweighted: kl_beta is the caller's


# ---------------------------------------------------------------- config validation
@pytest.mark.parametrize(
    "field,value",
    [
        ("local_module", "vae"),
        ("global_module", "gin"),
        ("graph_radius", -40.0),
        ("graph_radius", float("nan")),
        ("position_scale", 0.0),
        ("leaky_slope", 1.5),
        ("obs_dim", 0),
        ("latent_dim", 2.5),
        ("hidden", True),
        ("detach_latent", "yes"),
        ("cvae_encoder_layers", 0),
        ("gat_heads", 0),
        ("gat_heads", 2.0),
        ("gat_heads", True),
        ("gat_init", "kaiming"),
    ],
)
def test_bad_config_values_raise_naming_the_value(field, value):
    with pytest.raises(ValueError) as err:
        CentralCriticConfig(**{**SMALL, field: value})
    assert field in str(err.value) and repr(value) in str(err.value)


def test_radius_needs_two_position_entries():
    with pytest.raises(ValueError, match="state_dim=1"):
        CentralCriticConfig(obs_dim=4, state_dim=1, graph_radius=40.0)
    CentralCriticConfig(obs_dim=4, state_dim=1)  # fine without a radius


# ---------------------------------------------------------------- gradients and edge cases
@pytest.mark.parametrize("local_module,global_module", [("cvae", g) for g in GLOBAL_MODULES] + [("attention", "gat")])
def test_gradcheck_in_double_precision(local_module, global_module):
    critic = make_critic(local_module=local_module, global_module=global_module, graph_radius=2.0).double()
    x = {k: (v.double() if v.is_floating_point() else v) for k, v in make_inputs().items()}
    a = x["action"].clone().requires_grad_(True)
    os_ = x["others_state"].clone().requires_grad_(True)
    oa = x["others_action"].clone().requires_grad_(True)
    m = x["others_mask"]
    assert torch.autograd.gradcheck(lambda a, s, u: critic.q_values(x["obs"], x["state"], a, s, u, m), (a, os_, oa))
    assert torch.autograd.gradcheck(lambda s, u: critic.baseline(x["obs"], x["state"], s, u, m), (os_, oa))


def test_no_other_agents_at_all():
    critic = make_critic()
    x = make_inputs()
    x.update(others_state=torch.zeros(B, 0, S), others_action=torch.zeros(B, 0, A), others_mask=torch.zeros(B, 0, dtype=torch.bool))
    out = run_all(critic, x, target_for())
    assert out.q1.shape == out.v.shape == (B,) and torch.isfinite(out.recon_mse)
    a1, a2 = critic.q1_branch.graph.last_attention
    assert torch.equal(a1, torch.ones(B, 2, 1, 1)) and torch.equal(a2, torch.ones(B, 1, 1, 1))


def test_a_single_head_layer_loads_the_attention_vectors_of_the_previous_layout():
    layer = GATLayer(8, 8, heads=1, init="default")
    old = {k: v.clone() for k, v in layer.state_dict().items()}
    old["a_recv"], old["a_nbr"] = old["a_recv"][0] * 2.0, old["a_nbr"][0] * 3.0  # (F,) as saved before the multi-head layer
    layer.load_state_dict(old)
    assert torch.equal(layer.a_recv[0], old["a_recv"]) and torch.equal(layer.a_nbr[0], old["a_nbr"])
