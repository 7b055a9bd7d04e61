"""The PPO learner of the COIN / CoPO baselines: Ray 1.x's PPO objective and update rules on RLlib 2.60's PPO learner.

Where Ray 1.2's PPO (the CoPO paper runs, ``docs/decisions.md`` §7) and RLlib 2.60 differ, the
learner does what Ray 1.x did, each difference a learner-connector piece or a learner hook:

* Value loss: PPO2-style clipping around the value before the update (``losses.py``).
  ``OldValuePredictions``, appended after RLlib's GAE piece, stores ``V_old(o)`` in the batch
  (RLlib's GAE piece drops it).
* Advantage standardization over the real rows only. RLlib's GAE piece standardizes over the
  whole batch, including the one artificial bootstrap row it appends to every episode chunk;
  ``RealRowAdvantages`` standardizes the raw advantages ``target - V_old`` over the rows of
  ``LOSS_MASK`` instead (Ray 1.x's batches had no such rows).
* Per-agent time-outs (``learner_config_dict["timeout_bootstrap"]`` False, the default):
  ``TimeoutsAsTerminal``, placed before RLlib's ``AddOneTsToEpisodesAndTruncate``, marks every
  episode the env truncated (a vehicle's own step limit, the force stop) as terminated, so GAE
  bootstraps it with 0, as Ray 1.x did for every done. Chunk ends, which the env did not
  truncate, still bootstrap with V. True keeps RLlib's bootstrap with V(o_T).
* Adaptive KL coefficient (``kl_signal`` "epoch_mean", the default): RLlib's x1.5 / x0.5 step
  (above 2 x target / below target / 2) reads the mean KL of the last epoch's minibatches, the
  value Ray 1.x's SGD loops reported; "last_minibatch" keeps RLlib 2.60's signal, the KL of the
  last minibatch only.

Every learner-connector pipeline starts with ``FixedAgentOrder`` (``agent_order.py``): the batch's
rows do not depend on the Python hash seed.

``learner_config_dict["precision"]`` "bf16" runs each minibatch's forward pass and losses under
bfloat16 autocast (``precision.py``); "fp32", the default, is RLlib's update as it is. Either steps
with fused Adam after one finiteness check over all gradients (``gradient_step.py``).
"""

from __future__ import annotations

from collections import defaultdict
from typing import Any

import torch
from ray.rllib.algorithms.ppo.ppo import LEARNER_RESULTS_KL_KEY, LEARNER_RESULTS_VF_EXPLAINED_VAR_KEY
from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.connectors.connector_v2 import ConnectorV2
from ray.rllib.connectors.learner import AddOneTsToEpisodesAndTruncate
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.learner import ENTROPY_KEY, POLICY_LOSS_KEY, VF_LOSS_KEY
from ray.rllib.core.rl_module.apis.value_function_api import ValueFunctionAPI
from ray.rllib.evaluation.postprocessing import Postprocessing
from ray.rllib.utils.torch_utils import explained_variance

from coin_app.algorithms.gradient_step import FastGradientStep
from coin_app.algorithms.ppo_family.agent_order import fix_agent_order
from coin_app.algorithms.ppo_family.losses import clipped_value_loss, last_epoch_mean, surrogate_loss
from coin_app.algorithms.ppo_family.precision import MixedPrecisionLearner

OLD_VALUES = "coin_old_values"
EPOCH_KL_KEY = "mean_kl_last_epoch"  # the KL the coefficient adapted to (kl_signal "epoch_mean")


class TimeoutsAsTerminal(ConnectorV2):
    """Learner connector: an episode the env truncated (time-out, force stop) ends as terminated, so GAE bootstraps it with 0."""

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: Any, **kwargs: Any) -> dict[str, Any]:
        """Set ``is_terminated`` on every single-agent episode the env truncated (sampling-chunk cuts are not truncated yet)."""
        for episode in self.single_agent_episode_iterator(episodes, agents_that_stepped_only=False):
            if episode.is_truncated and not episode.is_terminated:
                episode.is_terminated = True
        return batch


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


