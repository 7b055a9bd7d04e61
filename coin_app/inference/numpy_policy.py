"""The numpy export format: an actor MLP as plain ``.npz`` weights and a numpy forward pass.

File layout (``np.savez``): ``format`` = ``"coin_app.numpy_mlp.v1"``, ``activations`` = one
name per layer (``relu`` | ``tanh`` | ``leaky_relu`` | ``clip`` (to [-1, 1]) | ``identity``), ``W<k>`` (out, in) and
``b<k>`` (out,) for each linear layer k, and optional ``meta`` (a JSON string: algorithm,
scenario, observation size). Loading needs only numpy: no torch, no Ray.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

FORMAT = "coin_app.numpy_mlp.v1"
_ACTIVATIONS = {
    "relu": lambda x: np.maximum(x, 0.0),
    "tanh": np.tanh,
    "leaky_relu": lambda x: np.where(x > 0, x, 0.01 * x),
    "identity": lambda x: x,
    "clip": lambda x: np.clip(x, -1.0, 1.0),
}


class NumpyPolicy:
    """A deterministic actor ``(N, obs_dim) -> (N, act_dim)`` evaluated with numpy (float32)."""

    def __init__(self, weights: list[np.ndarray], biases: list[np.ndarray], activations: list[str], meta: dict[str, Any] | None = None):
        if not (len(weights) == len(biases) == len(activations) >= 1):
            raise ValueError(f"need one weight, bias and activation per layer, got {len(weights)}, {len(biases)}, {len(activations)}")
        bad = [a for a in activations if a not in _ACTIVATIONS]
        if bad:
            raise ValueError(f"unknown activation(s) {bad}; allowed: {', '.join(_ACTIVATIONS)}")
        for k in range(1, len(weights)):
            if weights[k].shape[1] != weights[k - 1].shape[0]:
                raise ValueError(f"layer {k} expects {weights[k].shape[1]} inputs but layer {k - 1} gives {weights[k - 1].shape[0]}")
        self.weights = [np.ascontiguousarray(w.T, dtype=np.float32) for w in weights]  # (in, out) for x @ W
        self.biases = [np.asarray(b, dtype=np.float32) for b in biases]
        self.activations = list(activations)
        self.meta = dict(meta or {})

    @property
    def obs_dim(self) -> int:
        """Observation size the actor expects."""
        return int(self.weights[0].shape[0])

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, act_dim) for observations (N, obs_dim)."""
        x = np.asarray(obs, dtype=np.float32)
        if x.ndim != 2 or x.shape[1] != self.obs_dim:
            raise ValueError(f"observations must have shape (N, {self.obs_dim}), got {x.shape}")
        for w, b, act in zip(self.weights, self.biases, self.activations):
            x = _ACTIVATIONS[act](x @ w + b)
        return x


def _layers(module: Any) -> tuple[list[np.ndarray], list[np.ndarray], list[str]]:
    """Weights, biases and activations of a torch MLP (``nn.Sequential`` of Linear and activation modules)."""
    from torch import nn

    seq = next((m for m in module.modules() if isinstance(m, nn.Sequential)), None)
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


def export_numpy(actor: Any, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write a torch actor MLP to ``path`` in the numpy format; returns the path."""
    weights, biases, acts = _layers(actor)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"W{k}": w for k, w in enumerate(weights)} | {f"b{k}": b for k, b in enumerate(biases)}
    with open(path, "wb") as f:  # a file object keeps np.savez from appending ".npz"
        np.savez(f, format=np.array(FORMAT), activations=np.array(acts), meta=np.array(json.dumps(meta or {})), **arrays)
    return path


def load_policy(path: str | Path) -> Any:
    """Load an exported actor file (``.npz``) or a switching pair of them (``.json``) as a callable policy (numpy only)."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"policy file {path} does not exist")
    if path.suffix == ".json":
        from coin_app.inference.switching import load_pair

        return load_pair(path, load_policy)
    try:
        data = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as exc:
        raise ValueError(f"{path} is not a coin_app numpy policy file (.npz): {exc}") from exc
    with data:
        if "format" not in data or str(data["format"]) != FORMAT:
            raise ValueError(f"{path} is not a coin_app numpy policy file (format {FORMAT!r} expected)")
        n = len(data["activations"])
        return NumpyPolicy(
            [data[f"W{k}"] for k in range(n)],
            [data[f"b{k}"] for k in range(n)],
            [str(a) for a in data["activations"]],
            json.loads(str(data["meta"])),
        )
