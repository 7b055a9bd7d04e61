"""Training: the validated config of a run, the train loop, checkpoints, iteration metrics and periodic evaluation.

``config.build_config`` is where a run is set up: the seed is checked, ``--set`` overrides are routed
(``registry.split_overrides``), the scenario config is parsed **once** into a frozen
``ScenarioConfig`` / ``ArenaConfig`` and handed to the algorithm's spec, and the callbacks
every run gets are attached (agent outcomes; periodic evaluation for algorithms that declare
it). ``loop.train`` runs RLlib iterations until an env-step or wall-time budget, logs one line per
iteration (``monitor``) and writes coin_app checkpoints (RLlib's layout plus ``coin_app.json``; ``checkpoints``).
"""

from coin_app.training.address import check_address
from coin_app.training.checkpoints import check_restorable, check_resume, check_run_dir, checkpoint_meta, clear_run, save
from coin_app.training.config import build_config, fresh_module, with_env_runner
from coin_app.training.loop import (
    RAY_LOG,
    STOPPED_AT_BUDGET,
    STOPPED_AT_MAX_CPU,
    STOPPED_AT_MAX_MINUTES,
    TENSORBOARD_DIR,
    Interrupted,
    StopRequest,
    stop_on_signal,
    train,
)
from coin_app.training.monitor import (
    COLLAPSED_ACTION_STD,
    CRITIC_LOSS_KEYS,
    EVAL_RESULT_KEY,
    FreezeDetector,
    PeriodicEvaluation,
    RunProgress,
    evaluate_algorithm,
    iteration_metrics,
    outcome_text,
    ray_noise_to,
)

__all__ = [
    "COLLAPSED_ACTION_STD",
    "CRITIC_LOSS_KEYS",
    "EVAL_RESULT_KEY",
    "RAY_LOG",
    "STOPPED_AT_BUDGET",
    "STOPPED_AT_MAX_CPU",
    "STOPPED_AT_MAX_MINUTES",
    "TENSORBOARD_DIR",
    "FreezeDetector",
    "Interrupted",
    "PeriodicEvaluation",
    "RunProgress",
    "StopRequest",
    "build_config",
    "check_address",
    "check_restorable",
    "check_resume",
    "check_run_dir",
    "checkpoint_meta",
    "clear_run",
    "evaluate_algorithm",
    "fresh_module",
    "iteration_metrics",
    "outcome_text",
    "ray_noise_to",
    "save",
    "stop_on_signal",
    "train",
    "with_env_runner",
]
