"""The networks of the TraCo baseline (Liu et al., CoRL 2023) as COIN ran it (COIN paper §5.2): TD3 with a domain critic.

COIN §5.2 describes TraCo as "a cross-attention mechanism to capture crucial information from nearby
vehicles" and "a counterfactual advantage function for credit assignment within a neighborhood range
of 40 meters". Neither TraCo's code nor its full text is public, so every structural detail below
(widths, heads, the null token, the neighbour token features, the default action) is an inference,
marked as such at its constructor argument.

* :func:`neighbourhood_mask`: the ego's domain, the valid others strictly within ``radius`` metres
  (CPPO's convention, ``ppo_family/neighbours.py``; positions = ``state[..., :2] * position_scale``).
* :class:`DomainAttention`: ego token ``e_i = MLP([o_i, a_i])``, neighbour tokens
  ``h_j = MLP([s_j - s_i, s_j, a_j])``, multi-head cross-attention (query from e_i, keys / values
  from a learned null token and the h_j of the domain), ``c_i = LayerNorm(e_i + Attn)``.
* :class:`DomainCritic`: the twin domain critic Q^D_k(o_i, a_i, domain) = MLP([e_i, c_i]), k = 1, 2.
* :class:`CounterfactualBaseline`: the same architecture with the ego action replaced by a constant
  default action (-1, -1), as COIN's released code does for its counterfactual baseline.
* :func:`counterfactual_advantage`: ``Q^D - b``.

Plain ``torch.nn``; nothing here imports Ray. Shapes: ``B`` batch rows, ``N`` padded other-agent
slots, ``O`` observation, ``S`` local state (``schema.STATE_DIM``), ``A`` action
(``schema.ACT_DIM``), ``H`` heads, ``F`` the model width ``hidden``. The columns are CIG-TD3's
(``td3/columns.py``): OBS (B, O), ACTIONS (B, A), STATE (B, S), OTHERS_STATE (B, N, S),
OTHERS_ACTIONS (B, N, A), OTHERS_MASK (B, N). Slots outside the domain (padded or far) are zeroed
(their s_j, a_j) on input and masked with -inf before the softmax, so their contents cannot change any output
(bit-identical) and their attention weight is exactly 0.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from coin_app.algorithms.choices import NEIGHBOUR_FEATURES
from coin_app.algorithms.masked_softmax import masked_softmax
from coin_app.algorithms.td3.networks import mlp
from coin_app.algorithms.traco.settings import TracoSettings
from coin_app.sim import schema

__all__ = [
    "DEFAULT_ACTION",
    "DOMAIN_RADIUS",
    "NEIGHBOUR_FEATURES",
    "CounterfactualBaseline",
    "DomainAttention",
    "DomainCritic",
    "compact_domain",
    "counterfactual_advantage",
    "neighbourhood_mask",
]

DOMAIN_RADIUS: float = TracoSettings.declarations()["domain_radius"].default  # metres: COIN §5.2 (declared in settings.py)
# Inference: COIN's released code replaces the ego's action by the constant -1 vector in its counterfactual V.
DEFAULT_ACTION = (-1.0, -1.0)


def neighbourhood_mask(state: Tensor, others_state: Tensor, others_mask: Tensor, radius: float, position_scale: float) -> Tensor:
    """The ego's domain (B, N) bool: valid others strictly within ``radius`` metres (positions = ``state[..., :2] * position_scale``)."""
    with torch.no_grad():
        dtype = torch.promote_types(state.dtype, torch.float32)  # bf16 positions are too coarse for a metre threshold
        ego = state[..., :2].to(dtype) * position_scale  # (B, 2)
        pos = others_state[..., :2].to(dtype) * position_scale  # (B, N, 2)
        d2 = (pos - ego.unsqueeze(1)).square().sum(-1)
        return others_mask.to(torch.bool) & (d2 < radius * radius)


