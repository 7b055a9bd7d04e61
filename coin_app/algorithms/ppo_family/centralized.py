"""CPPO and MFPO: PPO with a centralized value function on neighbour information.

``CriticInputs`` is a learner-connector piece inserted before RLlib's GAE piece. For every
agent row of the train batch it finds the agents present at the same env step of the same
episode (the env's ``env_step`` info and multi-agent episode id, never row order, so it is
exact across respawns and episode chunks; see ``rows.py``), selects neighbours by distance (positions from the
``state`` info) and writes the critic input (``neighbours.py``) as column ``CRITIC_OBS``. It
checks that its rows are the batch's rows (same observations) and refuses otherwise.
``CentralizedCriticPPOModule`` is the family's PPO module (``rl_module.py``) whose ``compute_values``
reads that column through its own tanh MLP; the policy is untouched (env runners build only it).
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.connectors.learner.general_advantage_estimation import GeneralAdvantageEstimation
from ray.rllib.core.columns import Columns
from torch import nn

from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner
from coin_app.algorithms.ppo_family.neighbours import concat_critic_input, mean_field_critic_input, neighbour_indices
from coin_app.algorithms.ppo_family.precision import full_precision
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule
from coin_app.algorithms.ppo_family.rows import check_aligned, episode_rows, like

CRITIC_OBS = "coin_critic_obs"
MODES = ("concat", "mean_field")


def critic_input_dim(mode: str, obs_dim: int, act_dim: int, num_neighbours: int) -> int:
    """Length of the critic input of ``mode``."""
    return obs_dim + num_neighbours * (obs_dim + act_dim) if mode == "concat" else 2 * obs_dim + act_dim


def value_mlp(in_dim: int, widths: list[int]) -> nn.Sequential:
    """A value network: tanh hidden layers of ``widths``, then one linear output."""
    sizes = [in_dim, *widths]
    layers: list[nn.Module] = []
    for a, b in zip(sizes[:-1], sizes[1:]):
        layers += [nn.Linear(a, b), nn.Tanh()]
    return nn.Sequential(*layers, nn.Linear(sizes[-1], 1))


class CriticInputs(ConnectorV2):
    """Learner connector: the CPPO / MFPO critic input of every row, aligned by (episode, env step)."""

    def __init__(self, *args: Any, mode: str, radius: float, num_neighbours: int, position_scale: float, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if mode not in MODES:
            raise ValueError(f"unknown critic mode {mode!r}; allowed: {', '.join(MODES)}")
        self.mode, self.radius, self.k, self.scale = mode, float(radius), int(num_neighbours), float(position_scale)

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], **kwargs: Any) -> dict[str, Any]:
        """Add ``CRITIC_OBS`` to each module's batch."""
        mask = next((b.get(Columns.LOSS_MASK) for b in batch.values()), None)
        rows = episode_rows(self, episodes, self.scale, mask)
        if rows is None:
            return batch
        nbr = neighbour_indices(rows.positions, rows.group, self.radius, self.k if self.mode == "concat" else None)
        fuse = concat_critic_input if self.mode == "concat" else mean_field_critic_input
        critic = fuse(rows.obs, rows.actions, nbr)
        for module_batch in batch.values():
            check_aligned(module_batch, rows)
            module_batch[CRITIC_OBS] = like(module_batch[Columns.OBS], critic)
        return batch


class CentralizedCriticPPOModule(PPOActorModule):
    """The family's PPO module with the value function on the centralized critic input."""

    def setup_heads(self) -> None:
        """The centralized value MLP (learner copies only)."""
        if not self.inference_only:
            self.central_vf = value_mlp(int(self.model_config["critic_input_dim"]), self.model_config["fcnet_hiddens"])

    def get_non_inference_attributes(self) -> list[str]:
        """The centralized value network is not needed to act."""
        return [*super().get_non_inference_attributes(), "central_vf"]

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        """V(critic input) of shape (B,), in fp32."""
        return full_precision(self.central_vf(batch[CRITIC_OBS]).squeeze(-1))


class CentralizedCriticPPOLearner(ClippedValuePPOLearner):
    """The clipped-value PPO learner with ``CriticInputs`` before GAE (GAE needs the central values)."""

    def build(self) -> None:
        """Build, then insert the critic-input piece right before RLlib's GAE piece."""
        super().build()
        cfg = self.config.learner_config_dict
        piece = CriticInputs(
            mode=cfg["critic_mode"],
            radius=cfg["neighbour_radius"],
            num_neighbours=cfg["num_neighbours"],
            position_scale=cfg["position_scale"],
        )
        self._learner_connector.insert_before(GeneralAdvantageEstimation, piece)
