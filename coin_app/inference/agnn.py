"""The A-GNN baseline (Ma, Khan, Cremers, ITSC 2023) with its released weights, and its adapter to the arena.

One graph per scenario. Vehicles and obstacles are nodes with 8 features in world coordinates:

    vehicle   [x, y, psi, v, x_d, y_d, psi_d, 0]   (pose, speed, target pose)
    obstacle  [x, y, 0, 0, x, y, 0, r]             (centre twice, radius last: the non-zero mark)

Edges go from every vehicle to every other vehicle and from every obstacle to every vehicle, so
obstacles receive no messages. The network (the paper's Fig. 2 and supplementary §A; the layer
sizes are read off the tensor shapes of the released file, ``weights/agnn/README.md``):

* ``block0``: Linear 8→80, BatchNorm, ReLU;
* ``block1`` and ``block2``: residual blocks ``relu(bn2(conv2(relu(bn1(conv1(x))))) + x)`` of two
  U-attention convolutions, 80→160 and 160→80;
* ``block3``: Linear 80→2, BatchNorm, tanh; times the bounds [1, 0.8]: (pedal m/s², steering rad).

A U-attention convolution with ``in`` → ``out`` channels (supplementary Eqs. 9–13): each edge j→i
gets ``e = [x_i, x_j - x_i]`` (2·in). A U-Net (encoder 2·in → out/2 → out; two decoders, each
out → half → [·, encoder's first output] → full, the last layer without ReLU) gives the key
(2·in) and the value (out). The query is BatchNorm(e). Then
``alpha = softmax over the edges into i of (query · key) / sqrt(out)`` and
``out_i = sum_j alpha_ij value_ij + W_skip x_i + b_skip``. The key's latent width equals ``out``
(160 and 80 in the released file), and the dot product is scaled by its square root.

It runs in eval mode (the BatchNorm layers use their running statistics), on torch only: no Ray.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

WEIGHTS = Path(__file__).resolve().parent / "weights" / "agnn" / "IterGNN_UAttentionConv.pth"
PARAMETERS = 473_846  # trainable parameters of the released file (the seed paper's "474k")
NODE_DIM = 8
HIDDEN, WIDE = 80, 160
BOUND = (1.0, 0.8)  # |pedal| <= 1 m/s², |steering| <= 0.8 rad (the A-GNN's output scale)
DT = 0.2  # s, the A-GNN's simulator step
# the arena settings of the A-GNN's own simulator (config.py: update_order)
ARENA_PHYSICS: dict[str, Any] = {"dt": DT, "update_order": "position_first"}


class LinearBN(nn.Module):
    """Linear layer, BatchNorm, then ``activation`` ("relu", "tanh" or "none")."""

    def __init__(self, n_in: int, n_out: int, activation: str = "relu"):
        super().__init__()
        if activation not in ("relu", "tanh", "none"):
            raise ValueError(f"bad activation {activation!r}; allowed: relu, tanh, none")
        self.linear = nn.Linear(n_in, n_out)
        self.bn = nn.BatchNorm1d(n_out)
        self.activation = activation

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """(E, n_in) -> (E, n_out)."""
        x = self.bn(self.linear(x))
        if self.activation == "relu":
            return torch.relu(x)
        return torch.tanh(x) if self.activation == "tanh" else x


class UNet(nn.Module):
    """Shared encoder and two decoders with a skip from the encoder's first layer: (key, value) of an edge input."""

    def __init__(self, n_in: int, n_out: int, latent: int):
        super().__init__()
        half = latent // 2
        self.encoder_layer1 = LinearBN(n_in, half)
        self.encoder_layer2 = LinearBN(half, latent)
        self.decoder1_layer2 = LinearBN(latent, n_in // 2)
        self.decoder1_layer1 = LinearBN(n_in // 2 + half, n_in, "none")
        self.decoder2_layer2 = LinearBN(latent, n_out // 2)
        self.decoder2_layer1 = LinearBN(n_out // 2 + half, n_out, "none")

    def forward(self, e: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Key (E, n_in) and value (E, n_out) of edge inputs (E, n_in)."""
        h1 = self.encoder_layer1(e)
        z = self.encoder_layer2(h1)
        key = self.decoder1_layer1(torch.cat([self.decoder1_layer2(z), h1], dim=-1))
        value = self.decoder2_layer1(torch.cat([self.decoder2_layer2(z), h1], dim=-1))
        return key, value


def edge_softmax(logits: torch.Tensor, dst: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """Softmax (E,) of edge ``logits`` over the edges that share a destination node."""
    top = torch.full((num_nodes,), -torch.inf, dtype=logits.dtype).scatter_reduce(0, dst, logits, "amax")
    e = torch.exp(logits - top[dst])
    total = torch.zeros(num_nodes, dtype=logits.dtype).index_add_(0, dst, e)
    return e / total[dst]


class UAttentionConv(nn.Module):
    """The U-attention graph convolution (see module doc): attention-weighted U-Net values plus a linear skip."""

    def __init__(self, n_in: int, n_out: int):
        super().__init__()
        self.n_out = n_out
        self.unet = UNet(2 * n_in, n_out, latent=n_out)
        self.query_bn = nn.BatchNorm1d(2 * n_in)
        self.lin_skip = nn.Linear(n_in, n_out)

    def forward(self, x: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
        """Node features (N, n_in) and edges src -> dst (E,) each -> (N, n_out)."""
        out = self.lin_skip(x)
        if len(src) == 0:
            return out
        e = torch.cat([x[dst], x[src] - x[dst]], dim=-1)
        key, value = self.unet(e)
        logits = (self.query_bn(e) * key).sum(-1) / self.n_out**0.5
        alpha = edge_softmax(logits, dst, len(x))
        return out.index_add(0, dst, alpha[:, None] * value)


class ConvResidualBlock(nn.Module):
    """``relu(bn2(conv2(relu(bn1(conv1(x))))) + x)`` with two U-attention convolutions."""

    def __init__(self, width: int, hidden: int):
        super().__init__()
        self.conv1 = UAttentionConv(width, hidden)
        self.bn1 = nn.BatchNorm1d(hidden)
        self.conv2 = UAttentionConv(hidden, width)
        self.bn2 = nn.BatchNorm1d(width)

    def forward(self, x: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
        """(N, width) -> (N, width)."""
        h = torch.relu(self.bn1(self.conv1(x, src, dst)))
        return torch.relu(self.bn2(self.conv2(h, src, dst)) + x)


class AGNN(nn.Module):
    """The A-GNN controller: node features (N, 8) and edges -> (pedal, steering angle) (N, 2) of every node."""

    def __init__(self) -> None:
        super().__init__()
        self.block0 = LinearBN(NODE_DIM, HIDDEN)
        self.block1 = ConvResidualBlock(HIDDEN, WIDE)
        self.block2 = ConvResidualBlock(HIDDEN, WIDE)
        self.block3 = LinearBN(HIDDEN, 2, "tanh")
        self.register_buffer("bound", torch.tensor(BOUND), persistent=False)

    def forward(self, x: torch.Tensor, src: torch.Tensor, dst: torch.Tensor) -> torch.Tensor:
        """Controls (N, 2) = (pedal m/s², steering rad) for node features (N, 8) and edges src -> dst."""
        h = self.block0(x)
        h = self.block1(h, src, dst)
        h = self.block2(h, src, dst)
        return self.block3(h) * self.bound


def graph_edges(num_vehicles: int, num_obstacles: int) -> tuple[torch.Tensor, torch.Tensor]:
    """(src, dst) of every vehicle -> other vehicle edge and every obstacle -> vehicle edge (vehicles first, then obstacles)."""
    v = torch.arange(num_vehicles)
    src, dst = (t.reshape(-1) for t in torch.meshgrid(v, v, indexing="ij"))
    keep = src != dst
    obs_src = (num_vehicles + torch.arange(num_obstacles)).repeat(num_vehicles)
    obs_dst = v.repeat_interleave(num_obstacles)
    return torch.cat([src[keep], obs_src]), torch.cat([dst[keep], obs_dst])


def node_features(pos: np.ndarray, heading: np.ndarray, speed: np.ndarray, targets: np.ndarray, obstacles: np.ndarray) -> torch.Tensor:
    """Node features (N + M, 8): vehicles [x, y, psi, v, x_d, y_d, psi_d, 0], then obstacles [x, y, 0, 0, x, y, 0, r]."""
    pos, targets, obstacles = np.asarray(pos, float), np.asarray(targets, float), np.asarray(obstacles, float).reshape(-1, 3)
    n, m = len(pos), len(obstacles)
    if pos.shape != (n, 2) or targets.shape != (n, 3) or np.shape(heading) != (n,) or np.shape(speed) != (n,):
        raise ValueError(
            f"bad A-GNN state shapes pos {pos.shape}, heading {np.shape(heading)}, speed {np.shape(speed)}, targets {targets.shape}; "
            "allowed: (N, 2), (N,), (N,), (N, 3)"
        )
    x = np.zeros((n + m, NODE_DIM), np.float32)
    x[:n, 0:2] = pos
    x[:n, 2] = heading
    x[:n, 3] = speed
    x[:n, 4:7] = targets
    x[n:, 0:2] = obstacles[:, :2]
    x[n:, 4:6] = obstacles[:, :2]
    x[n:, 7] = obstacles[:, 2]
    return torch.from_numpy(x)


def load_agnn(path: str | Path = WEIGHTS) -> AGNN:
    """The A-GNN in eval mode with the state dict of ``path`` loaded exactly (every key, every shape), or one-line ValueError."""
    path = Path(path)
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # a missing file, a pickle of something else, a truncated file
        first = (str(exc).splitlines() or [""])[0]
        raise ValueError(f"{path}: not a readable A-GNN state dict ({type(exc).__name__}: {first})") from None
    if not isinstance(state, Mapping):
        raise ValueError(f"{path}: not an A-GNN state dict (a {type(state).__name__}, a mapping of names to tensors expected)")
    model = AGNN()
    want = model.state_dict()
    for key, tensor in want.items():
        if key not in state:
            raise ValueError(f"{path}: not the A-GNN checkpoint: missing key {key!r}")
        got = state[key]
        if not isinstance(got, torch.Tensor) or tuple(got.shape) != tuple(tensor.shape):
            shape = tuple(got.shape) if isinstance(got, torch.Tensor) else type(got).__name__
            raise ValueError(f"{path}: not the A-GNN checkpoint: key {key!r} has shape {shape}, expected {tuple(tensor.shape)}")
    for key in state:
        if key not in want:
            raise ValueError(f"{path}: not the A-GNN checkpoint: unexpected key {key!r}")
    model.load_state_dict(state, strict=True)
    return model.eval()


class AgnnArenaPolicy:
    """The A-GNN driving every arena vehicle from the world state (it reads the simulator, not the ego observations)."""

    def __init__(self, model: AGNN | None = None, path: str | Path = WEIGHTS):
        self.model = (model if model is not None else load_agnn(path)).eval()
        self.arena_overrides = dict(ARENA_PHYSICS)  # the suite runs it in the physics it was trained on
        self.meta = {"scenario": "arena", "policy": "agnn", "weights": "a given model" if model is not None else str(path)}
        self._edges: dict[tuple[int, int], tuple[torch.Tensor, torch.Tensor]] = {}

    def controls(self, pos: np.ndarray, heading: np.ndarray, speed: np.ndarray, targets: np.ndarray, obstacles: np.ndarray) -> np.ndarray:
        """The A-GNN's (pedal m/s², steering rad) (N, 2) for N vehicles and M obstacles (x, y, r) in world coordinates."""
        x = node_features(pos, heading, speed, targets, obstacles)
        n = len(pos)
        key = (n, len(x) - n)
        if key not in self._edges:
            self._edges[key] = graph_edges(*key)
        with torch.inference_mode():
            return self.model(x, *self._edges[key])[:n].numpy()

    def from_sim(self, sim: Any) -> np.ndarray:
        """Arena actions (steering, pedal) in [-1, 1] (N, 2) of every vehicle of an ``ArenaSimulator`` (parked ones included)."""
        cfg = sim.config
        u = self.controls(sim.pos, sim.heading, sim.speed, sim.layout.targets, sim.layout.obstacles)
        # the arena scales its actions by max_steer and max_pedal (simulator.py); the A-GNN's are in rad and m/s²
        return np.clip(np.stack([u[:, 1] / cfg.max_steer, u[:, 0] / cfg.max_pedal], axis=1), -1.0, 1.0)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Refused: the A-GNN needs the world state (every pose, target and obstacle), which ego observations do not hold."""
        raise TypeError("the A-GNN acts on the world state, not on observations; run it with: python -m coin_app evaluate-arena agnn")
