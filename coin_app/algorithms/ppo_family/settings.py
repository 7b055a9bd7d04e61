"""The PPO family's settings, each declared once, its presets (values of these classes) and the IPPO, CPPO and MFPO specs.

The defaults are the PPO baselines of the COIN paper, which ran CoPO's code (Peng et al., NeurIPS
2021) on Ray 1.2's PPO, as the MetaDrive benchmark did (docs/guides/ppo-family.md;
docs/decisions.md §7). ``train_batch_size_per_learner`` counts env steps (each gives one
transition per present agent): Ray 1.x sampled 200-step chunks on 4 workers until at least 1024
env steps were in, 2 rounds, 1600 env steps per update. Sampling runs in the training process
by default; the ``paper`` preset adds the reference's four sampling workers. CoPO's and
nav_ppo's classes (their packages' ``settings.py``) extend these.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

from coin_app.algorithms.checks import BOOL, INF, choice, non_negative, positive, unit
from coin_app.algorithms.choices import KL_SIGNALS, PRECISIONS, WEIGHT_INITS
from coin_app.algorithms.settings import Settings, redeclare, setting
from coin_app.algorithms.spec import AlgorithmSpec, Capabilities

TRAINING = "PPOConfig.training"
RUNNERS = "PPOConfig.env_runners"
LEARNER = "the learner (ppo_family/learner.py)"
MODULE = "the RLModule (ppo_family/config.py policy_model)"
NEIGHBOURS = "the centralized critic's inputs (ppo_family/centralized.py)"


@dataclass(frozen=True)
class PpoCore(Settings):
    """What every PPO of this project has: the update, the batch and the networks."""

    lr: float = setting(3e-4, positive("float", 1.0), "Adam learning rate of policy and value networks", reads=TRAINING)
    gamma: float = setting(0.99, unit(), "discount", reads=TRAINING)
    lambda_: float = setting(0.95, unit(), "GAE lambda", reads=TRAINING)
    clip_param: float = setting(0.3, positive(), "PPO ratio clip", reads=TRAINING)
    vf_loss_coeff: float = setting(1.0, non_negative(), "weight of the value loss", reads=TRAINING)
    entropy_coeff: float = setting(0.0, non_negative(), "entropy bonus (none in the paper runs)", reads=TRAINING)
    train_batch_size_per_learner: int = setting(
        1600, positive("int"), "env steps per training batch (paper runs: 2 rounds of 4 workers x 200 steps)", reads=TRAINING
    )
    minibatch_size: int = setting(512, positive("int"), "SGD minibatch (agent transitions)", reads=TRAINING)
    num_epochs: int = setting(5, positive("int"), "SGD passes over each batch", reads=TRAINING)
    hidden: int = setting(256, positive("int"), "width of the two tanh layers of the separate policy and value networks", reads=MODULE)
    num_env_runners: int = setting(
        0,
        non_negative("int"),
        "remote env runners (0 = sample in the training process, one env; paper: 4, the sweeps' paper scale)",
        reads=RUNNERS,
        official=4,
    )
    precision: str = setting(
        "fp32",
        choice(*PRECISIONS),
        "learner update precision: 'fp32', or 'bf16' = each minibatch's forward pass and losses under torch.autocast bfloat16 "
        "(module outputs, losses, parameters, optimizer state and the value predictions for GAE stay fp32)",
        reads="the learner (ppo_family/precision.py)",
    )


@dataclass(frozen=True)
class PpoSettings(PpoCore):
    """IPPO: the core plus the reference's (Ray 1.x) behaviours, each with RLlib's as an option."""

    vf_clip_param: float = setting(10.0, positive(), "PPO2-style value clip around the collection-time value (Ray 1.x)", reads=TRAINING)
    kl_coeff: float = setting(0.2, non_negative(), "initial adaptive KL penalty", reads=TRAINING)
    kl_target: float = setting(0.01, positive(), "target KL of the adaptive penalty", reads=TRAINING)
    kl_signal: str = setting(
        "epoch_mean",
        choice(*KL_SIGNALS),
        "KL the penalty adapts to (x1.5 above 2 target, x0.5 below target / 2): 'epoch_mean' = mean over the last "
        "SGD epoch's minibatches (Ray 1.x), 'last_minibatch' = the last minibatch's (RLlib 2.60)",
        reads=LEARNER,
    )
    rollout_fragment_length: int | str = setting(
        200, positive("int", INF, "auto"), "env steps per sampling chunk (paper: 200); 'auto' = batch / runners", reads=RUNNERS
    )
    timeout_bootstrap: bool = setting(
        False,
        BOOL,
        "False: a vehicle's own step limit and the force stop end its GAE like any done, zero bootstrap (Ray 1.x); "
        "True: they bootstrap with V(o_T) (RLlib's truncation)",
        reads=LEARNER,
    )
    weight_init: str = setting(
        "normc",
        choice(*WEIGHT_INITS),
        "'normc' = Ray 1.x's initialization (each unit's weights of norm 1, output layers 0.01, biases 0); 'torch' = PyTorch's default",
        reads=MODULE,
    )


@dataclass(frozen=True)
class CppoSettings(PpoSettings):
    """CPPO: IPPO's settings plus the neighbours its critic reads."""

    neighbour_radius: float = setting(40.0, positive(), "neighbours are the others strictly within this many metres", reads=NEIGHBOURS)
    num_neighbours: int = setting(
        4,
        positive("int"),
        "CPPO: the k nearest neighbours concatenated (zero-padded); MFPO averages all",
        reads=NEIGHBOURS,
    )


