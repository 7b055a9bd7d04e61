"""IPPO, CPPO and MFPO: their RLlib configs (their settings, presets and specs: ``settings.py``).

Values are those of the PPO baselines of the COIN paper, which ran CoPO's code (Peng et al.,
"Learning to Simulate Self-Driven Particles System with Coordinated Policy Optimization",
NeurIPS 2021) on Ray 1.2's PPO, as the MetaDrive benchmark did (docs/guides/ppo-family.md;
``docs/decisions.md`` §7). ``train_batch_size`` counts env steps (each gives one transition per
present agent). Ray 1.x sampled 200-step chunks on 4 workers until at least 1024 env steps
were in: 2 rounds, 1600 env steps per update. The defaults are that batch in 200-step chunks
(``rollout_fragment_length``); sampling runs in the training process (``num_env_runners`` 0,
one env), and ``num_env_runners=4`` (set at the sweeps' ``paper`` scale) adds the reference's
four sampling workers. RLlib 2.60 accepts any batch that is a whole number of
runners x chunk (``"auto"`` = the batch split over the runners).

The other reference behaviours are defaults too, each with RLlib's behaviour as an option:
``kl_signal`` (the adaptive-KL step reads the mean KL of the last SGD epoch, Ray 1.x, or the
last minibatch's, RLlib), ``timeout_bootstrap`` (a vehicle's own step limit is terminal, Ray
1.x, or bootstraps V(o_T), RLlib) and ``weight_init`` (Ray 1.x's normc, or PyTorch's
default). See ``learner.py`` and ``rl_module.py``. ``precision`` "bf16" runs the learner's SGD
forward passes in bfloat16 (``precision.py``); the default "fp32" is RLlib's update.

The helpers (``ppo_settings``, ``policy_model``, ``ppo_base_config``, ``learner_options``,
``checked``) are shared with CoPO (``coin_app.algorithms.copo.copo``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, TypeVar

from ray.rllib.algorithms.algorithm import Algorithm
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig
from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.adapters.rllib_env import env_config_of, env_id_of
from coin_app.algorithms.common import backend_errors, shared_policy_config
from coin_app.algorithms.ppo_family.agent_order import acting_order
from coin_app.algorithms.ppo_family.centralized import CentralizedCriticPPOLearner, CentralizedCriticPPOModule, critic_input_dim
from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule
from coin_app.algorithms.ppo_family.settings import CppoSettings, MfpoSettings, PpoSettings
from coin_app.algorithms.settings import Settings
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.road_map import load_map

S = TypeVar("S", bound=Settings)

# the settings that are not PPOConfig.training arguments (sampling, learner and model options)
OWN_KEYS = ("hidden", "num_env_runners", "rollout_fragment_length", "kl_signal", "timeout_bootstrap", "weight_init", "precision")
# the settings that go to PPOConfig.training as they are
TRAINING_KEYS = tuple(k for k in PpoSettings.keys() if k not in OWN_KEYS)


def ppo_settings(cls: type[S], algo_cfg: Mapping[str, Any]) -> S:
    """The settings of class ``cls`` (``PpoSettings`` or a child) with ``algo_cfg`` over its defaults; bad keys or values refused."""
    return cls.of(algo_cfg)


def policy_model(hidden: int, weight_init: str) -> dict[str, Any]:
    """Separate policy and value networks of two tanh layers of ``hidden`` units, linear heads, initialized by ``weight_init``."""
    model = DefaultModelConfig(fcnet_hiddens=[hidden] * 2, fcnet_activation="tanh", vf_share_layers=False, head_fcnet_hiddens=[])
    return {**dataclasses.asdict(model), "weight_init": weight_init}


def learner_options(hp: PpoSettings) -> dict[str, Any]:
    """The learner options of the PPO family's ``learner_config_dict`` (``learner.py``): KL signal, time-out bootstrap, precision."""
    return {"kl_signal": hp.kl_signal, "timeout_bootstrap": hp.timeout_bootstrap, "precision": hp.precision}


def ppo_base_config(
    scenario: ScenarioConfig, hp: PpoSettings, seed: int, env_config: dict[str, Any], algo_class: type[Algorithm] | None = None
) -> PPOConfig:
    """The PPO family's env, sampling, training values and seed; no learner, module or policy mapping yet."""
    return (
        PPOConfig(algo_class=algo_class)
        .environment(env_id_of(scenario), env_config=env_config)
        .env_runners(
            num_env_runners=hp.num_env_runners,
            rollout_fragment_length=hp.rollout_fragment_length,
            env_to_module_connector=acting_order,  # RLlib's runner acts on the agents in a fixed order (agent_order.py)
        )
        .training(**{k: getattr(hp, k) for k in TRAINING_KEYS})
        .debugging(seed=seed)
        .evaluation(evaluation_interval=None)
    )


def checked(name: str, config: PPOConfig, errors: list[str] | None = None) -> PPOConfig:
    """``config`` if neither its env backend nor ``errors`` object; else a ValueError listing every problem."""
    problems = backend_errors(config) + list(errors or [])
    if problems:
        raise ValueError(f"invalid {name} config: " + "; ".join(problems))
    return config


def driving_scenario(name: str, scenario: Any) -> ScenarioConfig:
    """``scenario`` if it is a driving scenario's config; else a ValueError."""
    if not isinstance(scenario, ScenarioConfig):
        raise ValueError(f"{name} trains on driving scenarios only, got {type(scenario).__name__}; allowed: a ScenarioConfig")
    return scenario


def build_ippo_config(scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """IPPO: one shared Gaussian policy and a value function on the agent's own observation."""
    hp = ppo_settings(PpoSettings, algo_cfg)
    config = (
        ppo_base_config(driving_scenario("IPPO", scenario), hp, seed, env_config_of(scenario))
        .learners(learner_class=ClippedValuePPOLearner, learner_config_dict=learner_options(hp))
        .rl_module(model_config=policy_model(hp.hidden, hp.weight_init), rl_module_spec=RLModuleSpec(module_class=PPOActorModule))
    )
    return checked("IPPO", shared_policy_config(config))


def centralized_config(
    name: str, mode: str, cls: type[CppoSettings], scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int
) -> PPOConfig:
    """CPPO / MFPO: IPPO's policy with the value function on the ``mode`` critic input of the neighbours within the radius."""
    hp = ppo_settings(cls, algo_cfg)
    k = hp.num_neighbours
    scenario = driving_scenario(name, scenario)
    learner_config = {
        **learner_options(hp),
        "critic_mode": mode,
        "neighbour_radius": float(hp.neighbour_radius),
        "num_neighbours": k,
        "position_scale": load_map(scenario.scenario).scale,
    }
    model = {**policy_model(hp.hidden, hp.weight_init), "critic_input_dim": critic_input_dim(mode, scenario.obs_dim, 2, k)}
    config = (
        ppo_base_config(scenario, hp, seed, env_config_of(scenario))
        .learners(learner_class=CentralizedCriticPPOLearner, learner_config_dict=learner_config)
        .rl_module(model_config=model, rl_module_spec=RLModuleSpec(module_class=CentralizedCriticPPOModule))
    )
    return checked(name, shared_policy_config(config))


def build_cppo_config(scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """CPPO: the critic reads the own observation and the (observation, action) of the 4 nearest others within 40 m."""
    return centralized_config("CPPO", "concat", CppoSettings, scenario, algo_cfg, seed)


def build_mfpo_config(scenario: ScenarioConfig, algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """MFPO: the critic reads the own observation and the mean (observation, action) of the others within 10 m."""
    return centralized_config("MFPO", "mean_field", MfpoSettings, scenario, algo_cfg, seed)
