"""nav_ppo: RLlib PPO (new API stack, one shared policy) on the arena, one training stage at a time.

The paper (§III-C, §IV) trains two PPO-Clip models with ``[256, 256]`` networks: a long-range
one on scenarios of 4 vehicles and 3 obstacles, and a short-range (parking) one on 1–8 vehicles
and 0–8 obstacles; at run time the short-range one drives inside ``switch_radius`` of the
target (``coin_app.inference.switching``). ``--set stage=long|short`` picks the stage; its
scenario mix is ``STAGES[stage]``, the spec's scenario defaults (any arena key in ``--set``
overrides it; the arena config is parsed once, before the builder sees it). The short stage
starts vehicles within the switching radius of their targets (``generator="short"``), the
part of the task that policy will see.

The paper gives no PPO hyper-parameters beyond the loss (clip + value + entropy, no KL term);
ours are Stable-Baselines3's PPO defaults with a larger minibatch for speed, all in
``NavPpoSettings`` (``settings.py``). Where the paper trains one "primary" vehicle and copies its policy to
the others, every vehicle here trains the one shared policy (parameter sharing): the same
policy for all, without discarding the other vehicles' experience.

Options for the parking stage, off by default (the paper's setting): a lower initial action std
(``log_std_init``) and a floor under it (``log_std_min``), a start-spread curriculum (``curriculum_steps``), a warm start that clones
the scripted driver before the first PPO iteration (``warm_start="heuristic"``, ``warm_start.py``)
and an auxiliary loss toward the driver's actions during PPO (``bc_coeff``, ``bc_steps``).

The learner is RLlib's PPO learner with the PPO family's ``precision`` option (``learner.py``):
"bf16" runs each minibatch's forward pass and loss under bfloat16 autocast.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any

from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.utils.metrics import ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME

from coin_app.adapters.rllib_env import env_config_of, env_id_of, parse_env_config
from coin_app.algorithms.checkpoint_files import SHARED_MODULE_ID
from coin_app.algorithms.common import set_on_envs, shared_policy_config
from coin_app.algorithms.nav_ppo.learner import NavPPOLearner
from coin_app.algorithms.nav_ppo.settings import NavPpoSettings, stage_of
from coin_app.algorithms.nav_ppo.warm_start import bc_weight, warm_start
from coin_app.algorithms.ppo_family.agent_order import acting_order
from coin_app.algorithms.ppo_family.config import policy_model
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule
from coin_app.sim.arena.config import ArenaConfig

# the learner's keys (its learner_config_dict): the warm start's and the teacher loss's, named by their prefixes
WARM_KEYS = tuple(k for k in NavPpoSettings.keys() if k.startswith(("warm_start", "bc_")))


def progress(line: str) -> None:
    """One progress line of a long phase on standard output (the warm start's rounds)."""
    print(line, flush=True)


def curriculum_difficulty(env_steps: int, steps: int, start: float) -> float:
    """The short stage's start spread after ``env_steps``: ``start`` rising linearly to 1 over ``steps`` (1 when ``steps`` is 0)."""
    if steps <= 0:
        return 1.0
    return min(1.0, start + (1.0 - start) * env_steps / steps)


class NavPPO(PPO):
    """RLlib PPO whose training step first warm-starts the policy (once) and moves the short stage's curriculum."""

    def training_step(self) -> Any:
        """The optional warm start before the first samples, then every env runner's start spread, then PPO's step."""
        cfg = self.config.learner_config_dict
        done = int(self.metrics.peek((ENV_RUNNER_RESULTS, NUM_ENV_STEPS_SAMPLED_LIFETIME), default=0))
        if cfg.get("warm_start", "none") != "none" and done == 0:
            self._warm_start(cfg)
        if cfg.get("bc_coeff", 0.0) > 0:
            weight = bc_weight(done, cfg["bc_coeff"], cfg["bc_steps"])
            self.learner_group.foreach_learner(lambda learner: learner.set_bc_weight(weight))
            self.metrics.log_value("bc_weight", weight, window=1)
        if cfg.get("curriculum_steps", 0) > 0:
            difficulty = curriculum_difficulty(done, cfg["curriculum_steps"], cfg["curriculum_start"])
            self.env_runner_group.foreach_env_runner(
                lambda runner: set_on_envs(runner, "set_start_difficulty", difficulty), local_env_runner=True
            )
            self.metrics.log_value("start_difficulty", difficulty, window=1)
        return super().training_step()

    def _warm_start(self, cfg: Mapping[str, Any]) -> None:
        """Clone the scripted driver into every learner's module (``warm_start.py``) and send the weights to the env runners."""
        scenario, _ = parse_env_config(self.config.env_config)
        scenario = dataclasses.replace(scenario, start_difficulty=1.0)  # the whole start spread, whatever a curriculum's start
        seed = int(self.config.seed or 0)
        options = {
            "driver": cfg["warm_start"],
            "episodes": cfg["warm_start_episodes"],
            "noise": cfg["warm_start_noise"],
            "epochs": cfg["warm_start_epochs"],
            "log_std": cfg["log_std_init"],
            "seed": seed,
            "gamma": self.config.gamma,
            "rounds": cfg["warm_start_rounds"],
            "weight": cfg["warm_start_weight"],
        }

        def fit(learner: Any) -> tuple[dict[str, float], list[tuple[float, int]]]:
            losses, rounds = warm_start(learner.module[SHARED_MODULE_ID], scenario, **options, log=progress)
            return losses, [(demos.success_rate, len(demos.obs)) for demos in rounds]

        # every learner runs the same seeded warm start (the demonstrations are generated in the learner's process)
        losses, rounds = next(iter(self.learner_group.foreach_learner(fit))).get()
        self.env_runner_group.sync_weights(from_worker_or_learner_group=self.learner_group, inference_only=True)
        stats = {"warm_start_demo_success": rounds[0][0], "warm_start_samples": sum(n for _, n in rounds), **losses}
        if len(rounds) > 1:
            stats["warm_start_clone_success"] = rounds[-1][0]  # the clone driving the last DAgger round (half with noise)
        for key, value in stats.items():
            self.metrics.log_value(f"warm_start/{key}", value, window=1)


def build_nav_ppo_config(scenario: ArenaConfig, algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """RLlib PPO-Clip on the arena for one stage (see module doc)."""
    if not isinstance(scenario, ArenaConfig):
        raise ValueError(f"nav_ppo trains on the arena only, got {type(scenario).__name__}; allowed: an ArenaConfig")
    stage = stage_of(algo_cfg)  # the stage's scenario mix is in ``scenario`` already (the spec's scenario_defaults)
    hp = {k: v for k, v in NavPpoSettings.of(algo_cfg).values().items() if k != "stage"}
    precision = hp.pop("precision")
    curriculum = {"curriculum_steps": hp.pop("curriculum_steps"), "curriculum_start": hp.pop("curriculum_start")}
    warm = {k: hp.pop(k) for k in WARM_KEYS}
    warm["log_std_init"] = hp["log_std_init"]
    floor = hp.pop("log_std_min")
    if floor is not None and floor > hp["log_std_init"]:
        raise ValueError(f"log_std_min={floor} is above log_std_init={hp['log_std_init']}; allowed: a floor at most log_std_init")
    if curriculum["curriculum_steps"] > 0:
        if stage != "short" or scenario.generator != "short":
            raise ValueError(
                f"curriculum_steps={curriculum['curriculum_steps']} narrows the short stage's starts; "
                f"allowed with stage=short (generator 'short'), got stage={stage!r}, generator {scenario.generator!r}"
            )
        scenario = dataclasses.replace(scenario, start_difficulty=curriculum["curriculum_start"])  # the first iteration's spread
    model = policy_model(hp.pop("hidden"), "torch") | {"log_std_init": hp.pop("log_std_init"), "log_std_min": floor}
    config = (
        PPOConfig(algo_class=NavPPO)
        .environment(env_id_of(scenario), env_config=env_config_of(scenario))
        .env_runners(num_env_runners=hp.pop("num_env_runners"), env_to_module_connector=acting_order)  # fixed agent order
        .training(**hp, use_kl_loss=False, vf_clip_param=1e6)  # PPO-Clip: no KL term, no value clipping
        .learners(learner_class=NavPPOLearner, learner_config_dict={"precision": precision, **curriculum, **warm})
        .rl_module(model_config=model, rl_module_spec=RLModuleSpec(module_class=PPOActorModule))
        .debugging(seed=seed)
        .evaluation(evaluation_interval=None)
    )
    return shared_policy_config(config)
