"""Networks of CIG-TD3 (COIN, paper section 4): actor, local twin critic, interaction-aware centralized critic.

Plain ``torch.nn``; nothing here imports Ray. Shapes: ``B`` batch rows (one ego agent at one env
step each), ``N`` padded slots for the other agents, ``M = N + 1`` graph nodes (node 0 = the ego),
``O`` observation, ``S`` local state (10), ``A`` action (2), ``L`` latent (20).

Centralized critic (paper Fig. 2, Eqs. 1-6, App. B), with the choices made where the paper is silent:

* **Local module "cvae"** (Eqs. 1-3). For every pair (i, j), j = i included (the ego node uses its
  own s_i, a_i as s_j, a_j), the encoder q(z_ij | o_i, s_i, s_j, a_i, a_j) gives (mu_ij, logvar_ij)
  and the decoder p(y | z_ij, o_i, s_i, s_j, a_i, a_j) reconstructs y = [o'_i, s'_i, r_i] (the
  official code drops o_i from the decoder and s'_i from y; we follow the paper). Encoder: 3 hidden
  layers of 256 (ReLU) then linear mu / logvar heads; decoder: 2 hidden layers of 256 (ReLU) then a
  linear output (as the official code). The first layer of both acts on the concatenation
  ``[o_i, s_i, a_i | s_j, a_j]`` (decoder: ``[o_i, s_i, a_i | z_ij, s_j, a_j]``); it is one
  ``nn.Linear`` whose ego columns are applied once per row and broadcast over the pairs
  (:class:`PairLinear`, mathematically the plain layer on the concatenation).
* **Latent fed to Q.** The Q branches use the posterior mean mu_ij (not a sample), so Q is
  deterministic (TD targets and actor gradients carry no CVAE sampling noise); z is sampled (with
  the reparameterization trick) only inside the ELBO. By default (``detach_latent=False``) mu_ij
  stays in the autograd graph: the Q loss also trains the encoder (jointly with the ELBO, Alg. 1
  "jointly optimizing the CVAE") and dQ/da_i includes the path through the latents.
  ``detach_latent=True`` reproduces the official code (encoder trained by the ELBO only).
* **Node inputs.** Q: ``x_j = [s_j, a_j, mu_ij]`` for every node j (node 0: ``[s_i, a_i, mu_ii]``).
  The paper writes ``[s_i, a_i, z_ij]``; with s_i, a_i on every node the nodes would differ only by
  their latent, so we use node j's own state and action, as the official code does and as a GAT
  over agents implies. V (counterfactual baseline): ``x_j = [s_j, a_j]`` for the others and
  ``x_0 = [s_i, 0]`` for the ego (zeros in the action slot; the official code writes -1 there), no
  latents, observation branch on o_i only, so V does not depend on a_i at all.
* **Local module "attention"** (Table B.1 ablation): a deterministic pairwise fusion
  ``f_ij = sigmoid(q(o_i, s_i, a_i) . k(s_j, a_j) / sqrt(L)) * v(s_j, a_j)`` (L-dim). The gate is
  a sigmoid rather than a softmax over j so the feature stays pairwise (like z_ij) and does not
  shrink with the number of agents; the cross-agent normalisation is the graph module's job.
  **"none"**: ``x_j = [s_j, a_j]``.
* **Node MLP**: Linear(., 128) -> LeakyReLU -> Linear(128, 128) -> LeakyReLU (paper; the official
  code uses ReLU). The slope is ``leaky_slope`` (also the GAT score slope).
* **Graph.** Node 0 + valid others, self-loops included; with ``graph_radius`` only nodes within
  that distance (metres, from the first two state entries times ``position_scale``, ``<=``) of the
  receiving node. Padded slots are zeroed on input, never enter a per-pair / per-node MLP (the
  valid (b, j) slots are packed into P rows, :class:`PairPacker`), receive only from themselves
  and have zero output rows, so their contents cannot change any output (bit-identical) and they
  cost no MLP work.
* **Global module "gat"**: 2 single-head GAT layers (Eqs. 4-6): ``e_ij = LeakyReLU(a1.Wh_i + a2.Wh_j)``
  by broadcasting, masked softmax over j, ``h'_i = ReLU(sum_j alpha_ij W h_j)``. **"gcn"**:
  ``ReLU(W mean_{j in N(i)} h_j)``; **"graphsage"**: ``ReLU(W [h_i || mean_{j in N(i), j != i} h_j])``
  (zero mean when i has no other neighbour); **"none"**: ReLU(Linear(mean of h_j over the ego's
  neighbourhood)). Only the ego's final feature is read out, so the second layer is computed for
  the ego row only, as ``W (sum_j alpha_0j h_j)`` (exactly what a full second layer gives at node
  0, without W on every node). The scores use ``a . (W h) = (a^T W) h``.
* **Readout**: ``Linear([h_ego, MLP_obs(.)])`` -> scalar, one layer (paper Fig. 2; the official code
  uses two). MLP_obs: 2 layers of ``hidden`` with ReLU on ``[o_i, a_i]`` (Q) or ``o_i`` (V).
* **Twin Q**: Q1 and Q2 have their own node MLP, graph module, observation branch and head and share
  the local module; V has its own as well.

Cost: with every slot valid, one forward + backward of twin Q + V + ELBO is about 1.1 M
multiply-adds per node (about 2/3 in the CVAE's three 256x256 layers), i.e. about 28 GFLOP for
B=256, N=47; use :meth:`CentralCritic.forward` to run the encoder once for all terms.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

LOCAL_MODULES = ("cvae", "attention", "none")
GLOBAL_MODULES = ("gat", "gcn", "graphsage", "none")

__all__ = [
    "GLOBAL_MODULES",
    "LOCAL_MODULES",
    "Actor",
    "CentralCritic",
    "CentralCriticConfig",
    "CriticBranch",
    "CriticOutputs",
    "GATLayer",
    "Graph",
    "GraphModule",
    "MeanAggLayer",
    "PairAttention",
    "PairCVAE",
    "PairLinear",
    "PairPacker",
    "TwinQ",
    "build_graph",
    "mlp",
    "radius_adjacency",
]


def mlp(sizes: Sequence[int], activation: Callable[[], nn.Module], out_activation: Callable[[], nn.Module] | None = None) -> nn.Sequential:
    """Linear layers ``sizes[0] -> ... -> sizes[-1]`` with ``activation()`` between them and ``out_activation()`` last."""
    if len(sizes) < 2:
        raise ValueError(f"mlp needs at least an input and an output size, got sizes={list(sizes)}")
    layers: list[nn.Module] = []
    for k in range(len(sizes) - 1):
        layers.append(nn.Linear(sizes[k], sizes[k + 1]))
        if k < len(sizes) - 2:
            layers.append(activation())
        elif out_activation is not None:
            layers.append(out_activation())
    return nn.Sequential(*layers)


class Actor(nn.Module):
    """Deterministic policy mu_theta(o): MLP with ReLU, tanh output in [-1, 1]."""

    def __init__(self, obs_dim: int, act_dim: int = 2, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp([obs_dim, *hidden, act_dim], nn.ReLU, nn.Tanh)

    def forward(self, obs: Tensor) -> Tensor:
        """Action (B, act_dim) in [-1, 1] for observations (B, obs_dim)."""
        return self.net(obs)


class TwinQ(nn.Module):
    """Local (individual) twin critic Q^l_1, Q^l_2 on [o, a] (paper Eqs. 7-8)."""

    def __init__(self, obs_dim: int, act_dim: int = 2, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.q1_net = mlp([obs_dim + act_dim, *hidden, 1], nn.ReLU)
        self.q2_net = mlp([obs_dim + act_dim, *hidden, 1], nn.ReLU)

    def forward(self, obs: Tensor, act: Tensor) -> tuple[Tensor, Tensor]:
        """(q1, q2), each of shape (B,)."""
        x = torch.cat([obs, act], -1)
        return self.q1_net(x).squeeze(-1), self.q2_net(x).squeeze(-1)

    def q1_only(self, obs: Tensor, act: Tensor) -> Tensor:
        """Q1 of shape (B,) (actor loss)."""
        return self.q1_net(torch.cat([obs, act], -1)).squeeze(-1)


def _is_int(x: object) -> bool:
    return isinstance(x, int) and not isinstance(x, bool)


def _is_real(x: object) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x)


@dataclass
class CentralCriticConfig:
    """Hyper-parameters of :class:`CentralCritic` (defaults: paper section 4.1 / 5.1, official code where the paper is silent).

    Fields: ``obs_dim`` O; ``state_dim`` S (10: x, y, vx, vy, cos h, sin h, two navigation
    vectors); ``act_dim`` A; ``latent_dim`` L of z_ij (20); ``hidden`` width of the CVAE and of the
    observation branches (256); ``node_width`` node-MLP / graph width (128); ``local_module``
    "cvae" | "attention" | "none"; ``global_module`` "gat" | "gcn" | "graphsage" | "none";
    ``graph_radius`` None = fully connected graph, else the radius in metres (App. B.2 uses 40);
    ``position_scale`` metres per unit of the first two state entries (the scenario's position
    normalisation); ``leaky_slope`` of the node-MLP LeakyReLU and the GAT scores; ``detach_latent``
    stop Q gradients into the CVAE encoder (official code) instead of training it jointly;
    ``cvae_encoder_layers`` / ``cvae_decoder_layers`` hidden layers of width ``hidden`` in the
    encoder (3) and decoder (2), as in the official code.
    """

    obs_dim: int
    state_dim: int = 10
    act_dim: int = 2
    latent_dim: int = 20
    hidden: int = 256
    node_width: int = 128
    local_module: str = "cvae"
    global_module: str = "gat"
    graph_radius: float | None = None
    position_scale: float = 1.0
    leaky_slope: float = 0.2
    detach_latent: bool = False
    cvae_encoder_layers: int = 3
    cvae_decoder_layers: int = 2

    def __post_init__(self) -> None:
        """Validate every field; raise ValueError naming the bad value and what is allowed."""
        for name in ("obs_dim", "state_dim", "act_dim", "latent_dim", "hidden", "node_width", "cvae_encoder_layers", "cvae_decoder_layers"):
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                raise ValueError(f"{name}={v!r} is invalid: must be a positive int")
        if self.local_module not in LOCAL_MODULES:
            raise ValueError(f"local_module={self.local_module!r} is invalid: allowed {LOCAL_MODULES}")
        if self.global_module not in GLOBAL_MODULES:
            raise ValueError(f"global_module={self.global_module!r} is invalid: allowed {GLOBAL_MODULES}")
        if self.graph_radius is not None:
            if not _is_real(self.graph_radius) or self.graph_radius <= 0:
                raise ValueError(f"graph_radius={self.graph_radius!r} is invalid: must be None (full graph) or a finite float > 0 (metres)")
            if self.state_dim < 2:
                raise ValueError(f"state_dim={self.state_dim!r} is invalid with a graph_radius: positions need state_dim >= 2")
        if not _is_real(self.position_scale) or self.position_scale <= 0:
            raise ValueError(f"position_scale={self.position_scale!r} is invalid: must be a finite float > 0 (metres per state unit)")
        if not _is_real(self.leaky_slope) or not 0 <= self.leaky_slope < 1:
            raise ValueError(f"leaky_slope={self.leaky_slope!r} is invalid: must be a float in [0, 1)")
        if not isinstance(self.detach_latent, bool):
            raise ValueError(f"detach_latent={self.detach_latent!r} is invalid: must be a bool")


def radius_adjacency(state_all: Tensor, valid: Tensor, radius: float | None = None, position_scale: float = 1.0) -> Tensor:
    """Boolean adjacency (B, M, M), ``adj[b, i, j]`` = node i receives from node j.

    Valid receivers receive from valid nodes (within ``radius`` metres when given, distance from
    ``state_all[..., :2] * position_scale``); every node has a self-loop, so padded receivers
    receive only from themselves and no softmax row is empty.
    """
    with torch.no_grad():
        adj = valid[:, :, None] & valid[:, None, :]
        if radius is not None:
            pos = state_all[..., :2] * position_scale
            d2 = (pos[:, :, None, :] - pos[:, None, :, :]).square().sum(-1)
            adj = adj & (d2 <= radius * radius)
        eye = torch.eye(valid.shape[1], dtype=torch.bool, device=valid.device)
        return adj | eye


class PairPacker:
    """Packs the valid (b, j) slots of (B, M, .) tensors into (P, .) rows (row-major order) and back."""

    def __init__(self, valid: Tensor) -> None:
        self.batch, self.nodes = valid.shape
        self.full = bool(valid.all())
        if self.full:
            self.idx = self.row = None
            self.size = self.batch * self.nodes
        else:
            self.idx = valid.reshape(-1).nonzero().squeeze(1)
            self.row = torch.div(self.idx, self.nodes, rounding_mode="floor")
            self.size = int(self.idx.numel())

    def pack(self, x: Tensor) -> Tensor:
        """(B, M, D) -> (P, D), the valid slots only."""
        x = x.reshape(self.batch * self.nodes, x.shape[-1])
        return x if self.idx is None else x.index_select(0, self.idx)

    def rows(self, x: Tensor) -> Tensor:
        """(B, D) -> (P, D): the batch row of every valid slot."""
        if self.row is None:
            return x.unsqueeze(1).expand(self.batch, self.nodes, x.shape[-1]).reshape(self.size, x.shape[-1])
        return x.index_select(0, self.row)

    def add_rows(self, per_row: Tensor, per_pair: Tensor) -> Tensor:
        """``rows(per_row) + per_pair`` for (B, D) and (P, D), broadcasting when no slot is padded."""
        if self.row is None:
            return (per_row.unsqueeze(1) + per_pair.view(self.batch, self.nodes, -1)).view(self.size, -1)
        return per_row.index_select(0, self.row) + per_pair

    def unpack(self, y: Tensor) -> Tensor:
        """(P, D) -> (B, M, D) with zeros in the padded slots."""
        if self.idx is None:
            return y.view(self.batch, self.nodes, y.shape[-1])
        out = y.new_zeros(self.batch * self.nodes, y.shape[-1]).index_copy(0, self.idx, y)
        return out.view(self.batch, self.nodes, y.shape[-1])


class Graph(NamedTuple):
    """Agent graph of one batch: node 0 = ego, then the N other slots."""

    state_all: Tensor  # (B, M, S), padded rows zeroed
    action_all: Tensor  # (B, M, A), padded rows zeroed
    valid: Tensor  # (B, M) bool, node 0 True
    adj: Tensor  # (B, M, M) bool, see radius_adjacency
    packer: PairPacker


def build_graph(
    state: Tensor,
    action: Tensor,
    others_state: Tensor,
    others_action: Tensor,
    others_mask: Tensor,
    radius: float | None = None,
    position_scale: float = 1.0,
) -> Graph:
    """Stack ego (node 0) and others, zero the padded slots' contents and build the adjacency."""
    mask = others_mask.to(torch.bool)
    m = mask.unsqueeze(-1)
    state_all = torch.cat([state.unsqueeze(1), torch.where(m, others_state, 0.0)], 1)
    action_all = torch.cat([action.unsqueeze(1), torch.where(m, others_action, 0.0)], 1)
    valid = torch.cat([torch.ones(mask.shape[0], 1, dtype=torch.bool, device=mask.device), mask], 1)
    adj = radius_adjacency(state_all, valid, radius, position_scale)
    return Graph(state_all, action_all, valid, adj, PairPacker(valid))