class RealRowAdvantages(ConnectorV2):
    """Learner connector: the advantages standardized over the real rows (``LOSS_MASK``), without RLlib's bootstrap rows."""

    def __call__(self, *, rl_module: Any, batch: dict[str, Any], episodes: Any, **kwargs: Any) -> dict[str, Any]:
        """Replace ``ADVANTAGES`` by ``(A - mean) / max(1e-4, std)`` of the raw ``A = target - V_old`` over the real rows."""
        needed = (Postprocessing.VALUE_TARGETS, OLD_VALUES, Columns.LOSS_MASK)
        for module_batch in batch.values():
            if not all(k in module_batch for k in needed):
                continue
            old = torch.as_tensor(module_batch[OLD_VALUES])  # the module's output: on the learner's device
            raw = torch.as_tensor(module_batch[Postprocessing.VALUE_TARGETS], device=old.device) - old
            real = torch.as_tensor(module_batch[Columns.LOSS_MASK], dtype=torch.bool, device=raw.device)
            mean, std = raw[real].mean(), raw[real].std(correction=0)
            module_batch[Postprocessing.ADVANTAGES] = (raw - mean) / torch.clamp(std, min=1e-4)
        return batch


class ClippedValuePPOLearner(MixedPrecisionLearner, FastGradientStep, PPOTorchLearner):
    """RLlib's PPO learner with Ray 1.x's value clipping, advantage standardization, time-outs, KL signal and precision (module doc)."""

    def build(self) -> None:
        """Build as RLlib's PPO learner, then add the time-out, old-value and advantage pieces around its GAE."""
        super().build()
        cfg = self.config.learner_config_dict
        self.kl_signal: str = cfg["kl_signal"]
        self._minibatch_kls: dict[str, list[torch.Tensor]] = defaultdict(list)
        fix_agent_order(self)
        if self._learner_connector is not None:
            if not cfg["timeout_bootstrap"]:
                self._learner_connector.insert_before(AddOneTsToEpisodesAndTruncate, TimeoutsAsTerminal())
            self._learner_connector.append(OldValuePredictions())
            self._learner_connector.append(RealRowAdvantages())

    def record_kl(self, module_id: str, kl: torch.Tensor) -> None:
        """Log one minibatch's mean KL(pi_old || pi) (RLlib's ``mean_kl_loss``) and keep it for this update's epoch mean."""
        self.metrics.log_value((module_id, LEARNER_RESULTS_KL_KEY), kl.detach(), window=1)
        self._minibatch_kls[module_id].append(kl.detach())

    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Start this update's record of minibatch KLs."""
        super().before_gradient_based_update(timesteps=timesteps)
        self._minibatch_kls.clear()

    def _update_module_kl_coeff(self, *, module_id: str, config: Any, kl_loss: float) -> None:
        """RLlib's x1.5 / x0.5 coefficient step, on the last epoch's mean KL when ``kl_signal`` is "epoch_mean"."""
        kls = self._minibatch_kls.pop(module_id, [])
        if self.kl_signal == "epoch_mean" and kls:
            kl_loss = last_epoch_mean(torch.stack(kls).tolist(), config.num_epochs)
            self.metrics.log_value((module_id, EPOCH_KL_KEY), kl_loss, window=1)
        super()._update_module_kl_coeff(module_id=module_id, config=config, kl_loss=kl_loss)

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
        kl = old_dist.kl(dist).mean() if config.use_kl_loss else torch.zeros((), dtype=logp.dtype, device=logp.device)
        entropy_coeff = self.entropy_coeff_schedulers_per_module[module_id].get_current_value()
        total = pi_loss + config.vf_loss_coeff * vf_loss - entropy_coeff * entropy
        if config.use_kl_loss:
            total = total + self.curr_kl_coeffs_per_module[module_id] * kl
        self.record_kl(module_id, kl)
        self.metrics.log_dict(
            {
                POLICY_LOSS_KEY: pi_loss,
                VF_LOSS_KEY: vf_loss,
                LEARNER_RESULTS_VF_EXPLAINED_VAR_KEY: explained_variance(targets, values),
                ENTROPY_KEY: entropy,
                **extra,
            },
            key=module_id,
            window=1,
        )
        return total
