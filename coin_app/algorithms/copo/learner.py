"""CoPO's learner: the clipped-value PPO learner with three value losses and the LCF meta-gradient step.

* Connector: RLlib's GAE piece, the old-value piece and the real-row standardization piece
  are replaced by ``CoPOAdvantages`` (which standardizes over the real rows itself); the
  family's time-out piece stays, so all three GAEs end a timed-out vehicle with 0 by default.
* Loss: PPO clipped surrogate on the standardized coordinated advantage; the PPO2-clipped
  value losses of the ego, neighbour and global heads added with ``vf_loss_coeff`` each; the
  adaptive KL penalty; no entropy bonus by default.
* After the SGD epochs of an update (``after_gradient_based_update``), ``lcf_num_iters`` passes
  of the meta-gradient step of ``coordination.py`` over shuffled minibatches of the same
  batch's real rows, against a frozen copy of the policy taken before the epochs; the new
  LCF parameters go into the module's buffer (and from there into checkpoints and the weights
  of the env runners; the algorithm pushes the distribution to their envs). It runs outside
  the minibatch updates' autocast, in fp32 under either ``precision`` (``ppo_family/precision.py``).
"""

from __future__ import annotations

import copy
from typing import Any

import numpy as np
import torch
from ray.rllib.connectors.learner.general_advantage_estimation import GeneralAdvantageEstimation
from ray.rllib.core.columns import Columns
from ray.rllib.evaluation.postprocessing import Postprocessing

from coin_app.algorithms.copo.advantages import (
    COORD_MEAN,
    COORD_STD,
    EGO_ADVANTAGES,
    GLOBAL_ADVANTAGES,
    GLOBAL_TARGETS,
    NEI_ADVANTAGES,
    NEI_TARGETS,
    OLD_GLOBAL_VALUES,
    OLD_NEI_VALUES,
    CoPOAdvantages,
)
from coin_app.algorithms.copo.coordination import gradient_dot, lcf_distribution, lcf_objective
from coin_app.algorithms.ppo_family.learner import OLD_VALUES, ClippedValuePPOLearner, OldValuePredictions, RealRowAdvantages
from coin_app.algorithms.ppo_family.losses import clipped_value_loss, surrogate_loss

POLICY_PREFIXES = ("encoder.actor_encoder.", "pi.")


def policy_parameters(module: Any) -> list[torch.nn.Parameter]:
    """The parameters of a PPO module's policy (actor encoder and action head), in a fixed order."""
    params = [p for name, p in module.named_parameters() if name.startswith(POLICY_PREFIXES)]
    if not params:
        raise ValueError(f"{type(module).__name__} has no separate policy parameters ({', '.join(POLICY_PREFIXES)})")
    return params


