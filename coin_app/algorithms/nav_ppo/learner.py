"""nav_ppo's learner: RLlib's PPO learner with the family's ``precision`` option (``ppo_family/precision.py``) and fixed agent order."""

from __future__ import annotations

from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner

from coin_app.algorithms.ppo_family.agent_order import fix_agent_order
from coin_app.algorithms.ppo_family.precision import MixedPrecisionLearner


class NavPPOLearner(MixedPrecisionLearner, PPOTorchLearner):
    """RLlib's PPO-Clip learner; ``learner_config_dict["precision"]`` "bf16" runs each minibatch's forward pass and loss in bf16."""

    def build(self) -> None:
        """Build as RLlib's PPO learner, with the agents of every episode in a fixed order (``agent_order.py``)."""
        super().build()
        fix_agent_order(self)
