"""nav_ppo's learner: RLlib's PPO learner with the family's ``precision`` option (``ppo_family/precision.py``) and fixed agent order.

With ``bc_weight`` > 0 (set by ``NavPPO`` before each iteration from ``bc_coeff``) the loss also
pulls the policy mean toward the scripted driver's actions at the minibatch's observations
(``warm_start.bc_loss``), each batch row labelled once however many epochs revisit it (``TeacherLabels``).
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner
from ray.rllib.core.columns import Columns

from coin_app.algorithms.gradient_step import FastGradientStep
from coin_app.algorithms.nav_ppo.warm_start import TeacherLabels, bc_loss, teacher
from coin_app.algorithms.ppo_family.agent_order import fix_agent_order
from coin_app.algorithms.ppo_family.precision import MixedPrecisionLearner


class NavPPOLearner(MixedPrecisionLearner, FastGradientStep, PPOTorchLearner):
    """RLlib's PPO-Clip learner; ``learner_config_dict["precision"]`` "bf16" runs each minibatch's forward pass and loss in bf16."""

    def build(self) -> None:
        """Build as RLlib's PPO learner, with the agents of every episode in a fixed order (``agent_order.py``)."""
        super().build()
        fix_agent_order(self)
        self.bc_weight = 0.0
        self.bc_labels = TeacherLabels(teacher(self.config.learner_config_dict))  # the driver is fixed for the run

    def set_bc_weight(self, weight: float) -> None:
        """The teacher loss's weight for the next training batch (whose observations are new: the label cache empties)."""
        self.bc_weight = float(weight)
        self.bc_labels.clear()

    def compute_loss_for_module(self, *, module_id: str, config: Any, batch: dict[str, Any], fwd_out: dict[str, Any]) -> Any:
        """PPO's loss, plus ``bc_weight`` times the gap to the scripted driver's actions when that weight is above 0."""
        loss = super().compute_loss_for_module(module_id=module_id, config=config, batch=batch, fwd_out=fwd_out)
        if self.bc_weight > 0:
            gap = bc_loss(batch[Columns.OBS], fwd_out[Columns.ACTION_DIST_INPUTS], batch.get(Columns.LOSS_MASK), self.bc_labels)
            self.metrics.log_value((module_id, "bc_loss"), gap.detach(), window=1)
            loss = loss + self.bc_weight * gap
        return loss
