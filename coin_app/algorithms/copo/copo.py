"""CoPO: its RLlib config (settings and spec: ``settings.py``) and the algorithm that keeps the LCF distribution in sync.

CoPO (Peng et al., "Learning to Simulate Self-Driven Particles System with Coordinated Policy
Optimization", NeurIPS 2021; docs/guides/ppo-family.md) is the PPO family's IPPO with local
coordination factors (LCF): every agent's observation ends with its LCF, the policy learns on
the coordinated advantage of its ego and neighbour rewards, and a meta-gradient moves the LCF
distribution towards the global reward (``learner.py``, ``coordination.py``). Its
settings are IPPO's plus ``CopoSettings``' (``settings.py``).

The learner's meta-gradient step moves the distribution after each update; before sampling and
right after each update the algorithm sets it on every env (local and remote runners, all
vectorized sub-envs), so agents spawned from then on draw their LCF from the new distribution.

At evaluation (``eval_lcf``, stored in the module's config and so in every checkpoint) each
vehicle draws its own LCF from the learned distribution, as CoPO's evaluation did, or every
vehicle gets the learned mean (``rl_module.py``; ``docs/decisions.md`` §7.5).
"""

from __future__ import annotations

from typing import Any

from ray.rllib.algorithms.ppo import PPO, PPOConfig
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.adapters.rllib_env import env_config_of
from coin_app.algorithms.common import SHARED_MODULE_ID, set_on_envs, shared_policy_config
from coin_app.algorithms.copo.learner import CoPOLearner
from coin_app.algorithms.copo.rl_module import CoPOModule
from coin_app.algorithms.copo.settings import CopoSettings
from coin_app.algorithms.ppo_family.config import (
    checked,
    driving_scenario,
    learner_options,
    policy_model,
    ppo_base_config,
    ppo_settings,
)
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.road_map import load_map


class CoPO(PPO):
    """RLlib PPO whose training step also keeps the env runners' LCF distribution in sync with the learner."""

    def lcf_distribution(self) -> tuple[float, float]:
        """The learner's current LCF (mean, std)."""
        results = self.learner_group.foreach_learner(lambda learner: learner.lcf_distribution(SHARED_MODULE_ID))
        return next(iter(results)).get()

    def push_lcf_distribution(self) -> tuple[float, float]:
        """Set the learner's LCF distribution on every env runner's envs; returns it."""
        mean, std = self.lcf_distribution()
        self.env_runner_group.foreach_env_runner(
            lambda runner: set_on_envs(runner, "set_lcf_distribution", mean, std), local_env_runner=True
        )
        return mean, std

    def training_step(self) -> None:
        """Push the LCF distribution, run PPO's training step (update + meta-gradient), push again."""
        self.push_lcf_distribution()
        super().training_step()
        mean, std = self.push_lcf_distribution()
        self.metrics.log_dict({"lcf_mean": mean, "lcf_std": std}, key="copo", window=1)


def build_copo_config(scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """CoPO: IPPO's settings plus LCFs in the envs, three value heads, the coordinated advantage and the LCF meta-gradient."""
    hp = ppo_settings(CopoSettings, algo_cfg)
    radius, mean, std = hp.neighbour_radius, hp.initial_lcf_mean, hp.initial_lcf_std
    scenario = driving_scenario("CoPO", scenario)
    learner_config = {
        **learner_options(hp),
        "lcf_lr": hp.lcf_lr,
        "lcf_num_iters": hp.lcf_num_iters,
        "lcf_minibatch_size": hp.lcf_minibatch_size,
        "neighbour_radius": float(radius),
        "position_scale": load_map(scenario.scenario).scale,
    }
    model = {**policy_model(hp.hidden, hp.weight_init), "initial_lcf": [float(mean), float(std)], "eval_lcf": hp.eval_lcf}
    env_config = env_config_of(scenario, lcf={"mean": float(mean), "std": float(std)})
    config = (
        ppo_base_config(scenario, hp, seed, env_config, algo_class=CoPO)
        .learners(learner_class=CoPOLearner, learner_config_dict=learner_config)
        .rl_module(model_config=model, rl_module_spec=RLModuleSpec(module_class=CoPOModule))
    )
    config = shared_policy_config(config)
    errors = []
    if config.num_learners > 1:
        errors.append(f"num_learners={config.num_learners}; allowed: 0 or 1 (one LCF distribution, one meta-gradient)")
    return checked("COPO", config, errors)
