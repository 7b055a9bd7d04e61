"""Neighbour sets and the centralized-critic inputs of CPPO and MFPO (docs/guides/ppo-family.md).

Rows are agent transitions; ``group`` says which rows share an env step of one episode
(e.g. ``episode_index * big + env_step`` from the env's ``env_step`` info, never row order), so
neighbours are the other agents present at that same env step. Everything is vectorized over
all groups at once (groups hold at most a few dozen agents).

* CPPO ("concat"): ``[o_i | (o_j, a_j) for the k = 4 nearest others within 40 m]``, nearest
  first, empty slots zero.
* MFPO ("mean field"): ``[o_i | mean o_j | mean a_j]`` over the others within 10 m; zeros
  when there are none.
"""

from __future__ import annotations

import numpy as np


def neighbour_indices(positions: np.ndarray, group: np.ndarray, radius: float, k: int | None = None) -> np.ndarray:
    """Row indices (n, k) of each row's nearest other rows of its group strictly within ``radius``, nearest first; -1 pads.

    ``k=None`` keeps every neighbour (width = largest group - 1). Ties keep row order.
    """
    pos = np.asarray(positions, dtype=float).reshape(-1, 2)
    group = np.asarray(group).reshape(-1)
    n = len(pos)
    if len(group) != n:
        raise ValueError(f"positions ({n}) and group ({len(group)}) must have one entry per row")
    if n == 0:
        return np.zeros((0, k or 0), dtype=np.int64)
    order = np.argsort(group, kind="stable")
    _, start, count = np.unique(group[order], return_index=True, return_counts=True)
    width = int(count.max())
    slot = np.arange(n) - np.repeat(start, count)  # position of each sorted row inside its group
    gid = np.repeat(np.arange(len(start)), count)
    rows = np.full((len(start), width), -1, dtype=np.int64)
    rows[gid, slot] = order
    p = np.full((len(start), width, 2), np.nan)
    p[gid, slot] = pos[order]
    d = np.linalg.norm(p[:, :, None, :] - p[:, None, :, :], axis=-1)  # (G, M, M), NaN on padding
    d[:, np.arange(width), np.arange(width)] = np.inf
    d = np.where(np.isnan(d) | (d >= radius), np.inf, d)
    nearest = np.argsort(d, axis=-1, kind="stable")
    keep = width - 1 if k is None else k
    cols = min(keep, width - 1)  # a group of m rows has at most m - 1 neighbours
    nearest = nearest[:, :, :cols]
    valid = np.take_along_axis(d, nearest, axis=-1) < np.inf
    picked = np.where(valid, np.take_along_axis(np.broadcast_to(rows[:, None, :], d.shape), nearest, axis=-1), -1)
    out = np.full((n, keep), -1, dtype=np.int64)
    out[order, :cols] = picked[gid, slot]
    return out


def concat_critic_input(obs: np.ndarray, actions: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """CPPO critic input ``[o_i | o_j1, a_j1 | ... | o_jk, a_jk]`` (zeros for -1 slots)."""
    obs, actions = np.asarray(obs, np.float32), np.asarray(actions, np.float32)
    pair = np.concatenate([obs, actions], 1)
    padded = np.concatenate([pair, np.zeros((1, pair.shape[1]), np.float32)])  # row -1 -> zeros
    return np.concatenate([obs, padded[neighbours].reshape(len(obs), -1)], 1)


def mean_field_critic_input(obs: np.ndarray, actions: np.ndarray, neighbours: np.ndarray) -> np.ndarray:
    """MFPO critic input ``[o_i | mean o_j | mean a_j]`` over the valid neighbours (zeros when none)."""
    obs, actions = np.asarray(obs, np.float32), np.asarray(actions, np.float32)
    valid = neighbours >= 0
    cnt = valid.sum(1, keepdims=True)
    pair = np.concatenate([obs, actions], 1)
    summed = (pair[np.where(valid, neighbours, 0)] * valid[..., None]).sum(1)
    return np.concatenate([obs, summed / np.maximum(cnt, 1)], 1).astype(np.float32)
