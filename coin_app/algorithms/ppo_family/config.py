"""PPO-family configs: every hyper-parameter of the COIN/CoPO baseline runs, documented in one table.

Values are the "paper path" of CoPO (``shared/reference/copo_baselines.md`` §4: Ray 1.2 PPO as
the MetaDrive benchmark and the COIN paper's baselines ran it). ``train_batch_size`` counts env
steps (each gives one transition per present agent). Ray 1.x gathered 200-step chunks until the
batch of 1024 was full; RLlib 2.60 needs the batch to equal runners x chunk, so the chunk is
``"auto"`` (the batch split over the env runners) unless set.
"""

from __future__ import annotations

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


def ppo_hyperparameter_keys() -> tuple[str, ...]:
    """The ``--set`` keys of the PPO family."""
    return tuple(HYPERPARAMETERS)


def build_ippo_config(scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> PPOConfig:
    """IPPO: RLlib PPO with one shared Gaussian policy, value on the agent's own observation."""
    from coin_app.algorithms.ppo_family.learner import ClippedValuePPOLearner

    hp = {k: v for k, (v, _) in HYPERPARAMETERS.items()} | dict(algo_cfg)
    for k in ("hidden", "num_env_runners"):
        if not (isinstance(hp[k], int) and not isinstance(hp[k], bool) and hp[k] >= (k == "hidden")):
            raise ValueError(f"bad value for {k!r}: {hp[k]!r}; allowed: an integer >= {int(k == 'hidden')}")
    frag = hp["rollout_fragment_length"]
    if frag != "auto" and not (isinstance(frag, int) and frag >= 1):
        raise ValueError(f"bad value for 'rollout_fragment_length': {frag!r}; allowed: 'auto' or an integer >= 1")
    cfg = (
        PPOConfig()
        .environment(f"coin-{scenario}-v0", env_config=env_cfg)
        .env_runners(num_env_runners=hp["num_env_runners"], rollout_fragment_length=hp["rollout_fragment_length"])
        .learners(learner_class=ClippedValuePPOLearner)
        .training(
            **{k: hp[k] for k in HYPERPARAMETERS if k not in ("hidden", "num_env_runners", "rollout_fragment_length")},
        )
        .rl_module(
            model_config=DefaultModelConfig(
                fcnet_hiddens=[hp["hidden"], hp["hidden"]], fcnet_activation="tanh", vf_share_layers=False, head_fcnet_hiddens=[]
            )
        )
        .debugging(seed=seed)
        .evaluation(evaluation_interval=None)
    )
    cfg = shared_policy_config(cfg)
    errors = backend_errors(cfg)
    if errors:
        raise ValueError("invalid IPPO config: " + "; ".join(errors))
    return cfg
