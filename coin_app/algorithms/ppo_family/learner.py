"""PPO learner with Ray 1.x's PPO2-style value clipping (the objective of the COIN/CoPO baseline runs).

``OldValuePredictions`` is a learner-connector piece appended after RLlib's GAE piece: it
stores ``V_old(o)`` (the value function before this update's SGD epochs) in the batch, which
the clipped value loss needs and RLlib's GAE piece drops.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.algorithms.ppo.ppo import LEARNER_RESULTS_KL_KEY, LEARNER_RESULTS_VF_EXPLAINED_VAR_KEY
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.learner import ENTROPY_KEY, POLICY_LOSS_KEY, VF_LOSS_KEY
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.torch_utils import explained_variance

from coin_app.algorithms.ppo_family.losses import clipped_value_loss, surrogate_loss

OLD_VALUES = "coin_old_values"


class OldValuePredictions(ConnectorV2):
    """Learner connector: put the current value predictions of every sample into the batch."""

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: Any, **kwargs: Any) -> dict[str, Any]:
        """Add ``OLD_VALUES`` to each module's batch (no gradient)."""
        for module_id, module_batch in batch.items():
            module = rl_module[module_id]
            if isinstance(module.unwrapped(), ValueFunctionAPI) and Columns.OBS in module_batch:
                with torch.no_grad():
                    module_batch[OLD_VALUES] = module.unwrapped().compute_values(module_batch)
        return batch


class ClippedValuePPOLearner(PPOTorchLearner):
    """RLlib's PPO learner with the PPO2 clipped value loss (see ``losses.py``)."""

    def build(self) -> None:
        """Build as RLlib's PPO learner, then append the old-value connector piece after GAE."""
        super().build()
        if self._learner_connector is not None:
            self._learner_connector.append(OldValuePredictions())

    def value_loss(self, module: Any, batch: dict[str, Any], fwd_out: dict[str, Any], config: Any) -> tuple[torch.Tensor, ...]:
        """(clipped value loss, values, value targets, extra metrics) of the value function."""
        values = module.compute_values(batch, embeddings=fwd_out.get(Columns.EMBEDDINGS))
        targets = batch[Postprocessing.VALUE_TARGETS]
        return clipped_value_loss(values, batch[OLD_VALUES], targets, config.vf_clip_param), values, targets, {}

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]) -> torch.Tensor:
        """Clipped surrogate + c_V * clipped value loss - entropy bonus + beta * KL."""
        module = self.module[module_id].unwrapped()
        if Columns.LOSS_MASK in batch:  # the artificial bootstrap timestep RLlib adds per episode
            mask = batch[Columns.LOSS_MASK]
            batch = {k: v[mask] if isinstance(v, torch.Tensor) and v.shape[:1] == mask.shape else v for k, v in batch.items()}
            fwd_out = {k: v[mask] if isinstance(v, torch.Tensor) and v.shape[:1] == mask.shape else v for k, v in fwd_out.items()}
        dist = module.get_train_action_dist_cls().from_logits(fwd_out[Columns.ACTION_DIST_INPUTS])
        old_dist = module.get_exploration_action_dist_cls().from_logits(batch[Columns.ACTION_DIST_INPUTS])
        logp = dist.logp(batch[Columns.ACTIONS])
        adv = batch[Postprocessing.ADVANTAGES]
        pi_loss = surrogate_loss(logp, batch[Columns.ACTION_LOGP], adv, config.clip_param)
        vf_loss, values, targets, extra = self.value_loss(module, batch, fwd_out, config)
        entropy = dist.entropy().mean()
        kl = old_dist.kl(dist).mean() if config.use_kl_loss else torch.zeros(())
        entropy_coeff = self.entropy_coeff_schedulers_per_module[module_id].get_current_value()
        total = pi_loss + config.vf_loss_coeff * vf_loss - entropy_coeff * entropy
        if config.use_kl_loss:
            total = total + self.curr_kl_coeffs_per_module[module_id] * kl
        self.metrics.log_dict(
            {
                POLICY_LOSS_KEY: pi_loss,
                VF_LOSS_KEY: vf_loss,
                LEARNER_RESULTS_VF_EXPLAINED_VAR_KEY: explained_variance(targets, values),
                ENTROPY_KEY: entropy,
                LEARNER_RESULTS_KL_KEY: kl,
                **extra,
            },
            key=module_id,
            window=1,
        )
        return total
