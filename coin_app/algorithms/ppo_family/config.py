"""PPO-family configs: every hyper-parameter of the COIN/CoPO baseline runs, documented in one table.

Values are the "paper path" of CoPO (``shared/reference/copo_baselines.md`` §4: Ray 1.2 PPO as
the MetaDrive benchmark and the COIN paper's baselines ran it). ``train_batch_size`` counts env
steps (each gives one transition per present agent). Ray 1.x gathered 200-step chunks until the
batch of 1024 was full; RLlib 2.60 needs the batch to equal runners x chunk, so the chunk is
``"auto"`` (the batch split over the env runners) unless set.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any

from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.rl_module.default_model_config import DefaultModelConfig

from coin_app.algorithms.common import backend_errors, shared_policy_config

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


# CoPO (copo_baselines.md §2.3, §4: the IPPO hyper-parameters plus these)
COPO_KEYS: dict[str, tuple[Any, str]] = {
    "neighbour_radius": (40.0, "neighbour reward: mean reward of the others strictly within this many metres"),
    "initial_lcf_mean": (0.0, "initial mean of the LCF distribution, in (-1, 1) (LCF 0 = selfish, 1 = altruistic)"),
    "initial_lcf_std": (0.1, "initial std of the LCF distribution"),
    "lcf_lr": (1e-4, "Adam learning rate of the LCF distribution parameters (meta-gradient)"),
    "lcf_num_iters": (5, "meta-gradient passes over each train batch (0 = fixed LCF distribution)"),
    "lcf_minibatch_size": (None, "meta-gradient minibatch (agent transitions); None = minibatch_size"),
}
VARIANTS = ("ippo", *CENTRAL_VARIANTS, "copo")


def ppo_hyperparameter_keys(variant: str = "ippo") -> tuple[str, ...]:
    """The ``--set`` keys of a PPO-family algorithm."""
    extra = tuple(CENTRAL_KEYS) if variant in CENTRAL_VARIANTS else tuple(COPO_KEYS) if variant == "copo" else ()
    return tuple(HYPERPARAMETERS) + extra


def _number(name: str, value: Any, ok: Callable[[float], bool], allowed: str, integer: bool = False) -> Any:
    """``value`` if it is a number (an integer if asked) that passes ``ok``; else a ValueError naming it."""
    kinds = (int,) if integer else (int, float)
    if not (isinstance(value, kinds) and not isinstance(value, bool) and ok(value)):
        raise ValueError(f"bad value for {name!r}: {value!r}; allowed: {allowed}")
    return value


def _central_parts(variant: str, opts: dict[str, Any], scenario: str, env_cfg: dict[str, Any], model: dict[str, Any]) -> dict[str, Any]:
    """Learner, module, model and learner settings of CPPO / MFPO."""
    from coin_app.algorithms.ppo_family.centralized import CentralizedCriticPPOLearner, CentralizedCriticPPOModule, critic_input_dim
    from coin_app.sim.config import config_from_dict
    from coin_app.sim.road_map import load_map

    mode, default_radius = CENTRAL_VARIANTS[variant]
    radius = default_radius if opts["neighbour_radius"] is None else opts["neighbour_radius"]
    radius = _number("neighbour_radius", radius, lambda v: v > 0, "a number of metres > 0")
    k = _number("num_neighbours", opts["num_neighbours"], lambda v: v >= 1, "an integer >= 1", integer=True)
    dim = critic_input_dim(mode, config_from_dict(scenario, env_cfg).obs_dim, 2, k)
    extra = {"critic_mode": mode, "neighbour_radius": float(radius), "num_neighbours": k, "position_scale": load_map(scenario).scale}
    return {
        "learner": CentralizedCriticPPOLearner,
        "module": CentralizedCriticPPOModule,
        "model": {**model, "critic_input_dim": dim},
        "learner_config": extra,
        "env_config": env_cfg,
    }


def _copo_parts(opts: dict[str, Any], scenario: str, env_cfg: dict[str, Any], model: dict[str, Any]) -> dict[str, Any]:
    """Algorithm, learner, module, model, learner settings and env config (with LCFs) of CoPO."""
    from coin_app.algorithms.copo.algorithm import CoPO
    from coin_app.algorithms.copo.learner import CoPOLearner
    from coin_app.algorithms.copo.rl_module import CoPOModule
    from coin_app.sim.road_map import load_map

    radius = _number("neighbour_radius", opts["neighbour_radius"], lambda v: v > 0, "a number of metres > 0")
    mean = _number("initial_lcf_mean", opts["initial_lcf_mean"], lambda v: -1 < v < 1, "a number in (-1, 1)")
    std = _number("initial_lcf_std", opts["initial_lcf_std"], lambda v: 0 < v < 7, "a number in (0, 7) (std = exp(p), p <= 2)")
    _number("lcf_lr", opts["lcf_lr"], lambda v: v > 0, "a number > 0")
    _number("lcf_num_iters", opts["lcf_num_iters"], lambda v: v >= 0, "an integer >= 0", integer=True)
    if opts["lcf_minibatch_size"] is not None:
        _number("lcf_minibatch_size", opts["lcf_minibatch_size"], lambda v: v >= 1, "None or an integer >= 1", integer=True)
    extra = {k: opts[k] for k in ("lcf_lr", "lcf_num_iters", "lcf_minibatch_size")}
    extra |= {"neighbour_radius": float(radius), "position_scale": load_map(scenario).scale}
    return {
        "algo": CoPO,
        "learner": CoPOLearner,
        "module": CoPOModule,
        "model": {**model, "initial_lcf": [float(mean), float(std)]},
        "learner_config": extra,
        "env_config": {**env_cfg, "lcf": {"mean": float(mean), "std": float(std)}},
    }


def build_ppo_config(variant: str, scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """IPPO (value on the own observation), CPPO / MFPO (centralized value) or CoPO as an RLlib PPO config."""
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec

    from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner

    if variant not in VARIANTS:
        raise ValueError(f"unknown PPO variant {variant!r}; allowed: {', '.join(VARIANTS)}")
    algo_cfg = dict(algo_cfg)
    table = CENTRAL_KEYS if variant in CENTRAL_VARIANTS else COPO_KEYS if variant == "copo" else {}
    opts = {k: algo_cfg.pop(k, v) for k, (v, _) in table.items()}
    hp = {k: v for k, (v, _) in HYPERPARAMETERS.items()} | algo_cfg
    _number("hidden", hp["hidden"], lambda v: v >= 1, "an integer >= 1", integer=True)
    _number("num_env_runners", hp["num_env_runners"], lambda v: v >= 0, "an integer >= 0", integer=True)
    frag = hp["rollout_fragment_length"]
    if frag != "auto":
        _number("rollout_fragment_length", frag, lambda v: v >= 1, "'auto' or an integer >= 1", integer=True)
    model = DefaultModelConfig(fcnet_hiddens=[hp["hidden"]] * 2, fcnet_activation="tanh", vf_share_layers=False, head_fcnet_hiddens=[])
    parts: dict[str, Any] = {"learner": ClippedValuePPOLearner, "model": model, "env_config": env_cfg}
    if variant in CENTRAL_VARIANTS:
        parts = _central_parts(variant, opts, scenario, env_cfg, dataclasses.asdict(model))
    elif variant == "copo":
        parts = _copo_parts(opts, scenario, env_cfg, dataclasses.asdict(model))
    cfg = (
        PPOConfig(algo_class=parts.get("algo"))
        .environment(f"coin-{scenario}-v0", env_config=parts["env_config"])
        .env_runners(num_env_runners=hp["num_env_runners"], rollout_fragment_length=frag)
        .learners(learner_class=parts["learner"], learner_config_dict=parts.get("learner_config", {}))
        .training(
            **{k: hp[k] for k in HYPERPARAMETERS if k not in ("hidden", "num_env_runners", "rollout_fragment_length")},
        )
        .rl_module(model_config=parts["model"])
        .debugging(seed=seed)
        .evaluation(evaluation_interval=None)
    )
    if "module" in parts:
        cfg = cfg.rl_module(rl_module_spec=RLModuleSpec(module_class=parts["module"]))
    cfg = shared_policy_config(cfg)
    errors = backend_errors(cfg)
    if variant == "copo" and cfg.num_learners > 1:
        errors.append(f"num_learners={cfg.num_learners}; allowed: 0 or 1 (one LCF distribution, one meta-gradient)")
    if errors:
        raise ValueError(f"invalid {variant.upper()} config: " + "; ".join(errors))
    return cfg
