"""CoPO's learner-connector piece: three GAE advantages and the coordinated advantage (replaces RLlib's GAE piece).

For the batch's rows (``ppo_family/rows.py``: aligned by episode and env step, never row
order) it computes the neighbour and global rewards (``coordination.py``), the ego, neighbour
and global values before this update (no gradient), and GAE with RLlib's own
``compute_value_targets`` (so termination and chunk-truncation bootstrapping are RLlib's):
ego and neighbour with (gamma, lambda), global with (1.0, lambda). The policy advantage is the
coordinated advantage ``cos(phi) A_ego + sin(phi) A_nei`` of each row's own LCF (decoded from
its observation's last feature), standardized over the real rows; its raw mean and std are
kept for the meta-gradient. The global advantage is standardized separately.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.numpy import convert_to_numpy
from ray.rllib.utils.postprocessing.value_predictions import compute_value_targets

from coin_app.adapters.lcf import decode
from coin_app.algorithms.copo.coordination import coordinated_advantage, neighbour_and_global_rewards, standardized
from coin_app.algorithms.ppo_family.learner import OLD_VALUES
from coin_app.algorithms.ppo_family.rows import check_aligned, episode_rows, like

NEI_REWARDS, GLOBAL_REWARDS = "coin_nei_rewards", "coin_global_rewards"
NEI_TARGETS, GLOBAL_TARGETS = "coin_nei_targets", "coin_global_targets"
OLD_NEI_VALUES, OLD_GLOBAL_VALUES = "coin_old_nei_values", "coin_old_global_values"
EGO_ADVANTAGES, NEI_ADVANTAGES = "coin_ego_advantages", "coin_nei_advantages"  # raw GAE
GLOBAL_ADVANTAGES = "coin_global_advantages"  # standardized
LCF = "coin_lcf"
COORD_MEAN, COORD_STD = "coin_coord_mean", "coin_coord_std"  # raw coordinated advantage statistics, per row


class CoPOAdvantages(ConnectorV2):
    """Learner connector: ego / neighbour / global GAE and the standardized coordinated advantage (see module doc)."""

    def __init__(self, *args: Any, gamma: float, lambda_: float, radius: float, position_scale: float, **kwargs: Any):
        super().__init__(*args, **kwargs)
        self.gamma, self.lambda_, self.radius, self.scale = float(gamma), float(lambda_), float(radius), float(position_scale)

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], **kwargs: Any) -> dict[str, Any]:
        """Write the CoPO columns into each module's batch."""
        for module_id, module_batch in batch.items():
            rows = episode_rows(self, episodes, self.scale, module_batch.get(Columns.LOSS_MASK))
            if rows is None:
                continue
            check_aligned(module_batch, rows)
            with torch.no_grad():
                values = [convert_to_numpy(v).astype(np.float32) for v in rl_module[module_id].unwrapped().compute_all_values(module_batch)]
            columns = self.columns(
                rows, values, convert_to_numpy(module_batch[Columns.TERMINATEDS]), convert_to_numpy(module_batch[Columns.TRUNCATEDS])
            )
            ref = module_batch[Columns.OBS]
            module_batch.update({k: like(ref, v) for k, v in columns.items()})
        return batch

    def columns(self, rows: Any, values: list[np.ndarray], terminateds: np.ndarray, truncateds: np.ndarray) -> dict[str, np.ndarray]:
        """The CoPO columns of a batch from its rows, its (ego, neighbour, global) values and its flags."""
        v_ego, v_nei, v_glob = values
        nei_r, glob_r = neighbour_and_global_rewards(rows.rewards, rows.positions, rows.group, self.radius)
        flags = (np.asarray(terminateds, np.float32), np.asarray(truncateds, np.float32))
        t_ego = compute_value_targets(v_ego, rows.rewards, *flags, gamma=self.gamma, lambda_=self.lambda_)
        t_nei = compute_value_targets(v_nei, nei_r, *flags, gamma=self.gamma, lambda_=self.lambda_)
        t_glob = compute_value_targets(v_glob, glob_r, *flags, gamma=1.0, lambda_=self.lambda_)
        a_ego, a_nei = t_ego - v_ego, t_nei - v_nei
        lcf = decode(rows.obs[:, -1])
        coord, mean, std = standardized(coordinated_advantage(a_ego, a_nei, lcf), rows.real)
        n = len(rows.obs)
        return {
            Postprocessing.ADVANTAGES: coord,
            Postprocessing.VALUE_TARGETS: t_ego,
            OLD_VALUES: v_ego,
            NEI_REWARDS: nei_r,
            GLOBAL_REWARDS: glob_r,
            NEI_TARGETS: t_nei,
            GLOBAL_TARGETS: t_glob,
            OLD_NEI_VALUES: v_nei,
            OLD_GLOBAL_VALUES: v_glob,
            EGO_ADVANTAGES: a_ego.astype(np.float32),
            NEI_ADVANTAGES: a_nei.astype(np.float32),
            GLOBAL_ADVANTAGES: standardized(t_glob - v_glob, rows.real)[0],
            LCF: lcf,
            COORD_MEAN: np.full(n, mean, np.float32),
            COORD_STD: np.full(n, std, np.float32),
        }
