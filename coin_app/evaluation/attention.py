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


def ego_attention(central: Any, obs: np.ndarray, state: np.ndarray, action: np.ndarray, env: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha, others) for the B acting vehicles (rows; ``env`` their env index): ``alpha`` (B, 1 + n) the attention of
    each one's Q1 GAT readout, column 0 the ego itself, column 1 + k its k-th other acting vehicle of its env in row
    order, whose row is ``others[i, k]`` (B, n); -1 and attention 0 past the env's vehicles (n: the largest env's, minus 1)."""
    b = len(obs)
    same = (env[:, None] == env[None, :]) & ~np.eye(b, dtype=bool)
    count = same.sum(1)
    n = max(int(count.max(initial=0)), 1)
    rows, cols = np.nonzero(same)  # row-major: each ego's others in row order
    others = np.full((b, n), -1)
    others[rows, np.arange(len(rows)) - np.repeat(np.cumsum(count) - count, count)] = cols
    mask = others >= 0

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float32))

    with torch.no_grad():
        central.q1(
            t(obs), t(state), t(action), t(state[others] * mask[..., None]), t(action[others] * mask[..., None]), torch.as_tensor(mask)
        )
    graph: GraphModule = central.q1_branch.graph
    row = graph.last_attention[1][:, 0, 0].numpy()[:, : 1 + n]  # the ego row of layer 2 (no column for a lone ego's padding)
    alpha = np.zeros((b, 1 + n), np.float32)
    alpha[:, : row.shape[1]] = row
    alpha[:, 1:][~mask] = 0.0
    return alpha, others


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
        alpha, others = ego_attention(central, obs, envs.state[slots], action, env)
        inside = alpha[:, 1:] > 0  # the masked softmax gives exactly 0 outside the neighbourhood and past the env's vehicles
        degree = inside.sum(1) + 1
        ego, k = np.nonzero(inside)  # by ego, then its others in row order
        if not len(ego):
            return action
        a, b = slots[ego], slots[others[ego, k]]
        conflict = crossing_conflict(sim.pos[a], sim.heading[a], sim.speed[a], sim.pos[b], sim.heading[b], sim.speed[b])
        distance = np.linalg.norm(sim.pos[a] - sim.pos[b], axis=1)
        share = alpha[ego, 1 + k] * degree[ego].astype(np.float32)
        e = env[ego]
        parts.append(
            {
                "seed": np.asarray(seeds)[e],
                "env_step": sim.env_step[e].astype(int),
                "ego": a,
                "other": b,
                "distance": distance,
                "alpha": alpha[ego, 1 + k],
                "share": share,
                "degree": degree[ego],
                "conflict": conflict,
            }
        )
        close = np.nonzero(conflict & (distance < near_m) & (degree[ego] - 2 >= min_neighbours))[0]
        if snapshot is None and len(close):
            first = close[0]  # the first ego in row order, its first partner
            i, partner = int(ego[first]), int(others[ego[first], k[first]])
            scene = np.nonzero(env == env[i])[0]
            mine = ego == i
            snapshot = {
                "seed": int(seeds[env[i]]),
                "env_step": int(sim.env_step[env[i]]),
                "pos": sim.pos[slots[scene]].copy(),
                "heading": sim.heading[slots[scene]].copy(),
                "ego": int(np.nonzero(scene == i)[0][0]),
                "partner": int(np.nonzero(scene == partner)[0][0]),
                "share": {int(np.nonzero(scene == j)[0][0]): float(s) for j, s in zip(others[i, k[mine]], share[mine], strict=True)},
                "self_share": float(alpha[i, 0] * np.float32(degree[i])),
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
    return edges.assign(bin=cut).groupby(["bin", "conflict"], observed=True)["share"].agg(["mean", "count"]).reset_index()
