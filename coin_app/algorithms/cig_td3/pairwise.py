"""Pairwise (local) interaction modules of the COIN centralized critic: the CVAE and its attention alternative.

For every pair (i, j) of a batch row, j = i included (the ego node uses its own s_i, a_i as
s_j, a_j), a local module turns ``[o_i, s_i, a_i | s_j, a_j]`` into an L-dim pair feature f_ij
that the graph module (``graph.py``) then aggregates over j (COIN §4.1, Fig. 2). Shapes: ``B``
batch rows, ``N`` padded other-agent slots, ``M = N + 1`` nodes (node 0 = the ego), ``P`` valid
(b, j) pairs, ``O`` observation, ``S`` local state, ``A`` action, ``L`` latent (20).

* **"cvae"** (COIN Eqs. 1-3): the encoder q(z_ij | o_i, s_i, s_j, a_i, a_j) gives
  (mu_ij, logvar_ij) and the decoder p(y | z_ij, o_i, s_i, s_j, a_i, a_j) reconstructs
  y = [o'_i, s'_i, r_i] (the official code drops o_i from the decoder and s'_i from y; we follow
  the paper). Encoder: 3 hidden layers of 256 (ReLU) then linear mu / logvar heads; decoder: 2
  hidden layers of 256 (ReLU) then a linear output (as the official code). The first layer of
  both acts on the concatenation ``[o_i, s_i, a_i | s_j, a_j]`` (decoder:
  ``[o_i, s_i, a_i | z_ij, s_j, a_j]``); it is one ``nn.Linear`` whose ego columns are applied
  once per row and broadcast over the pairs (:class:`PairLinear`, mathematically the plain layer
  on the concatenation).
* **"attention"** (COIN Table B.1 ablation): a deterministic pairwise fusion
  ``f_ij = sigmoid(q(o_i, s_i, a_i) . k(s_j, a_j) / sqrt(L)) * v(s_j, a_j)`` (L-dim). The gate is
  a sigmoid rather than a softmax over j so the feature stays pairwise (like z_ij) and does not
  shrink with the number of agents; the cross-agent normalisation is the graph module's job.
* **"none"**: no pair feature; the critic (``critic.py``) uses ``x_j = [s_j, a_j]``.

Padded slots never enter a per-pair MLP: :class:`PairPacker` packs the valid (b, j) slots into
P rows, so their contents cannot change any output and they cost no MLP work.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from coin_app.algorithms.choices import LOCAL_MODULES  # noqa: F401 (re-exported)
from coin_app.algorithms.td3.networks import mlp

__all__ = ["LOCAL_MODULES", "PairAttention", "PairCVAE", "PairLinear", "PairPacker"]


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
        h = self._hidden(ego_x, pair_x, packer)
        # both heads in one GEMM (one pass over h): the same as mu_head(h), logvar_head(h)
        w = torch.cat([self.mu_head.weight, self.logvar_head.weight])
        return F.linear(h, w, torch.cat([self.mu_head.bias, self.logvar_head.bias])).chunk(2, -1)

    def encode_mean(self, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> Tensor:
        """mu of :meth:`encode` alone (P, L) (the Q branches' latent; no logvar computed)."""
        return self.mu_head(self._hidden(ego_x, pair_x, packer))

    def _hidden(self, ego_x: Tensor, pair_x: Tensor, packer: PairPacker) -> Tensor:
        """The encoder's last hidden layer (P, hidden)."""
        return self.enc_body(F.relu(self.enc_in(ego_x, pair_x, packer)))

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