def compact_domain(domain: Tensor, *slots: Tensor) -> tuple[Tensor, ...]:
    """The domain (B, N) and per-slot tensors (B, N, ...) cut to K = the largest domain in the batch (at least 1 slot).

    Each row's domain slots move to the front in their original order (a stable sort), the rest
    follow, and only the first K columns are kept: the attention is order-invariant and gives
    slots outside the domain zero weight, so every output is unchanged (up to the float
    summation order) while the token MLPs run on K instead of N slots.
    """
    k = max(1, int(domain.sum(-1).max()))
    order = torch.argsort((~domain.to(torch.bool)).to(torch.uint8), dim=-1, stable=True)[:, :k]  # (B, K)
    out = [torch.gather(domain, 1, order)]
    for t in slots:
        index = order.reshape(*order.shape, *([1] * (t.dim() - 2))).expand(-1, -1, *t.shape[2:])
        out.append(torch.gather(t, 1, index))
    return tuple(out)


def _check_positive_int(name: str, value: object) -> None:
    """Raise ValueError unless ``value`` is a positive int (not a bool)."""
    if not isinstance(value, int) or isinstance(value, bool) or value < 1:
        raise ValueError(f"bad value for {name!r}: {value!r}; allowed: an integer >= 1")


class DomainAttention(nn.Module):
    """Cross-attention of the ego token over a learned null token and its domain's neighbour tokens; returns (c_i, weights).

    ``hidden`` (F, 256 in COIN's TD3 settings) is the token and model width, split over ``heads``
    heads of width F / H; ``token_layers`` linear layers (ReLU between, linear output) build each
    token. The null token is one learned F-vector in the neighbour-token space, projected by the
    same key / value maps; it is always attendable, so an empty domain is defined and every
    attention row sums to 1 over {null} and the domain. Scaled dot-product scores per head,
    ``softmax`` over the masked logits (-inf outside the domain), heads concatenated and mixed by an
    output projection (Vaswani et al., 2017), then ``c_i = LayerNorm(e_i + Attn)``.
    """

    def __init__(
        self,
        obs_dim: int,
        state_dim: int = schema.STATE_DIM,
        act_dim: int = schema.ACT_DIM,
        hidden: int = 256,  # COIN's TD3 hidden size; the attention width itself is an inference
        heads: int = 4,  # inference (no TraCo code or full text is public)
        token_layers: int = 2,  # inference: 2-layer token MLPs
        neighbour_features: str = "relative+absolute",  # inference: [s_j - s_i, s_j, a_j], see NEIGHBOUR_FEATURES
        null_token: bool = True,  # inference: a learned, always attendable null token (False: a fixed zero token)
    ) -> None:
        super().__init__()
        for name, value in (("obs_dim", obs_dim), ("state_dim", state_dim), ("act_dim", act_dim), ("hidden", hidden)):
            _check_positive_int(name, value)
        _check_positive_int("heads", heads)
        _check_positive_int("token_layers", token_layers)
        if hidden % heads:
            raise ValueError(f"bad value for 'hidden': {hidden}; allowed: a multiple of heads={heads}")
        if neighbour_features not in NEIGHBOUR_FEATURES:
            raise ValueError(
                f"bad value for 'neighbour_features': {neighbour_features!r}; allowed: {', '.join(map(repr, NEIGHBOUR_FEATURES))}"
            )
        self.hidden, self.heads, self.head_dim = hidden, heads, hidden // heads
        self.neighbour_features = neighbour_features
        nbr_dim = (2 * state_dim if neighbour_features == "relative+absolute" else state_dim) + act_dim
        self.ego_mlp = mlp([obs_dim + act_dim] + [hidden] * token_layers, nn.ReLU)
        self.nbr_mlp = mlp([nbr_dim] + [hidden] * token_layers, nn.ReLU)
        # Starts as the zero token (the spec's alternative to a learned one); a parameter when null_token=True, else a fixed buffer.
        if null_token:
            self.null = nn.Parameter(torch.zeros(hidden))
        else:
            self.register_buffer("null", torch.zeros(hidden))
        self.query = nn.Linear(hidden, hidden)
        self.key = nn.Linear(hidden, hidden)
        self.value = nn.Linear(hidden, hidden)
        self.out = nn.Linear(hidden, hidden)
        self.norm = nn.LayerNorm(hidden)
        self.scale = 1.0 / math.sqrt(self.head_dim)

    def ego_token(self, obs: Tensor, actions: Tensor) -> Tensor:
        """e_i = MLP([o_i, a_i]): obs (B, O), actions (B, A) -> (B, F)."""
        return self.ego_mlp(torch.cat([obs, actions], -1))

    def neighbour_tokens(self, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor) -> Tensor:
        """h_j = MLP(features of s_j, s_i, a_j) for every slot, (B, N, F); s_j, a_j of slots outside the domain are zeroed first."""
        m = nbr_mask.to(torch.bool).unsqueeze(-1)
        s_j = torch.where(m, others_state, 0.0)
        a_j = torch.where(m, others_actions, 0.0)
        rel = s_j - state.unsqueeze(1)
        if self.neighbour_features == "relative+absolute":
            x = torch.cat([rel, s_j, a_j], -1)
        elif self.neighbour_features == "absolute":
            x = torch.cat([s_j, a_j], -1)
        else:
            x = torch.cat([rel, a_j], -1)
        return self.nbr_mlp(x)

    def attend(self, ego: Tensor, nbr: Tensor, nbr_mask: Tensor) -> tuple[Tensor, Tensor]:
        """Ego token (B, F), neighbour tokens (B, N, F), domain (B, N) -> (c_i (B, F), weights (B, H, 1+N), null first)."""
        b, n = nbr.shape[:2]
        hh, d = self.heads, self.head_dim
        tokens = torch.cat([self.null.to(nbr.dtype).expand(b, 1, self.hidden), nbr], 1)  # (B, 1+N, F)
        q = self.query(ego).view(b, hh, d)
        k = self.key(tokens).view(b, n + 1, hh, d)
        v = self.value(tokens).view(b, n + 1, hh, d)
        keep = torch.cat([torch.ones(b, 1, dtype=torch.bool, device=nbr.device), nbr_mask.to(torch.bool)], 1)  # (B, 1+N)
        logits = (k.transpose(1, 2) @ q.unsqueeze(-1)).squeeze(-1) * self.scale  # (B, H, 1+N): q . k per head
        weights = masked_softmax(logits, keep.unsqueeze(1))  # exactly 0 outside
        attn = (weights.unsqueeze(2) @ v.transpose(1, 2)).reshape(b, self.hidden)  # (B, H, 1, D) -> (B, F)
        return self.norm(ego + self.out(attn)), weights

    def forward(
        self, obs: Tensor, actions: Tensor, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(context c_i (B, F), attention weights (B, H, 1+N) with the null token first)."""
        ego = self.ego_token(obs, actions)
        return self.attend(ego, self.neighbour_tokens(state, others_state, others_actions, nbr_mask), nbr_mask)


class _DomainQ(nn.Module):
    """One domain critic: a :class:`DomainAttention` and the head MLP([e_i, c_i]) -> 1."""

    def __init__(self, obs_dim: int, state_dim: int, act_dim: int, hidden: int, head_hidden: Sequence[int], **attention: Any) -> None:
        super().__init__()
        self.attention = DomainAttention(obs_dim, state_dim, act_dim, hidden, **attention)
        self.head = mlp([2 * hidden, *head_hidden, 1], nn.ReLU)

    def forward(
        self, obs: Tensor, actions: Tensor, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(q (B,), attention weights (B, H, 1+N))."""
        att = self.attention
        ego = att.ego_token(obs, actions)
        context, weights = att.attend(ego, att.neighbour_tokens(state, others_state, others_actions, nbr_mask), nbr_mask)
        return self.head(torch.cat([ego, context], -1)).squeeze(-1), weights


class DomainCritic(nn.Module):
    """Twin domain ("coordinator") critic Q^D_1, Q^D_2, each with its own attention and head (no shared tensors).

    ``head_hidden`` hidden widths of the head MLP([e_i, c_i]) -> 1 (default ``(hidden, hidden)``,
    i.e. 2F -> F -> F -> 1, an inference); the remaining keyword arguments go to
    :class:`DomainAttention` (``heads``, ``token_layers``, ``neighbour_features``, ``null_token``).
    """

    def __init__(
        self,
        obs_dim: int,
        state_dim: int = schema.STATE_DIM,
        act_dim: int = schema.ACT_DIM,
        hidden: int = 256,
        head_hidden: Sequence[int] | None = None,  # inference: (hidden, hidden)
        **attention: Any,
    ) -> None:
        super().__init__()
        head = tuple(head_hidden) if head_hidden is not None else (hidden, hidden)
        self.q1 = _DomainQ(obs_dim, state_dim, act_dim, hidden, head, **attention)
        self.q2 = _DomainQ(obs_dim, state_dim, act_dim, hidden, head, **attention)

    def forward(
        self, obs: Tensor, actions: Tensor, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor
    ) -> tuple[Tensor, Tensor]:
        """(q1, q2), each of shape (B,)."""
        args = (obs, actions, state, others_state, others_actions, nbr_mask)
        return self.q1(*args)[0], self.q2(*args)[0]

    def q1_only(
        self, obs: Tensor, actions: Tensor, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor
    ) -> Tensor:
        """Q^D_1 of shape (B,) (actor loss: the policy's action enters the ego token, hence the attention query)."""
        return self.q1(obs, actions, state, others_state, others_actions, nbr_mask)[0]


class CounterfactualBaseline(nn.Module):
    """Counterfactual baseline b(o_i, domain): one domain-critic copy evaluated with the ego action set to ``default_action``.

    ``default_action`` (-1, -1) follows COIN's released code (its counterfactual V replaces the ego's
    action by the constant -1 vector); for TraCo it is an inference. Other arguments as
    :class:`DomainCritic`.
    """

    def __init__(
        self,
        obs_dim: int,
        state_dim: int = schema.STATE_DIM,
        act_dim: int = schema.ACT_DIM,
        hidden: int = 256,
        head_hidden: Sequence[int] | None = None,  # inference: (hidden, hidden)
        default_action: Sequence[float] = DEFAULT_ACTION,  # inference: COIN's released-code convention
        **attention: Any,
    ) -> None:
        super().__init__()
        if len(default_action) != act_dim:
            raise ValueError(f"bad value for 'default_action': {tuple(default_action)!r}; allowed: {act_dim} numbers (act_dim)")
        head = tuple(head_hidden) if head_hidden is not None else (hidden, hidden)
        self.net = _DomainQ(obs_dim, state_dim, act_dim, hidden, head, **attention)
        self.register_buffer("default_action", torch.tensor([float(a) for a in default_action]), persistent=False)

    def forward(self, obs: Tensor, state: Tensor, others_state: Tensor, others_actions: Tensor, nbr_mask: Tensor) -> Tensor:
        """b of shape (B,); it does not depend on the ego's action."""
        actions = self.default_action.to(obs.dtype).expand(obs.shape[0], -1)
        return self.net(obs, actions, state, others_state, others_actions, nbr_mask)[0]


def counterfactual_advantage(q: Tensor, baseline: Tensor) -> Tensor:
    """A^cf = Q^D - b (same shapes); gradient-neutral for a deterministic policy gradient, so it is logged for diagnosis.

    In the actor loss ``-(Q^D_1(o, mu(o), .) - b.detach())`` the baseline does not depend on the ego
    action, so it contributes no gradient to the policy (as COIN's Eq. 12); the subtraction is kept
    for fidelity with COIN and the advantage is logged to diagnose the critic and the baseline.
    """
    if q.shape != baseline.shape:
        raise ValueError(f"q {tuple(q.shape)} and baseline {tuple(baseline.shape)} must have the same shape")
    return q - baseline
