"""The numpy export format: an actor MLP as plain ``.npz`` weights and a numpy forward pass.

File layout (``np.savez``): ``format`` = ``"coin_app.numpy_mlp.v1"``, ``activations`` = one
name per layer (see :mod:`coin_app.inference.layers`), ``W<k>`` (out, in) and ``b<k>`` (out,)
for each linear layer k, and ``meta`` (a JSON string: algorithm, scenario, seed, env config).
Loading needs only numpy: no torch, no Ray.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.inference.layers import ExportedPolicy, check_layers, mlp_layers

FORMAT = "coin_app.numpy_mlp.v1"
_ACTIVATIONS = {
    "relu": lambda x: np.maximum(x, 0.0),
    "tanh": np.tanh,
    "leaky_relu": lambda x: np.where(x > 0, x, 0.01 * x),
    "identity": lambda x: x,
    "clip": lambda x: np.clip(x, -1.0, 1.0),
}


class NumpyPolicy(ExportedPolicy):
    """A deterministic actor ``(N, obs_dim) -> (N, act_dim)`` evaluated with numpy (float32)."""

    format_name = "numpy"

    def __init__(self, weights: list[np.ndarray], biases: list[np.ndarray], activations: list[str], meta: dict[str, Any] | None = None):
        check_layers(weights, biases, activations)
        super().__init__(weights[0].shape[1], meta)
        self.weights = [np.ascontiguousarray(w.T, dtype=np.float32) for w in weights]  # (in, out) for x @ W
        self.biases = [np.asarray(b, dtype=np.float32) for b in biases]
        self.activations = list(activations)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, act_dim) for observations (N, obs_dim)."""
        x = self.batch(obs)
        for w, b, act in zip(self.weights, self.biases, self.activations):
            x = _ACTIVATIONS[act](x @ w + b)
        return x


def export_numpy(actor: Any, path: str | Path, meta: dict[str, Any] | None = None) -> Path:
    """Write a torch actor MLP to ``path`` in the numpy format; returns the path."""
    weights, biases, acts = mlp_layers(actor)
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {f"W{k}": w for k, w in enumerate(weights)} | {f"b{k}": b for k, b in enumerate(biases)}
    with open(path, "wb") as f:  # a file object keeps np.savez from appending ".npz"
        np.savez(f, format=np.array(FORMAT), activations=np.array(acts), meta=np.array(json.dumps(meta or {})), **arrays)
    return path


def load_numpy(path: str | Path) -> NumpyPolicy:
    """Load a numpy-format actor file (``.npz``)."""
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
