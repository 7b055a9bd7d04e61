"""Global (graph) interaction modules of the COIN centralized critic: the agent graph, GAT, GCN and GraphSAGE.

Shapes: ``B`` batch rows, ``N`` padded other-agent slots, ``M = N + 1`` nodes (node 0 = the
ego), ``P`` valid (b, j) slots, ``F`` node feature width (128).

* **Graph.** Node 0 + valid others, self-loops included; with ``graph_radius`` only nodes within
  that distance (metres, from the first two state entries times ``position_scale``, ``<=``) of the
  receiving node (COIN App. B.2). Padded slots are zeroed on input, receive only from themselves
  and have zero output rows, so their contents cannot change any output (bit-identical).
* **"gat"**: 2 single-head GAT layers (COIN Eqs. 4-6): ``e_ij = LeakyReLU(a1.Wh_i + a2.Wh_j)``
  by broadcasting, masked softmax over j, ``h'_i = ReLU(sum_j alpha_ij W h_j)``. **"gcn"**:
  ``ReLU(W mean_{j in N(i)} h_j)``; **"graphsage"**: ``ReLU(W [h_i || mean_{j in N(i), j != i} h_j])``
  (zero mean when i has no other neighbour); **"none"**: ReLU(Linear(mean of h_j over the ego's
  neighbourhood)) (COIN Table B.1 "w/o GAT"). Only the ego's final feature is read out, so the
  second layer is computed for the ego row only, as ``W (sum_j alpha_0j h_j)`` (exactly what a
  full second layer gives at node 0, without W on every node). The scores use
  ``a . (W h) = (a^T W) h``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coin_app.algorithms.cig_td3.pairwise import PairPacker

GLOBAL_MODULES = ("gat", "gcn", "graphsage", "none")

__all__ = ["GLOBAL_MODULES", "GATLayer", "Graph", "GraphModule", "MeanAggLayer", "build_graph", "radius_adjacency"]


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