class PairLinear(nn.Module):
    """``nn.Linear`` on ``[ego_x, pair_x]`` for every valid pair, with the ego columns applied once per batch row."""

    def __init__(self, ego_dim: int, pair_dim: int, out_dim: int) -> None:
        super().__init__()
        self.ego_dim = ego_dim
        self.linear = nn.Linear(ego_dim + pair_dim, out_dim)

    def forward(self, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> Tensor:
        """ego_x (B, E), packed pair_x (P, D) -> (P, out) = ``linear(cat([packer.rows(ego_x), pair_x], -1))``."""
        w = self.linear.weight
        return packer.add_rows(F.linear(ego_x, w[:, : self.ego_dim], self.linear.bias), F.linear(pair_x, w[:, self.ego_dim :]))


class PairCVAE(nn.Module):
    """Local interaction-aware CVAE (paper Eqs. 1-3) over the valid pairs (i, j) of a batch."""

    def __init__(
        self,
        obs_dim: int,
        state_dim: int,
        act_dim: int,
        latent_dim: int,
        hidden: int = 256,
        encoder_layers: int = 3,
        decoder_layers: int = 2,
    ) -> None:
        super().__init__()
        ego_dim = obs_dim + state_dim + act_dim
        pair_dim = state_dim + act_dim
        self.enc_in = PairLinear(ego_dim, pair_dim, hidden)
        self.enc_body = mlp([hidden] * encoder_layers, nn.ReLU, nn.ReLU) if encoder_layers > 1 else nn.Identity()
        self.mu_head = nn.Linear(hidden, latent_dim)
        self.logvar_head = nn.Linear(hidden, latent_dim)
        self.dec_in = PairLinear(ego_dim, latent_dim + pair_dim, hidden)
        self.dec_body = mlp([hidden] * decoder_layers + [obs_dim + state_dim + 1], nn.ReLU)

    def encode(self, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> tuple[Tensor, Tensor]:
        """q(z | ego=[o_i, s_i, a_i], pair=[s_j, a_j]): ego_x (B, O+S+A), pair_x (P, S+A) -> (mu, logvar), each (P, L)."""
        h = self.enc_body(F.relu(self.enc_in(ego_x, pair_x, packer)))
        return self.mu_head(h), self.logvar_head(h)

    def decode(self, z: Tensor, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> Tensor:
        """Mean of p(y | z_ij, o_i, s_i, a_i, s_j, a_j): z (P, L) -> y_hat (P, O+S+1) = [o'_i, s'_i, r_i]."""
        return self.dec_body(F.relu(self.dec_in(ego_x, torch.cat([z, pair_x], -1), packer)))


class PairAttention(nn.Module):
    """Deterministic pairwise attention fusion (Table B.1 variant): sigmoid(q_i . k_j / sqrt(L)) * v_j."""

    def __init__(self, obs_dim: int, state_dim: int, act_dim: int, latent_dim: int) -> None:
        super().__init__()
        self.query = nn.Linear(obs_dim + state_dim + act_dim, latent_dim)
        self.key = nn.Linear(state_dim + act_dim, latent_dim)
        self.value = nn.Linear(state_dim + act_dim, latent_dim)
        self.scale = 1.0 / math.sqrt(latent_dim)

    def forward(self, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> Tensor:
        """ego_x (B, O+S+A), packed pair_x (P, S+A) -> pair features (P, L)."""
        q = packer.rows(self.query(ego_x))
        gate = torch.sigmoid((q * self.key(pair_x)).sum(-1, keepdim=True) * self.scale)
        return gate * self.value(pair_x)


class GATLayer(nn.Module):
    """Single-head GAT layer (paper Eqs. 4-6): masked softmax over neighbours j of LeakyReLU(a^T [W h_i || W h_j])."""

    def __init__(self, in_dim: int, out_dim: int, leaky_slope: float = 0.2) -> None:
        super().__init__()
        self.W = nn.Linear(in_dim, out_dim, bias=False)
        # a_gat = [a_recv ; a_nbr]; Glorot init of the (2F, 1) vector as in pyGAT.
        bound = 1.414 * math.sqrt(6.0 / (2 * out_dim + 1))
        self.a_recv = nn.Parameter(torch.empty(out_dim).uniform_(-bound, bound))
        self.a_nbr = nn.Parameter(torch.empty(out_dim).uniform_(-bound, bound))
        self.leaky_slope = leaky_slope

    def _alpha(self, s_recv: Tensor, s_nbr: Tensor, adj: Tensor) -> Tensor:
        e = F.leaky_relu(s_recv.unsqueeze(-1) + s_nbr.unsqueeze(1), self.leaky_slope)
        return torch.softmax(e.masked_fill(~adj, float("-inf")), dim=-1)

    def forward(self, h: Tensor, graph: Graph) -> tuple[Tensor, Tensor]:
        """Packed h (P, F_in) -> (out (B, M, F), alpha (B, M, M)); padded receivers' rows are zero."""
        # a . (W h) = (a^T W) h: both scores by one thin GEMM on h instead of per-node dot products on W h.
        u = torch.stack([self.a_recv @ self.W.weight, self.a_nbr @ self.W.weight])  # (2, F_in)
        wh = graph.packer.unpack(self.W(h))  # (B, M, F)
        s = graph.packer.unpack(F.linear(h, u))  # (B, M, 2)
        s_recv, s_nbr = s[..., 0], s[..., 1]
        alpha = self._alpha(s_recv, s_nbr, graph.adj).masked_fill(~graph.valid.unsqueeze(-1), 0.0)
        return F.relu(alpha @ wh), alpha

    def forward_ego(self, h: Tensor, graph: Graph) -> tuple[Tensor, Tensor]:
        """Dense h (B, M, F_in) -> (ego output (B, F), alpha (B, 1, M)), computing receiver node 0 only."""
        # sum_j alpha_0j W h_j = W (sum_j alpha_0j h_j): W is applied once per row, not per node.
        u_recv = self.a_recv @ self.W.weight
        u_nbr = self.a_nbr @ self.W.weight
        alpha = self._alpha((h[:, :1] @ u_recv), h @ u_nbr, graph.adj[:, :1])
        return F.relu(self.W((alpha @ h).squeeze(1))), alpha


class MeanAggLayer(nn.Module):
    """GCN layer ReLU(W mean_{N(i)} h_j), or GraphSAGE layer ReLU(W [h_i || mean_{N(i) minus i} h_j])."""

    def __init__(self, width: int, sage: bool) -> None:
        super().__init__()
        self.sage = sage
        self.lin = nn.Linear(2 * width if sage else width, width)

    def _input(self, h: Tensor, adj: Tensor) -> Tensor:
        r = adj.shape[1]
        if self.sage:
            adj = adj & ~torch.eye(r, adj.shape[2], dtype=torch.bool, device=adj.device)
        w = adj.to(h.dtype)
        agg = (w @ h) / w.sum(-1, keepdim=True).clamp_min(1.0)
        return torch.cat([h[:, :r], agg], -1) if self.sage else agg

    def forward(self, h: Tensor, graph: Graph) -> Tensor:
        """Dense h (B, M, F) -> (B, M, F); padded receivers' rows are zero."""
        return graph.packer.unpack(F.relu(self.lin(graph.packer.pack(self._input(h, graph.adj)))))

    def forward_ego(self, h: Tensor, graph: Graph) -> Tensor:
        """Dense h (B, M, F) -> ego output (B, F), computing receiver node 0 only."""
        return F.relu(self.lin(self._input(h, graph.adj[:, :1]).squeeze(1)))


class GraphModule(nn.Module):
    """Global interaction-aware module: 2 message-passing layers (or a masked mean-pool); returns the ego feature (B, F)."""

    def __init__(self, kind: str, width: int, leaky_slope: float = 0.2) -> None:
        super().__init__()
        if kind not in GLOBAL_MODULES:
            raise ValueError(f"global_module={kind!r} is invalid: allowed {GLOBAL_MODULES}")
        self.kind = kind
        self.last_attention: list[Tensor] = []
        if kind == "gat":
            self.layers = nn.ModuleList([GATLayer(width, width, leaky_slope), GATLayer(width, width, leaky_slope)])
        elif kind in ("gcn", "graphsage"):
            self.layers = nn.ModuleList([MeanAggLayer(width, kind == "graphsage"), MeanAggLayer(width, kind == "graphsage")])
        else:
            self.pool = nn.Linear(width, width)

    def forward(self, h: Tensor, graph: Graph) -> Tensor:
        """Packed node features h (P, F) -> the ego node's final feature (B, F).

        "gat" stores the detached attention of this pass in ``last_attention``: layer 1 (B, M, M)
        and layer 2's ego row (B, 1, M).
        """
        if self.kind == "none":
            w = graph.adj[:, :1].to(h.dtype)  # the ego's neighbourhood (valid, within the radius, itself)
            pooled = (w @ graph.packer.unpack(h)).squeeze(1) / w.sum(-1)
            return F.relu(self.pool(pooled))
        if self.kind == "gat":
            h1, a1 = self.layers[0](h, graph)
            out, a2 = self.layers[1].forward_ego(h1, graph)
            self.last_attention = [a1.detach(), a2.detach()]
            return out
        h1 = self.layers[0](graph.packer.unpack(h), graph)
        return self.layers[1].forward_ego(h1, graph)


class CriticBranch(nn.Module):
    """One value head of the centralized critic: node MLP -> graph module -> Linear([h_ego, obs MLP]) -> scalar."""

    def __init__(self, node_in: int, obs_in: int, cfg: CentralCriticConfig) -> None:
        super().__init__()
        act = partial(nn.LeakyReLU, cfg.leaky_slope)
        self.node_mlp = mlp([node_in, cfg.node_width, cfg.node_width], act, act)
        self.graph = GraphModule(cfg.global_module, cfg.node_width, cfg.leaky_slope)
        self.obs_mlp = mlp([obs_in, cfg.hidden, cfg.hidden], nn.ReLU, nn.ReLU)
        self.head = nn.Linear(cfg.node_width + cfg.hidden, 1)

    def forward(self, node_x: Tensor, obs_x: Tensor, graph: Graph) -> Tensor:
        """Packed node inputs (P, node_in), obs_x (B, obs_in) -> value (B,)."""
        g = self.graph(self.node_mlp(node_x), graph)
        return self.head(torch.cat([g, self.obs_mlp(obs_x)], -1)).squeeze(-1)


class CriticOutputs(NamedTuple):
    """Everything one critic update needs from a single pass (the encoder runs once)."""

    q1: Tensor
    q2: Tensor
    v: Tensor
    recon_mse: Tensor
    kl: Tensor


class CentralCritic(nn.Module):
    """COIN interaction-aware centralized critic: twin global Q heads and the counterfactual baseline V (see module doc)."""

    def __init__(self, cfg: CentralCriticConfig) -> None:
        super().__init__()
        self.cfg = cfg
        o, s, a, lat = cfg.obs_dim, cfg.state_dim, cfg.act_dim, cfg.latent_dim
        self.local: nn.Module | None
        if cfg.local_module == "cvae":
            self.local = PairCVAE(o, s, a, lat, cfg.hidden, cfg.cvae_encoder_layers, cfg.cvae_decoder_layers)
        elif cfg.local_module == "attention":
            self.local = PairAttention(o, s, a, lat)
        else:
            self.local = None
        feat = 0 if self.local is None else lat
        self.q1_branch = CriticBranch(s + a + feat, o + a, cfg)
        self.q2_branch = CriticBranch(s + a + feat, o + a, cfg)
        self.v_branch = CriticBranch(s + a, o, cfg)

    # ------------------------------------------------------------------ internals
    def _graph(self, state: Tensor, action: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor) -> Graph:
        return build_graph(state, action, others_state, others_action, others_mask, self.cfg.graph_radius, self.cfg.position_scale)

    def _q_nodes(self, obs: Tensor, state: Tensor, action: Tensor, graph: Graph, mu: Tensor | None = None) -> Tensor:
        """Packed Q node inputs [s_j, a_j, f_ij] (P, S+A(+L)); ``mu`` = packed CVAE means if already computed."""
        pair_x = graph.packer.pack(torch.cat([graph.state_all, graph.action_all], -1))
        if self.local is None:
            return pair_x
        ego_x = torch.cat([obs, state, action], -1)
        if isinstance(self.local, PairAttention):
            feat = self.local(ego_x, pair_x, graph.packer)
        else:
            if mu is None:
                mu = self.local.encode(ego_x, pair_x, graph.packer)[0]
            feat = mu.detach() if self.cfg.detach_latent else mu
        return torch.cat([pair_x, feat], -1)

    def _v(self, obs: Tensor, graph: Graph) -> Tensor:
        action_v = torch.cat([torch.zeros_like(graph.action_all[:, :1]), graph.action_all[:, 1:]], 1)
        return self.v_branch(graph.packer.pack(torch.cat([graph.state_all, action_v], -1)), obs, graph)

    def _elbo(
        self,
        obs: Tensor,
        state: Tensor,
        action: Tensor,
        graph: Graph,
        target_y: Tensor,
        generator: torch.Generator | None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(recon_mse, kl, packed mu) over the valid pairs."""
        assert isinstance(self.local, PairCVAE)
        ego_x = torch.cat([obs, state, action], -1)
        pair_x = graph.packer.pack(torch.cat([graph.state_all, graph.action_all], -1))
        mu, logvar = self.local.encode(ego_x, pair_x, graph.packer)
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        y_hat = self.local.decode(mu + eps * torch.exp(0.5 * logvar), ego_x, pair_x, graph.packer)
        target = graph.packer.rows(target_y) if target_y.dim() == 2 else graph.packer.pack(target_y)
        recon = (y_hat - target).square().mean()
        kl = -0.5 * (1.0 + logvar - mu.square() - logvar.exp()).mean()
        return recon, kl, mu

    # ------------------------------------------------------------------ public API
    def q_values(
        self, obs: Tensor, state: Tensor, action: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Global twin Q (q1, q2), each (B,), of ego action ``action`` given the others' states/actions."""
        graph = self._graph(state, action, others_state, others_action, others_mask)
        node_x, obs_x = self._q_nodes(obs, state, action, graph), torch.cat([obs, action], -1)
        return self.q1_branch(node_x, obs_x, graph), self.q2_branch(node_x, obs_x, graph)

    def q1(self, obs: Tensor, state: Tensor, action: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor) -> Tensor:
        """Global Q1 (B,) only (actor loss, Eq. 12)."""
        graph = self._graph(state, action, others_state, others_action, others_mask)
        return self.q1_branch(self._q_nodes(obs, state, action, graph), torch.cat([obs, action], -1), graph)

    def baseline(self, obs: Tensor, state: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor) -> Tensor:
        """Counterfactual baseline V(o_i, s_i, s_-i, a_-i) (B,), independent of the ego action (Eq. 10)."""
        dummy = state.new_zeros(state.shape[0], self.cfg.act_dim)
        return self._v(obs, self._graph(state, dummy, others_state, others_action, others_mask))

    def cvae_loss(
        self,
        obs: Tensor,
        state: Tensor,
        action: Tensor,
        others_state: Tensor,
        others_action: Tensor,
        others_mask: Tensor,
        target_y: Tensor,
        kl_beta: float = 1.0,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """CVAE terms of the negative ELBO (Eq. 3) over the valid pairs: (recon_mse, kl), both unweighted.

        ``target_y`` = [o'_i, s'_i, r_i] of the ego, shape (B, O+S+1) (the same target for every
        pair of the row) or (B, N+1, O+S+1) per pair. Valid pairs (b, j): node 0 and the others
        whose mask is True; padded pairs are never computed and contribute nothing. With P valid
        pairs, D = O+S+1, L = latent_dim:
        ``recon_mse = sum_{valid (b,j)} sum_d (y_hat - y)^2 / (P * D)`` and
        ``kl = -0.5 * sum_{valid (b,j)} sum_l (1 + logvar - mu^2 - exp(logvar)) / (P * L)``
        (means per element, no sum over dims). ``kl_beta`` is NOT applied here (both values are
        returned raw for logging): the caller forms ``recon_mse + kl_beta * kl``; the argument is
        kept so that callers can pass it positionally.
        The decoder gets z = mu + eps * exp(logvar / 2) with eps ~ N(0, I) of shape (P, L), valid
        pairs in row-major (b, j) order, drawn from ``generator`` when given, else from the global
        torch RNG. Returns two zero scalars for the "attention" / "none" local modules.
        """
        if not isinstance(self.local, PairCVAE):
            return obs.new_zeros(()), obs.new_zeros(())
        graph = self._graph(state, action, others_state, others_action, others_mask)
        recon, kl, _ = self._elbo(obs, state, action, graph, target_y, generator)
        return recon, kl

    def forward(
        self,
        obs: Tensor,
        state: Tensor,
        action: Tensor,
        others_state: Tensor,
        others_action: Tensor,
        others_mask: Tensor,
        target_y: Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> CriticOutputs:
        """q1, q2, V and the CVAE terms in one pass (encoder run once); equal to the separate methods.

        The CVAE terms (unweighted, as in :meth:`cvae_loss`; same RNG use) are zeros when
        ``target_y`` is None or the local module is not "cvae".
        """
        graph = self._graph(state, action, others_state, others_action, others_mask)
        recon, kl, mu = obs.new_zeros(()), obs.new_zeros(()), None
        if isinstance(self.local, PairCVAE) and target_y is not None:
            recon, kl, mu = self._elbo(obs, state, action, graph, target_y, generator)
        node_x, obs_x = self._q_nodes(obs, state, action, graph, mu), torch.cat([obs, action], -1)
        q1 = self.q1_branch(node_x, obs_x, graph)
        q2 = self.q2_branch(node_x, obs_x, graph)
        return CriticOutputs(q1, q2, self._v(obs, graph), recon, kl)
