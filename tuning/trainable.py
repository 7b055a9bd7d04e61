"""The Tune trainable of every sweep: one coin_app training run (any registry algorithm) per trial.

A class trainable, so Tune's own ``CheckpointConfig`` (frequency, keep-N, at end) and
``Tuner.restore`` apply. Each ``step`` is one RLlib iteration and reports
``training.iteration_metrics`` (env steps, returns, agent outcomes, learner losses, periodic
validation metrics; the trial's last iteration is evaluated too) with the trial's ``cpu_s`` and ``wall_s``
(``training.loop.RunClock``, carried over a restore by the checkpoint's metadata: the trial's process and its children,
not remote env runners or learners, which Ray starts elsewhere); the trial is done once ``steps`` env steps are sampled. Checkpoints are
coin_app checkpoints (RLlib's layout plus ``coin_app.json``), so ``python -m coin_app
evaluate|export`` take any of them directly.

Resources: a trial reserves what its RLlib config asks for (:func:`trial_resources`, RLlib's own
``Algorithm.default_resource_request``): one bundle for the trial's process (with the learner's
GPUs when ``num_learners=0``), one CPU bundle per remote env runner and one bundle per remote
learner (``num_gpus_per_learner`` GPUs each). Tune starts the trial in the first bundle and RLlib's
env runner and learner actors in the others (Tune's placement groups capture child actors).
``--set num_learners=1 num_gpus_per_learner=1`` thus reserves one GPU per trial
(``coin_app.algorithms.registry.LEARNER_KEYS``).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from ray import tune
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.tune import PlacementGroupFactory

from coin_app.algorithms.checkpoint_files import verify
from coin_app.training import build_config, checkpoint_meta, iteration_metrics, save
from coin_app.training.checkpoints import check_restorable
from coin_app.training.loop import RunClock
from coin_app.training.monitor import EVAL_RESULT_KEY, validation_metrics
from tuning.experiment import trial_overrides


def build_trial_config(config: dict[str, Any]) -> AlgorithmConfig:
    """The validated RLlib config of one trial (raises ValueError naming any bad value)."""
    return build_config(config["algo"], config["scenario"], trial_overrides(config), int(config["seed"]))


def trial_resources(config: dict[str, Any]) -> PlacementGroupFactory:
    """The placement group one trial reserves: its process, remote env runners and remote learners (see module doc)."""
    cfg = build_trial_config(config)
    return cfg.algo_class.default_resource_request(cfg)


def trial_gpus(config: dict[str, Any]) -> float:
    """GPUs one trial reserves, all bundles together."""
    return float(sum(bundle.get("GPU", 0) for bundle in trial_resources(config).bundles))


class CoinTrial(tune.Trainable):
    """One trial: build the algorithm from the trial config, train it iteration by iteration, checkpoint it."""

    @classmethod
    def default_resource_request(cls, config: dict[str, Any]) -> Any:
        """The placement group the algorithm needs (main process, env runners, learners)."""
        if not isinstance(config, dict) or "algo" not in config:  # Tune also asks with partial configs
            return None
        return trial_resources(config)

    def setup(self, config: dict[str, Any]) -> None:
        """Build the algorithm; remember what every checkpoint's metadata says."""

        self.steps = int(config["steps"])
        self.last: dict[str, Any] = {}
        self.clock = RunClock()  # the trial's CPU and wall seconds, every segment (a restore carries them over)
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
        result = self.algo.train()
        done = int(self.algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0)) >= self.steps
        if done and getattr(self.algo.config, "eval_every", 0) and EVAL_RESULT_KEY not in result:
            # the last iteration is evaluated too, so the final checkpoint has the score its siblings are kept by (keep_best)
            result[EVAL_RESULT_KEY] = validation_metrics(self.algo)
        self.last = iteration_metrics(result) | self.clock.read()
        return self.last | {"done": done}

    def save_checkpoint(self, checkpoint_dir: str) -> None:
        """Write a coin_app checkpoint (algorithm state and metadata) into Tune's checkpoint directory."""

        # the trained env steps (what evaluation tables report) and the trial's clocks so far
        meta = self.meta | {"env_steps": int(self.last.get("env_steps", 0))} | self.clock.read()
        save(self.algo, Path(checkpoint_dir), meta, atomic=False)  # Tune made this directory for this save

    def load_checkpoint(self, checkpoint: str) -> None:
        """Restore the algorithm (weights, optimizers, replay buffer, counters) from a verified checkpoint."""
        meta = verify(Path(checkpoint))  # a torn or altered checkpoint is refused by name
        method = self.config["algo"]
        check_restorable(self.algo, Path(checkpoint), meta, f"sweep --resume --restart {method} (reruns its trials with this code)")
        self.algo.restore_from_path(str(Path(checkpoint).resolve()))
        self.clock = RunClock(meta)  # continues the checkpoint's cpu_s and wall_s
        self.last = {"env_steps": int(self.algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))}

    def cleanup(self) -> None:
        """Stop the algorithm's env runners and learners."""
        self.algo.stop()
