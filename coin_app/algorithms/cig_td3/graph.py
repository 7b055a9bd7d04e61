"""Global (graph) interaction modules of the COIN centralized critic: the agent graph, GAT, GCN and GraphSAGE.

Shapes: ``B`` batch rows, ``N`` padded other-agent slots, ``M = N + 1`` nodes (node 0 = the
ego), ``P`` valid (b, j) slots, ``F`` node feature width (128).

* **Graph.** Node 0 + valid others, self-loops included; with ``graph_radius`` only nodes within
  that distance (metres, from the first two state entries times ``position_scale``, ``<=``) of the
  receiving node (COIN App. B.2). Padded slots are zeroed on input, receive only from themselves
  and have zero output rows, so their contents cannot change any output (bit-identical).
* **"gat"**: 2 GAT layers (COIN Eqs. 4-6); per head k
  ``e^k_ij = LeakyReLU(a^k_1.W_k h_i + a^k_2.W_k h_j)`` by broadcasting, masked softmax over j,
  ``ReLU(sum_j alpha^k_ij W_k h_j)``. Layer 1 has ``heads`` heads of width F concatenated
  (``heads * F``), layer 2 one head ``heads * F -> F``; W_k and a_k are Xavier-uniform with gain
  1.414 (``init="xavier"``, as pyGAT) or W uses ``nn.Linear``'s default (``init="default"``; with
  ``heads=1`` exactly the single-head layer used before issue #27). Heads, initialization and the
  official code's GAT bugs we do not copy (softmax over receivers, ELU + log-softmax head):
  ``docs/decisions.md`` §2 (rows "GAT", "GAT heads, initialisation"). **"gcn"**:
  ``ReLU(W mean_{j in N(i)} h_j)``; **"graphsage"**: ``ReLU(W [h_i || mean_{j in N(i), j != i} h_j])``
  (zero mean when i has no other neighbour); **"none"**: ReLU(Linear(mean of h_j over the ego's
  neighbourhood)) (COIN Table B.1 "w/o GAT"). Only the ego's final feature is read out, so the
  second layer is computed for the ego row only, as ``W (sum_j alpha_0j h_j)`` (exactly what a
  full second layer gives at node 0, without W on every node). The scores use
  ``a . (W h) = (a^T W) h`` (one thin GEMM with 2 columns per head).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coin_app.algorithms.choices import GAT_INITS, GLOBAL_MODULES  # noqa: F401 (re-exported)
from coin_app.algorithms.cig_td3.pairwise import PairPacker
from coin_app.algorithms.masked_softmax import masked_softmax

XAVIER_GAIN = 1.414  # pyGAT's gain for W and a (the official COIN code's GAT, docs/decisions.md §2)

__all__ = [
    "GAT_INITS",
    "GLOBAL_MODULES",
    "GATLayer",
    "Graph",
    "GraphModule",
    "MeanAggLayer",
    "build_graph",
    "occupied_slots",
    "radius_adjacency",
]


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


def occupied_slots(mask: Tensor) -> int:
    """How many leading slot columns of ``mask`` (B, N) hold every valid slot of the batch: 1 + the last valid column, 0 if none."""
    cols = mask.any(0).nonzero()
    return int(cols[-1]) + 1 if cols.numel() else 0


def _check_gat_args(heads: object, init: object) -> None:
    """Raise ValueError unless ``heads`` is a positive int and ``init`` one of :data:`GAT_INITS`."""
    if not isinstance(heads, int) or isinstance(heads, bool) or heads < 1:
        raise ValueError(f"gat_heads={heads!r} is invalid: must be a positive int")
    if init not in GAT_INITS:
        raise ValueError(f"gat_init={init!r} is invalid: allowed {GAT_INITS}")


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
    """Multi-head GAT layer (COIN Eqs. 4-6): per head, masked softmax over j of LeakyReLU(a^T [W h_i || W h_j]); heads concatenated.

    Parameters: ``W`` one ``nn.Linear(in_dim, heads * out_dim)`` whose rows ``k*F:(k+1)*F`` are
    head k's W_k (F_in -> F); ``a_recv``, ``a_nbr`` (heads, F), head k's ``a_k = [a_recv[k] ; a_nbr[k]]``.
    ``init="xavier"``: every W_k and every (2F, 1) vector a_k Xavier-uniform with gain 1.414, as
    pyGAT / the official code (``docs/decisions.md`` §2); ``init="default"``: ``nn.Linear``'s
    default for W, a_k as Xavier (the draws of the single-head layer before issue #27, in the same
    RNG order, so ``heads=1, init="default"`` starts from its exact weights for a given torch seed;
    its outputs differ from that layer's by the float rounding of :func:`masked_softmax` only).
    """

    def __init__(self, in_dim: int, out_dim: int, leaky_slope: float = 0.2, heads: int = 1, init: str = "xavier") -> None:
        super().__init__()
        _check_gat_args(heads, init)
        self.heads, self.out_dim, self.leaky_slope = heads, out_dim, leaky_slope
        self.W = nn.Linear(in_dim, heads * out_dim, bias=False)
        # a_k = [a_recv[k] ; a_nbr[k]], a (2F, 1) vector: Glorot bound gain * sqrt(6 / (2F + 1)) as in pyGAT.
        bound = XAVIER_GAIN * math.sqrt(6.0 / (2 * out_dim + 1))
        self.a_recv = nn.Parameter(torch.empty(heads, out_dim).uniform_(-bound, bound))
        self.a_nbr = nn.Parameter(torch.empty(heads, out_dim).uniform_(-bound, bound))
        if init == "xavier":
            with torch.no_grad():
                for w_k in self.W.weight.split(out_dim):  # per head: fan_in + fan_out = F_in + F
                    nn.init.xavier_uniform_(w_k, gain=XAVIER_GAIN)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: Any, **kwargs: Any) -> None:
        """Accept the single-head layer's (F,) attention vectors of checkpoints saved before the multi-head layer."""
        for name in ("a_recv", "a_nbr"):
            key = prefix + name
            if key in state_dict and state_dict[key].dim() == 1 and self.a_recv.shape[0] == 1:
                state_dict[key] = state_dict[key].unsqueeze(0)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def _score_vectors(self) -> tuple[Tensor, Tensor]:
        """(u_recv, u_nbr), each (H, F_in): ``u[k] = a[k]^T W_k``, so that ``a[k] . (W_k h) = u[k] . h``."""
        if self.heads == 1:  # vector-matrix products, as the single-head layer before issue #27
            return (self.a_recv[0] @ self.W.weight).unsqueeze(0), (self.a_nbr[0] @ self.W.weight).unsqueeze(0)
        w = self.W.weight.view(self.heads, self.out_dim, -1)  # (H, F, F_in)
        return (self.a_recv.unsqueeze(1) @ w).squeeze(1), (self.a_nbr.unsqueeze(1) @ w).squeeze(1)

    def _alpha(self, s_recv: Tensor, s_nbr: Tensor, adj: Tensor) -> Tensor:
        """Scores s_recv (B, H, R), s_nbr (B, H, M), adj (B, R, M) -> alpha (B, H, R, M), softmax over j."""
        e = F.leaky_relu(s_recv.unsqueeze(-1) + s_nbr.unsqueeze(-2), self.leaky_slope)
        return masked_softmax(e, adj.unsqueeze(1))

    def head_outputs(self, h: Tensor, graph: Graph) -> tuple[list[Tensor], Tensor]:
        """Packed h (P, F_in) -> (each head's output (B, M, F), alpha (B, H, M, M)); padded receivers' outputs are zero.

        A padded receiver's alpha row is its self-loop (1 on the diagonal), not masked: its W h is
        zero, so its output is exactly zero either way (:meth:`forward` masks the rows).
        """
        hh = self.heads
        # All scores by one thin GEMM, then head-major (B, 2H, M) so that e and alpha are contiguous (B, H, M, M).
        s = graph.packer.unpack(F.linear(h, torch.cat(self._score_vectors()))).transpose(1, 2).contiguous()
        alpha = self._alpha(s[:, :hh], s[:, hh:], graph.adj)
        # Head k: alpha_k (B, M, M) @ W_k h (B, M, F), each head on its own contiguous block (no concatenation).
        outs = [
            F.relu(a_k @ graph.packer.unpack(F.linear(h, w_k)), inplace=True)
            for a_k, w_k in zip(alpha.unbind(1), self.W.weight.split(self.out_dim))
        ]
        return outs, alpha

    def forward(self, h: Tensor, graph: Graph) -> tuple[Tensor, Tensor]:
        """Packed h (P, F_in) -> (out (B, M, H*F), alpha (B, H, M, M)); padded receivers' rows are zero."""
        outs, alpha = self.head_outputs(h, graph)
        return torch.cat(outs, -1), alpha.masked_fill(~graph.valid[:, None, :, None], 0.0)

    def forward_ego(self, h: Tensor | Sequence[Tensor], graph: Graph) -> tuple[Tensor, Tensor]:
        """Dense h (B, M, F_in), or column blocks whose concatenation is h -> (ego output (B, H*F), alpha (B, H, 1, M)), receiver 0 only.

        Blocks (e.g. the first layer's heads) are used as they are, never concatenated. The scores
        are matrix-vector products per block and head, whose gradients are broadcast products (a
        GEMM with one inner column, as ``h @ u.T`` is, is several times slower on the CPU).
        """
        # sum_j alpha_0j W_k h_j = W_k (sum_j alpha_0j h_j): W is applied once per row and head, not per node.
        blocks = [h] if isinstance(h, Tensor) else list(h)
        hh, widths = self.heads, [b.shape[-1] for b in blocks]
        u_recv, u_nbr = (u.split(widths, -1) for u in self._score_vectors())  # per block (H, F_b)
        s_recv = torch.stack([sum(b[:, 0] @ u[k] for b, u in zip(blocks, u_recv)) for k in range(hh)], 1)  # (B, H)
        s_nbr = torch.stack([sum(b @ u[k] for b, u in zip(blocks, u_nbr)) for k in range(hh)], 1)  # (B, H, M)
        alpha = self._alpha(s_recv.unsqueeze(-1), s_nbr, graph.adj[:, :1])
        agg = torch.cat([alpha.squeeze(2) @ b for b in blocks], -1)  # (B, H, F_in): sum_j alpha^k_0j h_j
        if hh == 1:
            return F.relu(self.W(agg.squeeze(1))), alpha
        w = self.W.weight.view(hh, self.out_dim, -1)  # (H, F, F_in)
        out = torch.bmm(agg.transpose(0, 1), w.transpose(1, 2))  # (H, B, F), batched over heads
        return F.relu(out.transpose(0, 1).reshape(-1, hh * self.out_dim)), alpha


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
    """Global interaction-aware module: 2 message-passing layers (or a masked mean-pool); returns the ego feature (B, F).

    ``heads`` (first GAT layer's head count) and ``init`` (:data:`GAT_INITS`) apply to "gat" only
    and are validated for every kind.
    """

    def __init__(self, kind: str, width: int, leaky_slope: float = 0.2, heads: int = 2, init: str = "xavier") -> None:
        super().__init__()
        if kind not in GLOBAL_MODULES:
            raise ValueError(f"global_module={kind!r} is invalid: allowed {GLOBAL_MODULES}")
        _check_gat_args(heads, init)
        self.kind = kind
        self._attention: tuple[Tensor, Tensor, Tensor] | None = None  # (layer 1 alpha, layer 2 alpha, valid) of the last pass
        if kind == "gat":
            # Layer 1: `heads` heads of width F concatenated; layer 2: one head heads*F -> F (official code, docs/decisions.md §2).
            self.layers = nn.ModuleList(
                [GATLayer(width, width, leaky_slope, heads, init), GATLayer(heads * width, width, leaky_slope, 1, init)]
            )
        elif kind in ("gcn", "graphsage"):
            self.layers = nn.ModuleList([MeanAggLayer(width, kind == "graphsage"), MeanAggLayer(width, kind == "graphsage")])
        else:
            self.pool = nn.Linear(width, width)

    @property
    def last_attention(self) -> list[Tensor]:
        """The detached attention of the last "gat" pass ([] before any).

        Layer 1 (B, heads, M, M) with the padded receivers' rows zero, and layer 2's ego row (B, 1, 1, M).
        """
        if self._attention is None:
            return []
        a1, a2, valid = self._attention
        return [a1.masked_fill(~valid[:, None, :, None], 0.0), a2]

    def forward(self, h: Tensor, graph: Graph) -> Tensor:
        """Packed node features h (P, F) -> the ego node's final feature (B, F).

        "gat" stores the detached attention of this pass in ``last_attention``: layer 1
        (B, heads, M, M) and layer 2's ego row (B, 1, 1, M) (one head); ``alpha[b, k, i, j]``.
        """
        if self.kind == "none":
            w = graph.adj[:, :1].to(h.dtype)  # the ego's neighbourhood (valid, within the radius, itself)
            pooled = (w @ graph.packer.unpack(h)).squeeze(1) / w.sum(-1)
            return F.relu(self.pool(pooled))
        if self.kind == "gat":
            h1, a1 = self.layers[0].head_outputs(h, graph)
            out, a2 = self.layers[1].forward_ego(h1, graph)
            self._attention = (a1.detach(), a2.detach(), graph.valid)
            return out
        h1 = self.layers[0](graph.packer.unpack(h), graph)
        return self.layers[1].forward_ego(h1, graph)
