"""nav_ppo's learner: RLlib's PPO learner with the family's ``precision`` option (``ppo_family/precision.py``), nothing else."""

from __future__ import annotations

from ray.rllib.algorithms.ppo.torch.ppo_torch_learner import PPOTorchLearner

from coin_app.algorithms.ppo_family.precision import MixedPrecisionLearner


class NavPPOLearner(MixedPrecisionLearner, PPOTorchLearner):
    """RLlib's PPO-Clip learner; ``learner_config_dict["precision"]`` "bf16" runs each minibatch's forward pass and loss in bf16."""
