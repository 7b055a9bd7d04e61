"""nav_ppo's settings (the PPO core, ``ppo_family/settings.py``, with the seed-2 paper's values, its stages and options) and spec."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

from coin_app.algorithms.checks import Rule, choice, non_negative, positive, unit
from coin_app.algorithms.choices import NAV_WARM_STARTS
from coin_app.algorithms.ppo_family.settings import PpoCore
from coin_app.algorithms.settings import redeclare, setting
from coin_app.algorithms.spec import AlgorithmSpec, Capabilities

# the training stages and the arena scenario mix each trains on (beneath the user's arena --set values)
STAGES: dict[str, dict[str, Any]] = {
    "long": {"num_vehicles": 4, "num_obstacles": 3, "generator": "agnn"},
    "short": {"num_vehicles": 1, "max_vehicles": 8, "num_obstacles": 0, "max_obstacles": 8, "generator": "short"},
}

WARM = "the warm start (nav_ppo/warm_start.py)"
ALGO = "NavPPO.training_step (nav_ppo/config.py)"


@dataclass(frozen=True)
class NavPpoSettings(PpoCore):
    """PPO-Clip on the arena for one stage: the paper's update (no KL term, no value clip) and the project's options."""

    clip_param: float = redeclare(PpoCore, "clip_param", 0.2, "PPO ratio clip (epsilon)")
    vf_loss_coeff: float = redeclare(PpoCore, "vf_loss_coeff", 0.5, "c1, weight of the value loss")
    entropy_coeff: float = redeclare(PpoCore, "entropy_coeff", 0.0, "c2, entropy bonus")
    train_batch_size_per_learner: int = redeclare(PpoCore, "train_batch_size_per_learner", 2048, "env steps per training batch")
    minibatch_size: int = redeclare(PpoCore, "minibatch_size", 256)
    num_epochs: int = redeclare(PpoCore, "num_epochs", 10)
    hidden: int = redeclare(PpoCore, "hidden", 256, "width of the two tanh layers of the separate policy and value networks (paper: 256)")
    num_env_runners: int = redeclare(PpoCore, "num_env_runners", 0, "remote env runners (0 = sample in the training process)")
    stage: str = setting(
        "long",
        choice(*STAGES),
        "training stage: 'long' (4 vehicles, 3 obstacles) or 'short' (1-8 vehicles, 0-8 obstacles, starts near targets)",
        reads="the arena's scenario mix (STAGES)",
    )
    log_std_init: float = setting(
        0.0,
        Rule("float", -5.0, 2.0),
        "added to the policy's initial log std outputs: the initial action std is about e^x (0: the default init)",
        reads="the RLModule (ppo_family/rl_module.py)",
    )
    log_std_min: float | None = setting(
        None,
        Rule("float", -5.0, 2.0, also=(None,)),
        "floor on the policy's log std in every forward pass: the action std never falls below e^x (None: no floor, the "
        "paper; at most log_std_init)",
        reads="the RLModule (ppo_family/rl_module.py)",
    )
    curriculum_steps: int = setting(
        0,
        non_negative("int"),
        "stage=short: env steps over which the start spread (start_difficulty) rises linearly from curriculum_start to 1 "
        "(0 = no curriculum, the paper)",
        reads=ALGO,
    )
    curriculum_start: float = setting(
        0.2, unit(lo_open=True), "stage=short: the start spread (start_difficulty) at env step 0 of a curriculum", reads=ALGO
    )
    warm_start: str = setting(
        "none",
        choice(*NAV_WARM_STARTS),
        "'heuristic', 'avoiding' or 'planning' = before the first PPO iteration, clone that scripted arena driver (the plain "
        "one, the one that swerves from the closest entity, or the plain one behind a rollout safety filter) on the stage's "
        "scenario mix (warm_start.py; not in the paper); "
        "'none' = from scratch (the paper)",
        reads=WARM,
    )
    warm_start_episodes: int = setting(
        200, positive("int"), "warm start: scenarios the scripted driver drives (every second one with action noise)", reads=WARM
    )
    warm_start_noise: float = setting(
        0.3, non_negative(), "warm start: std of the Gaussian noise on the driver's actions in the noisy scenarios", reads=WARM
    )
    warm_start_epochs: int = setting(
        10, non_negative("int"), "warm start: passes over the demonstrations (minibatches of 512, Adam 1e-3)", reads=WARM
    )
    warm_start_rounds: int = setting(
        1,
        positive("int"),
        "warm start: 1 = clone the driver's demonstrations; R > 1 = then R - 1 DAgger rounds, each as many scenarios driven "
        "by the clone, labelled by the driver, added to the demonstrations and fitted again (warm_start.py)",
        reads=WARM,
    )
    warm_start_weight: float = setting(
        1.0,
        positive(),
        "warm start: weight of the rows where the driver's label differs from the plain heuristic's action (the avoiding "
        "driver's reflex, the planning driver's safety filter) in the clone's action loss (1 = all rows alike; warm_start.py)",
        reads=WARM,
    )
    bc_coeff: float = setting(
        0.0,
        non_negative(),
        "weight of an auxiliary loss pulling the policy mean toward the scripted driver's actions at each minibatch's "
        "observations (the warm start's driver, else the plain heuristic; warm_start.py; not in the paper; 0 = off)",
        reads="the learner (nav_ppo/learner.py)",
    )
    bc_steps: int = setting(0, non_negative("int"), "env steps over which bc_coeff falls linearly to 0 (0 = constant)", reads=ALGO)


DEFAULT = NavPpoSettings()
PRESETS: dict[str, NavPpoSettings] = {
    "quick": replace(DEFAULT, hidden=64),
    # the smallest scale (registry.tiny_settings, which adds the arena's short episodes): one epoch of two minibatches
    "tiny": replace(DEFAULT, train_batch_size_per_learner=100, minibatch_size=50, num_epochs=1, hidden=16),
}


def stage_of(algo_cfg: Mapping[str, Any]) -> str:
    """The training stage of nav_ppo's ``--set`` values (default ``"long"``); a ValueError if it is not one of ``STAGES``."""
    return NavPpoSettings.of({"stage": algo_cfg["stage"]} if "stage" in algo_cfg else {}).stage


def stage_scenario(algo_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """The arena values of the stage's scenario mix (beneath the user's arena ``--set`` values)."""
    return dict(STAGES[stage_of(algo_cfg)])


NAV_PPO = AlgorithmSpec(
    name="nav_ppo",
    description="seed-2 paper: PPO-Clip navigation (--set stage=long) and parking (stage=short) policies on the arena",
    build="coin_app.algorithms.nav_ppo.config:build_nav_ppo_config",
    capabilities=Capabilities(on_policy=True, centralized_critic=False, joint_replay=False),
    scenarios=("arena",),
    settings=NavPpoSettings,
    presets=PRESETS,
    scenario_defaults=stage_scenario,
)