def policy_logp(module: Any, obs: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
    """log pi(a | o) of a PPO module's Gaussian policy, with gradient."""
    logits = module.forward_train({Columns.OBS: obs})[Columns.ACTION_DIST_INPUTS]
    return module.get_train_action_dist_cls().from_logits(logits).logp(actions)


class CoPOLearner(ClippedValuePPOLearner):
    """PPO learner of CoPO: coordinated advantage, three value heads, LCF meta-gradient (see module doc)."""

    def build(self) -> None:
        """Build as the clipped-value PPO learner, swap in CoPO's advantage piece, set up the LCF optimizer."""
        super().build()
        cfg = self.config.learner_config_dict
        piece = CoPOAdvantages(
            gamma=self.config.gamma, lambda_=self.config.lambda_, radius=cfg["neighbour_radius"], position_scale=cfg["position_scale"]
        )
        self._learner_connector.insert_before(GeneralAdvantageEstimation, piece)
        self._learner_connector.remove(GeneralAdvantageEstimation)
        self._learner_connector.remove(OldValuePredictions)
        self._learner_connector.remove(RealRowAdvantages)
        self._lcf_params: dict[str, torch.nn.Parameter] = {}
        self._lcf_optimizers: dict[str, torch.optim.Optimizer] = {}
        for mid in self.module.keys():  # on the module's device (``super().build()`` moved the module there)
            module = self.module[mid].unwrapped()
            param = torch.nn.Parameter(module.lcf_params.detach().clone().to(next(module.parameters()).device))
            self._lcf_params[mid] = param
            self._lcf_optimizers[mid] = torch.optim.Adam([param], lr=cfg["lcf_lr"])
        # shuffles and LCF noise draw on the CPU whatever the device (seeded runs draw the same numbers), then move to the data's
        self._meta_generator = torch.Generator(device="cpu").manual_seed(int(self.config.seed or 0))
        self._copo_batch: Any = None
        self._policy_before: dict[str, Any] = {}

    def value_loss(self, module: Any, batch: dict[str, Any], fwd_out: dict[str, Any], config: Any) -> tuple[torch.Tensor, ...]:
        """Sum of the clipped ego, neighbour and global value losses (ego values and targets for the metrics)."""
        v_ego, v_nei, v_glob = module.compute_all_values(batch, fwd_out.get(Columns.EMBEDDINGS))
        clip = config.vf_clip_param
        ego = clipped_value_loss(v_ego, batch[OLD_VALUES], batch[Postprocessing.VALUE_TARGETS], clip)
        nei = clipped_value_loss(v_nei, batch[OLD_NEI_VALUES], batch[NEI_TARGETS], clip)
        glob = clipped_value_loss(v_glob, batch[OLD_GLOBAL_VALUES], batch[GLOBAL_TARGETS], clip)
        extra = {"vf_loss_ego": ego, "vf_loss_nei": nei, "vf_loss_global": glob}
        return ego + nei + glob, v_ego, batch[Postprocessing.VALUE_TARGETS], extra

    def before_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """Freeze a copy of each module's policy as it is before this update (the meta-gradient's old policy)."""
        super().before_gradient_based_update(timesteps=timesteps)
        self._policy_before = {mid: copy.deepcopy(self.module[mid].unwrapped()) for mid in self.module.keys()}

    def _make_batch_if_necessary(self, training_data: Any) -> Any:
        """Build the train batch as RLlib does, keeping it for the meta-gradient step after the epochs."""
        self._copo_batch = super()._make_batch_if_necessary(training_data)
        return self._copo_batch

    def after_gradient_based_update(self, *, timesteps: dict[str, Any]) -> None:
        """The family's KL-coefficient update, then the LCF meta-gradient step on this update's batch."""
        super().after_gradient_based_update(timesteps=timesteps)
        batch, self._copo_batch = self._copo_batch, None
        if batch is None:
            return
        for mid, module_batch in batch.policy_batches.items():
            self.meta_update(mid, module_batch)

    def meta_update(self, module_id: str, batch: Any) -> None:
        """``lcf_num_iters`` passes of the LCF meta-gradient over shuffled minibatches of the batch's real rows."""
        cfg = self.config.learner_config_dict
        module, before = self.module[module_id].unwrapped(), self._policy_before.pop(module_id)
        keys = (Columns.OBS, Columns.ACTIONS, Columns.ACTION_LOGP, GLOBAL_ADVANTAGES, EGO_ADVANTAGES, NEI_ADVANTAGES)
        mask = batch[Columns.LOSS_MASK] if Columns.LOSS_MASK in batch else None
        data = {k: batch[k] if mask is None else batch[k][mask] for k in keys}
        n, device = len(data[Columns.OBS]), data[Columns.OBS].device
        mean, std = float(batch[COORD_MEAN][0]), float(batch[COORD_STD][0])
        size = int(cfg["lcf_minibatch_size"] or self.config.minibatch_size or n)
        new_params, old_params = policy_parameters(module), policy_parameters(before)
        param, optimizer = self._lcf_params[module_id], self._lcf_optimizers[module_id]
        with torch.no_grad():  # the module's buffer is the source of truth (e.g. after a checkpoint restore)
            param.copy_(module.lcf_params)
        scales, objectives = [], []
        for _ in range(int(cfg["lcf_num_iters"])):
            order = torch.randperm(n, generator=self._meta_generator, device="cpu").to(device)
            for start in range(0, n, size):
                mb = {k: v[order[start : start + size]] for k, v in data.items()}
                logp_new = policy_logp(module, mb[Columns.OBS], mb[Columns.ACTIONS])
                new_loss = surrogate_loss(logp_new, mb[Columns.ACTION_LOGP], mb[GLOBAL_ADVANTAGES], self.config.clip_param)
                old_logp = policy_logp(before, mb[Columns.OBS], mb[Columns.ACTIONS]).mean()
                scale = gradient_dot(new_loss, new_params, old_logp, old_params)
                noise = torch.randn(len(mb[Columns.OBS]), generator=self._meta_generator, device="cpu").to(device)
                objective = lcf_objective(param, mb[EGO_ADVANTAGES], mb[NEI_ADVANTAGES], mean, std, noise)
                optimizer.zero_grad()
                (scale * objective).backward()
                optimizer.step()
                scales.append(float(scale))
                objectives.append(float(objective.detach()))
        with torch.no_grad():
            module.lcf_params.copy_(param)
            lcf_mean, lcf_std = lcf_distribution(param)
        self.metrics.log_dict(
            {
                "lcf_mean": float(lcf_mean),
                "lcf_std": float(lcf_std),
                "lcf_meta_scale": float(np.mean(scales)) if scales else 0.0,
                "lcf_objective": float(np.mean(objectives)) if objectives else 0.0,
                "coordinated_advantage_mean": mean,
                "coordinated_advantage_std": std,
            },
            key=module_id,
            window=1,
        )

    def lcf_distribution(self, module_id: str) -> tuple[float, float]:
        """The current LCF (mean, std) of a module."""
        return self.module[module_id].unwrapped().lcf_distribution()
