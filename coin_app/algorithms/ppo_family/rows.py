"""The rows of a PPO train batch as arrays, with each row's env step group (for neighbour pieces).

RLlib's learner connector lays the batch out episode by episode, in the order of
``single_agent_episode_iterator``; after ``AddOneTsToEpisodesAndTruncate`` every episode ends
with one artificial row (``LOSS_MASK`` False) that repeats the last observation and info.
``group`` keys a row by (multi-agent episode chunk, the env's ``env_step`` info, artificial
or not): rows of one group are the agents present at that env step, so neighbours are never
found by row order, and artificial rows (whose info repeats a step at which the agent no
longer acts) only meet other artificial rows.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.utils.numpy import convert_to_numpy

from coin_app.sim import schema


@dataclass
class EpisodeRows:
    """Per-row arrays of a batch: observations, actions, rewards, positions (m), group keys, real-row mask."""

    obs: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    positions: np.ndarray
    group: np.ndarray
    real: np.ndarray


def episode_rows(piece: ConnectorV2, episodes: list[Any], position_scale: float, loss_mask: Any = None) -> EpisodeRows | None:
    """The rows of ``episodes`` in batch order (None if there are none); ``loss_mask`` marks the real rows."""
    obs, act, rew, pos, step, chunk = [], [], [], [], [], []
    chunk_ids: dict[str, int] = {}
    for sa in piece.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
        n = len(sa)
        infos = sa.get_infos(slice(0, n))
        obs.append(np.asarray(sa.get_observations(slice(0, n)), np.float32))
        act.append(np.asarray(sa.get_actions(slice(0, n)), np.float32))
        rew.append(np.asarray(sa.get_rewards(slice(0, n)), np.float32))
        pos.append(np.array([info[schema.STATE][:2] for info in infos], float) * position_scale)
        step.append(np.array([info[schema.ENV_STEP] for info in infos], np.int64))
        chunk.append(np.full(n, chunk_ids.setdefault(sa.multi_agent_episode_id, len(chunk_ids)), np.int64))
    if not obs:
        return None
    steps = np.concatenate(step)
    real = np.ones(len(steps), bool) if loss_mask is None else np.asarray(convert_to_numpy(loss_mask), bool)
    if real.shape != steps.shape:
        raise RuntimeError(f"loss mask has {real.shape[0]} rows but the episodes have {steps.shape[0]}")
    group = (np.concatenate(chunk) * 10_000_000 + steps) * 2 + ~real
    return EpisodeRows(np.concatenate(obs), np.concatenate(act), np.concatenate(rew), np.concatenate(pos), group, real)


def check_aligned(module_batch: dict[str, Any], rows: EpisodeRows) -> None:
    """Refuse a batch whose observations are not ``rows``' observations in the same order."""
    got = convert_to_numpy(module_batch[Columns.OBS])
    if got.shape != rows.obs.shape or not np.array_equal(got, rows.obs):
        raise RuntimeError("the episode rows are not aligned with the train batch rows (RLlib changed its batch order?)")


def like(ref: Any, value: np.ndarray) -> Any:
    """``value`` as a tensor on ``ref``'s device when ``ref`` is a tensor, else as is."""
    return torch.as_tensor(value, device=ref.device) if isinstance(ref, torch.Tensor) else value
