"""The TD3 family's networks (COIN §4.2's individual networks): the actor, the individual twin critic, and the MLP builder.

* :class:`Actor`: the deterministic shared policy mu_theta(o_i), tanh output in [-1, 1] (Eq. 12).
* :class:`TwinQ`: the individual (local) twin critic Q^l_1, Q^l_2 on ``[o_i, a_i]`` (Eqs. 7-8): ITD3's
  only critic, CIG-TD3's local critic, TraCo's optional individual critic.
* :func:`mlp`: the plain MLP every TD3-family network is built from.
* :func:`full_precision`: a network output widened to fp32 (under bf16 autocast the networks return bf16).

Plain ``torch.nn``; nothing here imports Ray. Shapes: ``B`` batch rows, ``O`` observation,
``A`` action (``schema.ACT_DIM``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn
from torch.nn import functional as F

from coin_app.sim import schema

__all__ = ["Actor", "TwinQ", "full_precision", "mlp", "q_head"]

FEATURE_NORM_EPS = 1e-6  # floor of the penultimate features' L2 norm in q_head (an all-zero ReLU layer stays finite)


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


def full_precision(x: Tensor) -> Tensor:
    """``x`` as fp32 when it is a narrower float (bf16 / fp16 under autocast); fp32 and fp64 tensors unchanged."""
    return x.to(torch.promote_types(x.dtype, torch.float32))


def q_head(features: Tensor, head: nn.Module, feature_norm: bool) -> Tensor:
    """``head(features)``, the features first divided by their L2 norm when ``feature_norm`` (Bjorck et al., 2022)."""
    if feature_norm:
        features = F.normalize(features, dim=-1, eps=FEATURE_NORM_EPS)
    return head(features)


class Actor(nn.Module):
    """Deterministic policy mu_theta(o): MLP with ReLU, tanh output in [-1, 1]."""

    def __init__(self, obs_dim: int, act_dim: int = schema.ACT_DIM, hidden: Sequence[int] = (256, 256)) -> None:
        super().__init__()
        self.net = mlp([obs_dim, *hidden, act_dim], nn.ReLU, nn.Tanh)

    def forward(self, obs: Tensor) -> Tensor:
        """Action (B, act_dim) in [-1, 1] for observations (B, obs_dim)."""
        return self.net(obs)

    def preactivation(self, obs: Tensor) -> Tensor:
        """The output before the final tanh, (B, act_dim): ``forward(obs) == tanh(preactivation(obs))``."""
        return self.net[:-1](obs)


class TwinQ(nn.Module):
    """Local (individual) twin critic Q^l_1, Q^l_2 on [o, a] (paper Eqs. 7-8).

    ``feature_norm``: the last hidden layer's features are divided by their L2 norm before the
    output layer (the penultimate normalization of Bjorck et al., 2022, "Is high variance
    unavoidable in RL?"; not in COIN). The parameters are the same either way.
    """

    def __init__(self, obs_dim: int, act_dim: int = schema.ACT_DIM, hidden: Sequence[int] = (256, 256), feature_norm: bool = False) -> None:
        super().__init__()
        self.feature_norm = feature_norm
        self.q1_net = mlp([obs_dim + act_dim, *hidden, 1], nn.ReLU)
        self.q2_net = mlp([obs_dim + act_dim, *hidden, 1], nn.ReLU)

    def _q(self, net: nn.Sequential, x: Tensor) -> Tensor:
        """One critic's value (B,) for inputs x (B, O+A)."""
        if not self.feature_norm:
            return net(x).squeeze(-1)
        return q_head(net[:-1](x), net[-1], True).squeeze(-1)

    def forward(self, obs: Tensor, act: Tensor) -> tuple[Tensor, Tensor]:
        """(q1, q2), each of shape (B,)."""
        x = torch.cat([obs, act], -1)
        return self._q(self.q1_net, x), self._q(self.q2_net, x)

    def q1_only(self, obs: Tensor, act: Tensor) -> Tensor:
        """Q1 of shape (B,) (actor loss)."""
        return self._q(self.q1_net, torch.cat([obs, act], -1))
