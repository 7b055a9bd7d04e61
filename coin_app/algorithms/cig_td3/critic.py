"""The COIN interaction-aware centralized critic: twin global Q heads and the counterfactual baseline V.

Composes a pairwise module (``pairwise.py``: CVAE or attention) and a graph module
(``graph.py``: GAT, GCN, GraphSAGE) into the critic of COIN Fig. 2 (Eqs. 1-6, 9-11, App. B),
with the choices made where the paper is silent (docs/guides/train-cig-td3.md, "Where the paper is silent"). Plain
``torch.nn``; nothing here imports Ray. Shapes: ``B`` batch rows (one ego agent at one env step
each), ``N`` padded slots for the other agents, ``M = N + 1`` graph nodes (node 0 = the ego),
``O`` observation, ``S`` local state (``schema.STATE_DIM``), ``A`` action (``schema.ACT_DIM``),
``L`` latent (20).

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
  latents, observation branch on o_i only, so V does not depend on a_i at all. With the "attention"
  local module f_ij replaces mu_ij; with "none", ``x_j = [s_j, a_j]``.
* **Node MLP**: Linear(., 128) -> LeakyReLU -> Linear(128, 128) -> LeakyReLU (paper; the official
  code uses ReLU). The slope is ``leaky_slope`` (also the GAT score slope). Padded slots never
  enter it (packed rows, :class:`~coin_app.algorithms.cig_td3.pairwise.PairPacker`).
* **Readout**: ``Linear([h_ego, MLP_obs(.)])`` -> scalar, one layer (paper Fig. 2; the official code
  uses two). MLP_obs: 2 layers of ``hidden`` with ReLU on ``[o_i, a_i]`` (Q) or ``o_i`` (V).
* **Twin Q**: Q1 and Q2 have their own node MLP, graph module, observation branch and head and share
  the local module; V has its own as well.

Cost: with every slot valid, one forward + backward of twin Q + V + ELBO is about 1.3 M
multiply-adds per node (over half in the CVAE's three 256x256 layers; the 2-head first GAT layer
adds about 0.2 M over a single head), i.e. about 33 GFLOP for B=256, N=47 (28 with
``gat_heads=1``); use :meth:`CentralCritic.forward` to run the encoder once for all terms. The
graph is built over the occupied slots only: trailing slot columns that no row of the batch fills
(the replay pads every row to ``max_others``) are dropped before anything runs, which changes no
output (padded slots contribute exact zeros) and shrinks the GAT's dense (B, M, M) attention.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import partial
from typing import NamedTuple

import torch
from torch import Tensor, nn

from coin_app.algorithms.cig_td3.graph import GAT_INITS, GLOBAL_MODULES, Graph, GraphModule, build_graph, occupied_slots
from coin_app.algorithms.cig_td3.pairwise import LOCAL_MODULES, PairAttention, PairCVAE
from coin_app.algorithms.td3.networks import full_precision, mlp, q_head
from coin_app.sim import schema

__all__ = ["CentralCritic", "CentralCriticConfig", "CriticBranch", "CriticOutputs"]


def _is_int(x: object) -> bool:
    """Whether ``x`` is an int (not a bool)."""
    return isinstance(x, int) and not isinstance(x, bool)


def _is_real(x: object) -> bool:
    """Whether ``x`` is a finite int or float (not a bool)."""
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
    encoder (3) and decoder (2), as in the official code; ``gat_heads`` heads of width
    ``node_width`` concatenated in the first GAT layer (2; the second is one head
    ``gat_heads * node_width -> node_width``) and ``gat_init`` "xavier" (gain 1.414) | "default"
    (``nn.Linear``'s) GAT initialization, both as the official code where the paper is silent
    (``docs/decisions.md`` §2; ``gat_heads=1, gat_init="default"`` is the single-head GAT used before
    issue #27); both are validated for every ``global_module`` and used by "gat" only;
    ``feature_norm`` divides each branch's features ``[h_ego, obs MLP]`` by their L2 norm before its
    output layer (:func:`~coin_app.algorithms.td3.networks.q_head`; not in COIN).
    """

    obs_dim: int
    state_dim: int = schema.STATE_DIM
    act_dim: int = schema.ACT_DIM
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
    gat_heads: int = 2
    gat_init: str = "xavier"
    feature_norm: bool = False

    def __post_init__(self) -> None:
        """Validate every field; raise ValueError naming the bad value and what is allowed."""
        names = (
            "obs_dim",
            "state_dim",
            "act_dim",
            "latent_dim",
            "hidden",
            "node_width",
            "cvae_encoder_layers",
            "cvae_decoder_layers",
            "gat_heads",
        )
        for name in names:
            v = getattr(self, name)
            if not _is_int(v) or v < 1:
                raise ValueError(f"{name}={v!r} is invalid: must be a positive int")
        if self.local_module not in LOCAL_MODULES:
            raise ValueError(f"local_module={self.local_module!r} is invalid: allowed {LOCAL_MODULES}")
        if self.global_module not in GLOBAL_MODULES:
            raise ValueError(f"global_module={self.global_module!r} is invalid: allowed {GLOBAL_MODULES}")
        if self.gat_init not in GAT_INITS:
            raise ValueError(f"gat_init={self.gat_init!r} is invalid: allowed {GAT_INITS}")
        if self.graph_radius is not None:
            if not _is_real(self.graph_radius) or self.graph_radius <= 0:
                raise ValueError(f"graph_radius={self.graph_radius!r} is invalid: must be None (full graph) or a finite float > 0 (metres)")
            if self.state_dim < 2:
                raise ValueError(f"state_dim={self.state_dim!r} is invalid with a graph_radius: positions need state_dim >= 2")
        if not _is_real(self.position_scale) or self.position_scale <= 0:
            raise ValueError(f"position_scale={self.position_scale!r} is invalid: must be a finite float > 0 (metres per state unit)")
        if not _is_real(self.leaky_slope) or not 0 <= self.leaky_slope < 1:
            raise ValueError(f"leaky_slope={self.leaky_slope!r} is invalid: must be a float in [0, 1)")
        for name in ("detach_latent", "feature_norm"):
            if not isinstance(getattr(self, name), bool):
                raise ValueError(f"{name}={getattr(self, name)!r} is invalid: must be a bool")


