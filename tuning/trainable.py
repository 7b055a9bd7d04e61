"""The Tune trainable of every sweep: one coin_app training run (any registry algorithm) per trial.

A class trainable, so Tune's own ``CheckpointConfig`` (frequency, keep-N, at end) and
``Tuner.restore`` apply. Each ``step`` is one RLlib iteration and reports
``training.iteration_metrics`` (env steps, returns, agent outcomes, learner losses, periodic
validation metrics); the trial is done once ``steps`` env steps are sampled. Checkpoints are
coin_app checkpoints (RLlib's layout plus ``coin_app.json``), so ``python -m coin_app
evaluate|export`` take any of them directly.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ray import tune

from coin_app.training import build_config, checkpoint_meta, iteration_metrics, save
from tuning.experiment import trial_overrides


def build_trial_config(config: dict[str, Any]) -> Any:
    """The validated RLlib config of one trial (raises ValueError naming any bad value)."""

    return build_config(config["algo"], config["scenario"], trial_overrides(config), int(config["seed"]))


class CoinTrial(tune.Trainable):
    """One trial: build the algorithm from the trial config, train it iteration by iteration, checkpoint it."""

    @classmethod
    def default_resource_request(cls, config: dict[str, Any]) -> Any:
        """The placement group the algorithm needs (main process, env runners, learners)."""
        if not isinstance(config, dict) or "algo" not in config:  # Tune also asks with partial configs
            return None
        rllib_config = build_trial_config(config)
        return rllib_config.algo_class.default_resource_request(rllib_config)

    def setup(self, config: dict[str, Any]) -> None:
        """Build the algorithm; remember what every checkpoint's metadata says."""

        self.steps = int(config["steps"])
        self.last: dict[str, Any] = {}
        self.algo = build_trial_config(config).build_algo()
        self.meta = checkpoint_meta(
            config["algo"],
            config["scenario"],
            int(config["seed"]),
            trial_overrides(config),
            experiment=config["experiment"],
            variant=config["variant"],
        )

    def step(self) -> dict[str, Any]:
        """One RLlib training iteration; done once ``steps`` env steps are sampled."""

        sampled = int(self.algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))
        if sampled >= self.steps and self.last:  # restored at or past the budget (a resume right after the last step)
            return self.last | {"done": True}
        self.last = iteration_metrics(self.algo.train())
        return self.last | {"done": self.last["env_steps"] >= self.steps}

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        """Write a coin_app checkpoint (algorithm state and metadata) into Tune's checkpoint directory."""

        save(self.algo, Path(checkpoint_dir), self.meta)

    def load_checkpoint(self, checkpoint: str) -> None:
        """Restore the algorithm (weights, optimizers, replay buffer, counters) from a checkpoint."""
        self.algo.restore_from_path(str(Path(checkpoint).resolve()))
        self.last = {"env_steps": int(self.algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))}

    def cleanup(self) -> None:
        """Stop the algorithm's env runners and learners."""
        self.algo.stop()
