"""Where a trained CIG-TD3 critic's GAT looks: the attention of the ego over its neighbours along evaluation episodes.

The model drives deterministically on the given seeds (one batched simulator). At every env step
each acting vehicle is the ego, every other acting vehicle of its episode a node of its graph,
with the states and actions the critic reads in training (COIN Eqs. 4-6: node 0 the ego, the
others with their local states and this step's actions). The attention read is the second GAT
layer's ego row of the Q1 branch (the one the actor's loss differentiates): ``alpha_0j`` over the
ego's neighbourhood (itself included, within ``graph_radius`` when the model has one). A
neighbour's **share** is ``alpha_0j`` times the neighbourhood's size: 1 is what a uniform
attention gives it.

A **crossing conflict** (:func:`crossing_conflict`) is a pair whose headings cross at 30 degrees or
more and whose straight paths meet ahead of both, each reaching the meeting point within
``horizon_s`` and within ``gap_s`` of the other (the post-encroachment time of traffic-conflict
studies, speeds floored at 1 m/s). Each row of :attr:`AttentionSample.edges` is one (ego,
neighbour) edge at one step.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from coin_app.algorithms.checkpoints import load_module, scenario_of
from coin_app.algorithms.cig_td3.graph import GraphModule
from coin_app.sim.rollout import BatchedEnvs, rollout
from coin_app.sim.simulator import DrivingSimulator

MIN_CROSSING_DEG = 30.0
EDGE_COLUMNS = ("seed", "env_step", "ego", "other", "distance", "alpha", "share", "degree", "conflict")


@dataclass
class AttentionSample:
    """Every (ego, neighbour) edge with its attention (``EDGE_COLUMNS``), one conflict's scene (``snapshot``, or None), the map."""

    edges: pd.DataFrame
    snapshot: dict[str, Any] | None
    road_map: Any


def crossing_conflict(
    pos_i: np.ndarray,
    heading_i: np.ndarray,
    speed_i: np.ndarray,
    pos_j: np.ndarray,
    heading_j: np.ndarray,
    speed_j: np.ndarray,
    horizon_s: float = 3.0,
    gap_s: float = 1.5,
) -> np.ndarray:
    """Per pair (arrays of n): do i and j cross (module doc)? Positions (n, 2) in metres, headings in radians, speeds m/s."""
    u_i = np.stack([np.cos(heading_i), np.sin(heading_i)], -1)
    u_j = np.stack([np.cos(heading_j), np.sin(heading_j)], -1)
    cross = u_i[:, 0] * u_j[:, 1] - u_i[:, 1] * u_j[:, 0]
    d = np.asarray(pos_j, float) - np.asarray(pos_i, float)
    crossing = np.abs(cross) >= np.sin(np.radians(MIN_CROSSING_DEG))
    safe = np.where(crossing, cross, 1.0)
    # p_i + t_i u_i = p_j + t_j u_j  ->  t_i = (d x u_j) / (u_i x u_j),  t_j = (d x u_i) / (u_i x u_j)
    t_i = (d[:, 0] * u_j[:, 1] - d[:, 1] * u_j[:, 0]) / safe
    t_j = (d[:, 0] * u_i[:, 1] - d[:, 1] * u_i[:, 0]) / safe
    arrive_i = t_i / np.maximum(np.asarray(speed_i, float), 1.0)
    arrive_j = t_j / np.maximum(np.asarray(speed_j, float), 1.0)
    ahead = (t_i >= 0) & (t_j >= 0)
    return crossing & ahead & (np.maximum(arrive_i, arrive_j) <= horizon_s) & (np.abs(arrive_i - arrive_j) <= gap_s)


def gat_module(checkpoint: Path) -> Any:
    """The checkpoint's RLModule if its centralized critic's graph module is a GAT; a ValueError naming it otherwise."""
    module = load_module(Path(checkpoint))
    central = getattr(module, "central", None)
    if central is None or getattr(central.q1_branch.graph, "kind", None) != "gat":
        raise ValueError(f"{checkpoint} has no GAT in its centralized critic (only CIG-TD3 with global_module=gat has attention)")
    return module


def ego_attention(central: Any, obs: np.ndarray, state: np.ndarray, action: np.ndarray, env: np.ndarray) -> list[np.ndarray]:
    """For each of the B acting vehicles (rows; ``env`` their env index), the attention (1 + n,) of its Q1 GAT readout:
    entry 0 the ego itself, then the other acting vehicles of its env in row order."""
    b = len(obs)
    others = [np.nonzero((env == env[i]) & (np.arange(b) != i))[0] for i in range(b)]
    n = max((len(o) for o in others), default=0)
    o_state = np.zeros((b, max(n, 1), state.shape[1]), np.float32)
    o_action = np.zeros((b, max(n, 1), action.shape[1]), np.float32)
    mask = np.zeros((b, max(n, 1)), bool)
    for i, o in enumerate(others):
        o_state[i, : len(o)], o_action[i, : len(o)], mask[i, : len(o)] = state[o], action[o], True

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float32))

    with torch.no_grad():
        central.q1(t(obs), t(state), t(action), t(o_state), t(o_action), torch.as_tensor(mask))
    graph: GraphModule = central.q1_branch.graph
    alpha = graph.last_attention[1][:, 0, 0].numpy()  # (B, M): the ego row of layer 2
    return [alpha[i, : 1 + len(o)] for i, o in enumerate(others)]