@dataclass(frozen=True)
class MfpoSettings(CppoSettings):
    """MFPO: CPPO's keys, with the mean field over a 10 m radius."""

    neighbour_radius: float = redeclare(CppoSettings, "neighbour_radius", 10.0)


# The presets: values of PpoSettings (CPPO's, MFPO's and CoPO's are these lifted into their classes, ``Settings.lift``).
DEFAULT = PpoSettings()
PRESETS: dict[str, PpoSettings] = {
    # the sweeps' paper scale: CoPO's four sampling workers x 200-step chunks (each trial asks Tune for 1 + 4 CPUs)
    "paper": replace(DEFAULT, num_env_runners=4),
    # the quick scenario's small networks (train --quick, the learning curves)
    "quick": replace(DEFAULT, hidden=64),
    # the reduced protocol: the quick networks with the reference batch, sampled in the trial's process
    "reduced": replace(DEFAULT, hidden=64),
    # the dense protocol (30 vehicles; sweep seeds --scale dense): the defaults, i.e. the paper's networks, batch and update
    # (its reference budget, 1M env steps, is the scale's), sampled in the trial's process as reduced is (the paper preset's
    # four env runners would ask Tune for five CPUs a trial). The scenario is the scale's (tuning/seeds.py: metadrive_compat,
    # CoPO's penalties and lidar, for every method; docs/studies/ippo_dense.md)
    "dense": DEFAULT,
    # smoke sweeps (tests, CI): a few iterations of a few seconds; the chunk fits the batch
    "smoke": replace(DEFAULT, hidden=64, train_batch_size_per_learner=256, minibatch_size=128, num_epochs=1, rollout_fragment_length=128),
    # the smallest that builds, updates and checkpoints in seconds (registry.tiny_settings): two chunks, two epochs of two minibatches
    "tiny": replace(DEFAULT, train_batch_size_per_learner=100, rollout_fragment_length=50, minibatch_size=50, num_epochs=2, hidden=16),
}


def lifted(cls: type[Settings], presets: dict[str, Any] | None = None) -> dict[str, Any]:
    """The family's presets as values of ``cls`` (a child class of ``PpoSettings``)."""
    return {name: cls.lift(value) for name, value in (presets or PRESETS).items()}


CONFIG = "coin_app.algorithms.ppo_family.config"  # the builders (RLlib), imported when a config is built
PPO_CAPABILITIES = Capabilities(on_policy=True, centralized_critic=False, joint_replay=False)
CENTRAL_CAPABILITIES = Capabilities(on_policy=True, centralized_critic=True, joint_replay=False)

IPPO = AlgorithmSpec(
    name="ippo",
    description="IPPO: PPO with one shared policy, value on the own observation",
    build=f"{CONFIG}:build_ippo_config",
    capabilities=PPO_CAPABILITIES,
    settings=PpoSettings,
    presets=PRESETS,
)
CPPO = AlgorithmSpec(
    name="cppo",
    description="CPPO: PPO, value on own + 4 nearest neighbours' (obs, action)",
    build=f"{CONFIG}:build_cppo_config",
    capabilities=CENTRAL_CAPABILITIES,
    settings=CppoSettings,
    presets=lifted(CppoSettings),
)
MFPO = AlgorithmSpec(
    name="mfpo",
    description="MFPO: PPO, value on own obs + mean neighbour obs and action",
    build=f"{CONFIG}:build_mfpo_config",
    capabilities=CENTRAL_CAPABILITIES,
    settings=MfpoSettings,
    presets=lifted(MfpoSettings),
)
