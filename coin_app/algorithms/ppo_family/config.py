"""PPO-family configs: every hyper-parameter of the COIN/CoPO baseline runs, documented in one table.

Values are the "paper path" of CoPO (``shared/reference/copo_baselines.md`` §4: Ray 1.2 PPO as
the MetaDrive benchmark and the COIN paper's baselines ran it). ``train_batch_size`` counts env
steps (each gives one transition per present agent). Ray 1.x gathered 200-step chunks until the
batch of 1024 was full; RLlib 2.60 needs the batch to equal runners x chunk, so the chunk is
``"auto"`` (the batch split over the env runners) unless set.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

from coin_app.envs.rllib_env import backend_errors, shared_policy_config

# name -> (default, meaning)
HYPERPARAMETERS: dict[str, tuple[Any, str]] = {
    "lr": (3e-4, "Adam learning rate of policy and value networks"),
    "gamma": (0.99, "discount"),
    "lambda_": (0.95, "GAE lambda"),
    "clip_param": (0.3, "PPO ratio clip"),
    "vf_clip_param": (10.0, "PPO2-style value clip around the collection-time value (Ray 1.x)"),
    "vf_loss_coeff": (1.0, "weight of the value loss"),
    "kl_coeff": (0.2, "initial adaptive KL penalty"),
    "kl_target": (0.01, "target KL of the adaptive penalty"),
    "entropy_coeff": (0.0, "entropy bonus (none in the paper runs)"),
    "train_batch_size_per_learner": (1024, "env steps per training batch"),
    "minibatch_size": (512, "SGD minibatch (agent transitions)"),
    "num_epochs": (5, "SGD passes over each batch"),
    "rollout_fragment_length": ("auto", "env steps per sampling chunk; 'auto' = batch / runners (paper: 200-step chunks)"),
    "num_env_runners": (0, "remote env runners (0 = sample in the training process)"),
    "hidden": (256, "width of the two tanh layers of the separate policy and value networks"),
}


# centralized-critic variants: name -> (critic mode, default neighbour radius in metres)
CENTRAL_VARIANTS = {"cppo": ("concat", 40.0), "mfpo": ("mean_field", 10.0)}
CENTRAL_KEYS: dict[str, tuple[Any, str]] = {
    "neighbour_radius": (None, "neighbours are the others strictly within this many metres (CPPO 40, MFPO 10)"),
    "num_neighbours": (4, "CPPO: the k nearest neighbours concatenated (zero-padded); MFPO averages all"),
}


def ppo_hyperparameter_keys(variant: str = "ippo") -> tuple[str, ...]:
    """The ``--set`` keys of a PPO-family algorithm."""
    return tuple(HYPERPARAMETERS) + (tuple(CENTRAL_KEYS) if variant in CENTRAL_VARIANTS else ())


def build_ppo_config(variant: str, scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """IPPO (value on the own observation), CPPO or MFPO (centralized value) as an RLlib PPO config."""
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from coin_app.algorithms.ppo_family.centralized import CentralizedCriticPPOLearner, CentralizedCriticPPOModule, critic_input_dim
    from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner
    from coin_app.envs.config import config_from_dict
    from coin_app.envs.road_map import load_map

    algo_cfg = dict(algo_cfg)
    central = {k: algo_cfg.pop(k, v) for k, (v, _) in CENTRAL_KEYS.items()} if variant in CENTRAL_VARIANTS else {}
    hp = {k: v for k, (v, _) in HYPERPARAMETERS.items()} | algo_cfg
    for k in ("hidden", "num_env_runners"):
        if not (isinstance(hp[k], int) and not isinstance(hp[k], bool) and hp[k] >= (k == "hidden")):
            raise ValueError(f"bad value for {k!r}: {hp[k]!r}; allowed: an integer >= {int(k == 'hidden')}")
    frag = hp["rollout_fragment_length"]
    if frag != "auto" and not (isinstance(frag, int) and frag >= 1):
        raise ValueError(f"bad value for 'rollout_fragment_length': {frag!r}; allowed: 'auto' or an integer >= 1")
    model: Any = DefaultModelConfig(fcnet_hiddens=[hp["hidden"]] * 2, fcnet_activation="tanh", vf_share_layers=False, head_fcnet_hiddens=[])
    if central:
        mode, default_radius = CENTRAL_VARIANTS[variant]
        radius = default_radius if central["neighbour_radius"] is None else central["neighbour_radius"]
        k = central["num_neighbours"]
        if not (isinstance(radius, (int, float)) and not isinstance(radius, bool) and radius > 0):
            raise ValueError(f"bad value for 'neighbour_radius': {radius!r}; allowed: a number of metres > 0")
        if not (isinstance(k, int) and not isinstance(k, bool) and k >= 1):
            raise ValueError(f"bad value for 'num_neighbours': {k!r}; allowed: an integer >= 1")
        dim = critic_input_dim(mode, config_from_dict(scenario, env_cfg).obs_dim, 2, k)
        model = {**dataclasses.asdict(model), "critic_input_dim": dim}
        learner_extra = {"critic_mode": mode, "neighbour_radius": float(radius), "num_neighbours": k}
        learner_extra["position_scale"] = load_map(scenario).scale
    cfg = (
        PPOConfig()
        .environment(f"coin-{scenario}-v0", env_config=env_cfg)
        .env_runners(num_env_runners=hp["num_env_runners"], rollout_fragment_length=hp["rollout_fragment_length"])
        .learners(learner_class=CentralizedCriticPPOLearner if central else ClippedValuePPOLearner)
        .training(
            **{k: hp[k] for k in HYPERPARAMETERS if k not in ("hidden", "num_env_runners", "rollout_fragment_length")},
        )
        .rl_module(model_config=model)
        .debugging(seed=seed)
        .evaluation(evaluation_interval=None)
    )
    if central:
        cfg = cfg.learners(learner_config_dict=learner_extra).rl_module(
            rl_module_spec=RLModuleSpec(module_class=CentralizedCriticPPOModule)
        )
    cfg = shared_policy_config(cfg)
    errors = backend_errors(cfg)
    if errors:
        raise ValueError(f"invalid {variant.upper()} config: " + "; ".join(errors))
    return cfg