def collect_attention(checkpoint: Path, seeds: list[int], min_neighbours: int = 3, near_m: float = 15.0) -> AttentionSample:
    """The GAT attention of every acting ego over its neighbours along deterministic episodes of ``checkpoint`` on ``seeds``.

    ``snapshot``: the scene of the first crossing conflict (by seed, then step) within ``near_m`` metres
    whose ego has at least ``min_neighbours`` neighbours besides the partner: every acting vehicle's
    position and heading in that env, the ego's and the partner's index in them, each neighbour's share.
    """
    module = gat_module(checkpoint)
    config = scenario_of(Path(checkpoint))
    if config.backend != "native":
        raise ValueError(f"attention is collected on the native backend; {checkpoint} was trained on {config.backend!r}")
    actor, central = module.actor.eval(), module.central.eval()
    envs = BatchedEnvs(DrivingSimulator(config, num_envs=len(seeds)))
    sim = envs.sim
    parts: list[dict[str, np.ndarray]] = []
    snapshot: dict[str, Any] | None = None

    def act(obs: np.ndarray) -> np.ndarray:
        nonlocal snapshot
        with torch.no_grad():
            action = actor(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        slots = envs.acting
        env = sim.env_of[slots]
        alphas = ego_attention(central, obs, envs.state[slots], action, env)
        for i, alpha in enumerate(alphas):
            others = np.nonzero((env == env[i]) & (np.arange(len(slots)) != i))[0]
            inside = alpha[1:] > 0  # the masked softmax gives exactly 0 outside the neighbourhood
            if not inside.any():
                continue
            j = others[inside]
            degree = int(inside.sum()) + 1
            a, b = slots[np.full(len(j), i)], slots[j]
            conflict = crossing_conflict(sim.pos[a], sim.heading[a], sim.speed[a], sim.pos[b], sim.heading[b], sim.speed[b])
            e = int(env[i])
            parts.append(
                {
                    "seed": np.full(len(j), seeds[e]),
                    "env_step": np.full(len(j), int(sim.env_step[e])),
                    "ego": np.full(len(j), int(slots[i])),
                    "other": b,
                    "distance": np.linalg.norm(sim.pos[a] - sim.pos[b], axis=1),
                    "alpha": alpha[1:][inside],
                    "share": alpha[1:][inside] * degree,
                    "degree": np.full(len(j), degree),
                    "conflict": conflict,
                }
            )
            close = conflict & (np.linalg.norm(sim.pos[a] - sim.pos[b], axis=1) < near_m)
            if snapshot is None and close.any() and degree - 2 >= min_neighbours:
                scene = np.nonzero(env == e)[0]
                k = int(np.argmax(close))
                snapshot = {
                    "seed": int(seeds[e]),
                    "env_step": int(sim.env_step[e]),
                    "pos": sim.pos[slots[scene]].copy(),
                    "heading": sim.heading[slots[scene]].copy(),
                    "ego": int(np.nonzero(scene == i)[0][0]),
                    "partner": int(np.nonzero(scene == j[k])[0][0]),
                    "share": {int(np.nonzero(scene == jj)[0][0]): float(s) for jj, s in zip(j, alpha[1:][inside] * degree, strict=True)},
                    "self_share": float(alpha[0] * degree),
                    "half": sim.half.copy(),
                }
        return action

    for _ in rollout(envs, act, seeds, config.force_stop_factor * config.horizon):
        pass
    edges = pd.DataFrame({c: np.concatenate([p[c] for p in parts]) for c in EDGE_COLUMNS}) if parts else pd.DataFrame(columns=EDGE_COLUMNS)
    return AttentionSample(edges, snapshot, sim.map)


def conflict_summary(edges: pd.DataFrame, bins: tuple[float, ...] = (0.0, 5.0, 10.0, 20.0, 40.0, np.inf)) -> pd.DataFrame:
    """Mean share of conflict partners and of the other neighbours per distance bin, with their edge counts."""
    cut = pd.cut(edges["distance"], list(bins), right=False)
    g = edges.assign(bin=cut).groupby(["bin", "conflict"], observed=True)["share"].agg(["mean", "count"]).reset_index()
    return g