class CriticBranch(nn.Module):
    """One value head of the centralized critic: node MLP -> graph module -> Linear([h_ego, obs MLP]) -> scalar."""

    def __init__(self, node_in: int, obs_in: int, cfg: CentralCriticConfig) -> None:
        super().__init__()
        act = partial(nn.LeakyReLU, cfg.leaky_slope)
        self.node_mlp = mlp([node_in, cfg.node_width, cfg.node_width], act, act)
        self.graph = GraphModule(cfg.global_module, cfg.node_width, cfg.leaky_slope, cfg.gat_heads, cfg.gat_init)
        self.obs_mlp = mlp([obs_in, cfg.hidden, cfg.hidden], nn.ReLU, nn.ReLU)
        self.head = nn.Linear(cfg.node_width + cfg.hidden, 1)
        self.feature_norm = cfg.feature_norm

    def forward(self, node_x: Tensor, obs_x: Tensor, graph: Graph) -> Tensor:
        """Packed node inputs (P, node_in), obs_x (B, obs_in) -> value (B,)."""
        g = self.graph(self.node_mlp(node_x), graph)
        return q_head(torch.cat([g, self.obs_mlp(obs_x)], -1), self.head, self.feature_norm).squeeze(-1)


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
        """The agent graph over the occupied slots (the trailing slots no row fills change no output, so they are dropped)."""
        n = occupied_slots(others_mask)
        others_state, others_action, others_mask = others_state[:, :n], others_action[:, :n], others_mask[:, :n]
        return build_graph(state, action, others_state, others_action, others_mask, self.cfg.graph_radius, self.cfg.position_scale)

    @staticmethod
    def _pairs(obs: Tensor, state: Tensor, action: Tensor, graph: Graph) -> tuple[Tensor, Tensor]:
        """(ego_x = [o_i, s_i, a_i] (B, O+S+A), packed pair_x = [s_j, a_j] (P, S+A)): the local module's inputs."""
        return torch.cat([obs, state, action], -1), graph.packer.pack(torch.cat([graph.state_all, graph.action_all], -1))

    def _q_nodes(self, ego_x: Tensor, pair_x: Tensor, graph: Graph, mu: Tensor | None = None) -> Tensor:
        """Packed Q node inputs [s_j, a_j, f_ij] (P, S+A(+L)); ``mu`` = packed CVAE means if already computed."""
        if self.local is None:
            return pair_x
        if isinstance(self.local, PairAttention):
            feat = self.local(ego_x, pair_x, graph.packer)
        else:
            if mu is None:
                mu = self.local.encode_mean(ego_x, pair_x, graph.packer)
            feat = mu.detach() if self.cfg.detach_latent else mu
        return torch.cat([pair_x, feat], -1)

    def _v(self, obs: Tensor, graph: Graph) -> Tensor:
        action_v = torch.cat([torch.zeros_like(graph.action_all[:, :1]), graph.action_all[:, 1:]], 1)
        return self.v_branch(graph.packer.pack(torch.cat([graph.state_all, action_v], -1)), obs, graph)

    def _elbo(
        self, ego_x: Tensor, pair_x: Tensor, graph: Graph, target_y: Tensor, generator: torch.Generator | None
    ) -> tuple[Tensor, Tensor, Tensor]:
        """(recon_mse, kl, packed mu) over the valid pairs."""
        assert isinstance(self.local, PairCVAE)
        mu, logvar = map(full_precision, self.local.encode(ego_x, pair_x, graph.packer))  # the ELBO in fp32 under bf16 autocast
        eps = torch.randn(mu.shape, generator=generator, dtype=mu.dtype, device=mu.device)
        y_hat = full_precision(self.local.decode(mu + eps * torch.exp(0.5 * logvar), ego_x, pair_x, graph.packer))
        target = graph.packer.rows(target_y) if target_y.dim() == 2 else graph.packer.pack(target_y[:, : graph.valid.shape[1]])
        recon = (y_hat - target).square().mean()
        kl = -0.5 * (1.0 + logvar - mu.square() - logvar.exp()).mean()
        return recon, kl, mu

    # ------------------------------------------------------------------ public API
    def q_values(
        self, obs: Tensor, state: Tensor, action: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """Global twin Q (q1, q2), each (B,), of ego action ``action`` given the others' states/actions."""
        graph = self._graph(state, action, others_state, others_action, others_mask)
        node_x, obs_x = self._q_nodes(*self._pairs(obs, state, action, graph), graph), torch.cat([obs, action], -1)
        return self.q1_branch(node_x, obs_x, graph), self.q2_branch(node_x, obs_x, graph)

    def q1(self, obs: Tensor, state: Tensor, action: Tensor, others_state: Tensor, others_action: Tensor, others_mask: Tensor) -> Tensor:
        """Global Q1 (B,) only (actor loss, Eq. 12)."""
        graph = self._graph(state, action, others_state, others_action, others_mask)
        return self.q1_branch(self._q_nodes(*self._pairs(obs, state, action, graph), graph), torch.cat([obs, action], -1), graph)

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
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor]:
        """CVAE terms of the negative ELBO (Eq. 3) over the valid pairs: (recon_mse, kl), both unweighted.

        ``target_y`` = [o'_i, s'_i, r_i] of the ego, shape (B, O+S+1) (the same target for every
        pair of the row) or (B, N+1, O+S+1) per pair. Valid pairs (b, j): node 0 and the others
        whose mask is True; padded pairs are never computed and contribute nothing. With P valid
        pairs, D = O+S+1, L = latent_dim:
        ``recon_mse = sum_{valid (b,j)} sum_d (y_hat - y)^2 / (P * D)`` and
        ``kl = -0.5 * sum_{valid (b,j)} sum_l (1 + logvar - mu^2 - exp(logvar)) / (P * L)``
        (means per element, no sum over dims). Both values are returned unweighted (for logging):
        the caller forms ``recon_mse + kl_beta * kl`` (``losses.central_critic_loss``).
        The decoder gets z = mu + eps * exp(logvar / 2) with eps ~ N(0, I) of shape (P, L), valid
        pairs in row-major (b, j) order, drawn from ``generator`` when given, else from the global
        torch RNG. Returns two zero scalars for the "attention" / "none" local modules.
        """
        if not isinstance(self.local, PairCVAE):
            return obs.new_zeros(()), obs.new_zeros(())
        graph = self._graph(state, action, others_state, others_action, others_mask)
        recon, kl, _ = self._elbo(*self._pairs(obs, state, action, graph), graph, target_y, generator)
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
        ego_x, pair_x = self._pairs(obs, state, action, graph)
        recon, kl, mu = obs.new_zeros(()), obs.new_zeros(()), None
        if isinstance(self.local, PairCVAE) and target_y is not None:
            recon, kl, mu = self._elbo(ego_x, pair_x, graph, target_y, generator)
        node_x, obs_x = self._q_nodes(ego_x, pair_x, graph, mu), torch.cat([obs, action], -1)
        q1 = self.q1_branch(node_x, obs_x, graph)
        q2 = self.q2_branch(node_x, obs_x, graph)
        return CriticOutputs(q1, q2, self._v(obs, graph), recon, kl)
