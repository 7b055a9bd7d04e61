"""CoPO as an RLlib algorithm: PPO's training step, with the LCF distribution pushed to every env runner's envs.

The learner's meta-gradient step moves the distribution after each update; before sampling and
right after each update the algorithm sets it on every env (local and remote runners, all
vectorized sub-envs), so agents spawned from then on draw their LCF from the new distribution.
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.ppo import PPO

from coin_app.algorithms.common import SHARED_MODULE_ID, coin_envs


def _set_lcf(env_runner: Any, mean: float, std: float) -> int:
    """Set the LCF distribution on every coin env of an env runner; returns how many."""
    envs = coin_envs(env_runner)
    for env in envs:
        env.set_lcf_distribution(mean, std)
    return len(envs)


class CoPO(PPO):
    """RLlib PPO whose training step also keeps the env runners' LCF distribution in sync with the learner."""

    def lcf_distribution(self) -> tuple[float, float]:
        """The learner's current LCF (mean, std)."""
        results = self.learner_group.foreach_learner(lambda learner: learner.lcf_distribution(SHARED_MODULE_ID))
        return next(iter(results)).get()

    def push_lcf_distribution(self) -> tuple[float, float]:
        """Set the learner's LCF distribution on every env runner's envs; returns it."""
        mean, std = self.lcf_distribution()
        self.env_runner_group.foreach_env_runner(lambda runner: _set_lcf(runner, mean, std), local_env_runner=True)
        return mean, std

    def training_step(self) -> None:
        """Push the LCF distribution, run PPO's training step (update + meta-gradient), push again."""
        self.push_lcf_distribution()
        super().training_step()
        mean, std = self.push_lcf_distribution()
        self.metrics.log_dict({"lcf_mean": mean, "lcf_std": std}, key="copo", window=1)
