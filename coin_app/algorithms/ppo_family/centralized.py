"""CPPO and MFPO: PPO with a centralized value function on neighbour information.

``CriticInputs`` is a learner-connector piece inserted before RLlib's GAE piece. For every
agent row of the train batch it finds the agents present at the same env step of the same
episode (the env's ``env_step`` info and multi-agent episode id, never row order, so it is
exact across respawns and episode chunks), selects neighbours by distance (positions from the
``state`` info) and writes the critic input (``neighbours.py``) as column ``CRITIC_OBS``. It
checks that its rows are the batch's rows (same observations) and refuses otherwise.
``CentralizedCriticPPOModule`` is RLlib's default PPO module whose ``compute_values`` reads
that column through its own tanh MLP; the policy is untouched (env runners build only it).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.connectors.learner.general_advantage_estimation import GeneralAdvantageEstimation
from ray.rllib.core.columns import Columns
from torch import nn

from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner
from coin_app.algorithms.ppo_family.neighbours import concat_critic_input, mean_field_critic_input, neighbour_indices

CRITIC_OBS = "coin_critic_obs"
MODES = ("concat", "mean_field")


def critic_input_dim(mode: str, obs_dim: int, act_dim: int, num_neighbours: int) -> int:
    """Length of the critic input of ``mode``."""
    return obs_dim + num_neighbours * (obs_dim + act_dim) if mode == "concat" else 2 * obs_dim + act_dim


class CriticInputs(ConnectorV2):
    """Learner connector: the CPPO / MFPO critic input of every row, aligned by (episode, env step)."""

    def __init__(self, *args: Any, mode: str, radius: float, num_neighbours: int, position_scale: float, **kwargs: Any):
        super().__init__(*args, **kwargs)
        if mode not in MODES:
            raise ValueError(f"unknown critic mode {mode!r}; allowed: {', '.join(MODES)}")
        self.mode, self.radius, self.k, self.scale = mode, float(radius), int(num_neighbours), float(position_scale)

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: list[Any], **kwargs: Any) -> dict[str, Any]:
        """Add ``CRITIC_OBS`` to each module's batch."""
        obs, act, pos, group = [], [], [], []
        episode_ids: dict[str, int] = {}
        for sa in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            n = len(sa)
            infos = sa.get_infos(slice(0, n))
            obs.append(np.asarray(sa.get_observations(slice(0, n)), np.float32))
            act.append(np.asarray(sa.get_actions(slice(0, n)), np.float32))
            pos.append(np.array([info["state"][:2] for info in infos], float) * self.scale)
            eid = episode_ids.setdefault(sa.multi_agent_episode_id, len(episode_ids))
            group.append(np.array([eid * 10_000_000 + int(info["env_step"]) for info in infos], np.int64))
        if not obs:
            return batch
        obs_a, act_a = np.concatenate(obs), np.concatenate(act)
        nbr = neighbour_indices(np.concatenate(pos), np.concatenate(group), self.radius, self.k if self.mode == "concat" else None)
        fuse = concat_critic_input if self.mode == "concat" else mean_field_critic_input
        critic = fuse(obs_a, act_a, nbr)
        for module_batch in batch.values():
            got = module_batch[Columns.OBS]
            got = got.detach().cpu().numpy() if isinstance(got, torch.Tensor) else np.asarray(got)
            if got.shape != obs_a.shape or not np.array_equal(got, obs_a):
                raise RuntimeError("critic inputs are not aligned with the train batch rows (RLlib changed its batch order?)")
            ref = module_batch[Columns.OBS]
            module_batch[CRITIC_OBS] = torch.as_tensor(critic, device=ref.device) if isinstance(ref, torch.Tensor) else critic
        return batch


class CentralizedCriticPPOModule(DefaultPPOTorchRLModule):
    """RLlib's default PPO module with the value function on the centralized critic input."""

    def setup(self) -> None:
        """Build the default module, plus the centralized value MLP on learner copies."""
        super().setup()
        if not self.inference_only:
            width = self.model_config["fcnet_hiddens"]
            sizes = [int(self.model_config["critic_input_dim"]), *width]
            layers: list[nn.Module] = []
            for a, b in zip(sizes[:-1], sizes[1:]):
                layers += [nn.Linear(a, b), nn.Tanh()]
            self.central_vf = nn.Sequential(*layers, nn.Linear(sizes[-1], 1))

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        """V(critic input) of shape (B,)."""
        return self.central_vf(batch[CRITIC_OBS]).squeeze(-1)


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
