"""What every export format stores of an actor: its observation size, metadata, and its MLP layers.

An exported actor is a plain MLP: linear layers, each followed by one activation named
``relu`` | ``tanh`` | ``leaky_relu`` (slope 0.01) | ``clip`` (to [-1, 1]) | ``identity``.
:func:`mlp_layers` reads that list off a torch ``nn.Sequential`` (the only function here
that needs torch); :class:`ExportedPolicy` is the common interface of the loaded files.
"""

from __future__ import annotations

from typing import Any

import numpy as np

ACTIVATIONS = ("relu", "tanh", "leaky_relu", "identity", "clip")


class ExportedPolicy:
    """A loaded actor file: ``policy(obs)`` maps observations (N, obs_dim) to actions (N, act_dim) as float32."""

    format_name = "?"

    def __init__(self, obs_dim: int, meta: dict[str, Any] | None = None):
        self._obs_dim = int(obs_dim)
        self.meta = dict(meta or {})

    @property
    def obs_dim(self) -> int:
        """Observation size the actor expects."""
        return self._obs_dim

    def batch(self, obs: np.ndarray) -> np.ndarray:
        """``obs`` as a contiguous float32 (N, obs_dim) array; a ValueError naming a bad shape or a non-finite number.

        Every format refuses NaN and inf (one check, here): the actions of such an observation would be NaN or
        arbitrary, and a vehicle would drive on them. The refusal names the first row and column.
        """
        x = np.ascontiguousarray(obs, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.obs_dim:
            raise ValueError(f"observations must have shape (N, {self.obs_dim}), got {x.shape}")
        finite = np.isfinite(x)
        if not finite.all():
            row, col = (int(i[0]) for i in np.nonzero(~finite))
            count = int((~finite).any(axis=1).sum())
            raise ValueError(
                f"observation row {row} holds {x[row, col]} at index {col} ({count} row(s) non-finite); allowed: finite numbers"
            )
        return x

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, act_dim) for observations (N, obs_dim)."""
        raise NotImplementedError

    def __repr__(self) -> str:
        return f"{type(self).__name__}(format={self.format_name}, obs_dim={self.obs_dim}, meta={self.meta})"


def mlp_layers(module: Any) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Weights (out, in), biases and activation names of a torch MLP (``nn.Sequential`` of Linear and activations)."""
    from torch import nn  # optional: inference stays importable without torch (numpy and ONNX policies need none)

    seq = module if isinstance(module, nn.Sequential) else next((m for m in module.modules() if isinstance(m, nn.Sequential)), None)
    if seq is None:
        raise ValueError(f"cannot export {type(module).__name__}: no nn.Sequential MLP inside")
    names = {nn.ReLU: "relu", nn.Tanh: "tanh", nn.LeakyReLU: "leaky_relu", nn.Identity: "identity", nn.Hardtanh: "clip"}
    weights, biases, acts = [], [], []
    for layer in seq:
        if isinstance(layer, nn.Linear):
            weights.append(layer.weight.detach().cpu().numpy())
            biases.append(layer.bias.detach().cpu().numpy())
            acts.append("identity")
        elif type(layer) in names and weights:
            if type(layer) is nn.LeakyReLU and layer.negative_slope != 0.01:
                raise ValueError(f"LeakyReLU slope {layer.negative_slope} not supported; allowed: 0.01")
            if type(layer) is nn.Hardtanh and (layer.min_val, layer.max_val) != (-1.0, 1.0):
                raise ValueError(f"Hardtanh bounds ({layer.min_val}, {layer.max_val}) not supported; allowed: (-1, 1)")
            acts[-1] = names[type(layer)]
        else:
            raise ValueError(f"cannot export layer {layer!r}; allowed: Linear, ReLU, Tanh, LeakyReLU(0.01), Hardtanh(-1, 1), Identity")
    return weights, biases, acts


def check_layers(weights: list[np.ndarray], biases: list[np.ndarray], activations: list[str]) -> None:
    """A ValueError unless the layers chain (one weight, bias and known activation each; matching sizes)."""
    if not (len(weights) == len(biases) == len(activations) >= 1):
        raise ValueError(f"need one weight, bias and activation per layer, got {len(weights)}, {len(biases)}, {len(activations)}")
    bad = [a for a in activations if a not in ACTIVATIONS]
    if bad:
        raise ValueError(f"unknown activation(s) {bad}; allowed: {', '.join(ACTIVATIONS)}")
    for k in range(1, len(weights)):
        if weights[k].shape[1] != weights[k - 1].shape[0]:
            raise ValueError(f"layer {k} expects {weights[k].shape[1]} inputs but layer {k - 1} gives {weights[k - 1].shape[0]}")
