"""The TD3 family's settings, each declared once, its presets (values of the class) and ITD3's spec.

ITD3 (independent TD3 with parameter sharing) is the family's base; CIG-TD3 (``cig_td3/settings.py``)
and TraCo (``traco/settings.py``) extend it. Defaults are COIN's (§5.1, "consistent with TD3" for
ITD3, TraCo and COIN); where the official code differs, ``official`` holds its value and
docs/decisions.md §2.1 says which side coin_app follows.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from coin_app.algorithms.checks import BOOL, INF, choice, non_negative, positive, unit
from coin_app.algorithms.choices import TD3_PRECISIONS, UPDATE_ORDERS
from coin_app.algorithms.settings import Settings, setting
from coin_app.algorithms.spec import AlgorithmSpec, Capabilities

RLLIB = "RLlib's AlgorithmConfig"
STEP = "the training step (td3/td3.py)"
UPDATE = "the update (td3/learner.py, td3/losses.py)"
OPTIM = "the learner's optimizers (td3/learner.py)"
NOISE = "the exploration (td3/exploration.py)"
NETS = "the networks (td3/networks.py)"
REPLAY = "the joint-step replay (td3/buffer.py)"
EVAL = "the periodic evaluation (training/monitor.py)"


@dataclass(frozen=True)
class Td3Settings(Settings):
    """ITD3: TD3 with one shared actor and twin critics on each vehicle's own observation and action."""

    # RLlib's own keys
    gamma: float = setting(0.99, unit(), "discount", reads=RLLIB)
    train_batch_size_per_learner: int = setting(256, positive("int"), "agent transitions per gradient update (paper: 256)", reads=RLLIB)
    rollout_fragment_length: int | str = setting(
        1,
        positive("int", INF, "auto"),
        "env steps each env runner samples per training step, K: the step's updates (updates_per_env_step per env step past "
        "the warm-up, each on that env step's clock) run after the K steps; 1: one env step, then its updates",
        reads=RLLIB,
    )
    num_env_runners: int = setting(0, non_negative("int"), "remote env runners (0 = sample in the algorithm process)", reads=RLLIB)
    grad_clip: float | None = setting(
        None,
        positive("float", INF, None),
        "clip each optimizer's gradients to this global L2 norm before its step (None: no clipping, the paper)",
        reads=RLLIB,
    )
    # TD3
    actor_lr: float = setting(2e-4, positive("float", 1.0), "Adam learning rate of the actor", reads=OPTIM, official=1e-4)
    critic_lr: float = setting(3e-4, positive("float", 1.0), "Adam learning rate of the twin individual (local) critics", reads=OPTIM)
    tau: float = setting(0.005, unit(lo_open=True), "soft target update rate of every target network (actor and critics)", reads=UPDATE)
    policy_delay: int = setting(5, positive("int"), "actor and target updates every this many critic updates", reads=UPDATE, official=3)
    exploration_noise: float = setting(0.05, non_negative(), "std of the Gaussian noise added to actions while collecting", reads=NOISE)
    target_noise: float = setting(0.1, non_negative(), "std of the target-policy smoothing noise (Eq. 8)", reads=UPDATE)
    target_noise_clip: float = setting(0.5, non_negative(), "clip of the target-policy smoothing noise", reads=UPDATE)
    timeout_bootstrap: bool = setting(
        True,
        BOOL,
        "True: a vehicle's time-out (its own step limit or the force stop, reported truncated) bootstraps its TD targets; "
        "False: every done is terminal, time-outs too (the paper's d_i and the official code)",
        reads=UPDATE,
        official=False,
    )
    warmup_steps: int = setting(
        30_000, non_negative("int"), "env steps with uniform random actions before the policy acts (official code)", reads=NOISE
    )
    replay_capacity: int = setting(
        10_000_000,
        positive("int"),
        "agent transitions kept in the joint-step replay buffer (official code; memory grows with use)",
        reads=REPLAY,
    )
    updates_per_env_step: float = setting(
        1.0, positive("float", 1000.0), "gradient updates per sampled env step (official: one per env step)", reads=STEP
    )
    hidden: int = setting(256, positive("int"), "width of the actor's and the critics' hidden layers", reads=NETS)
    actor_layers: int = setting(
        3,
        positive("int"),
        "hidden layers of the actor (paper: a three-layer MLP; official code 3 x 256; 2 before coin_app 0.2)",
        reads=NETS,
    )
    update_order: str = setting(
        "critic_first",
        choice(*UPDATE_ORDERS),
        "critic_first: the critics step, then the actor loss on the updated critics (TD3, official code) | "
        "joint: every loss from the critics before the update (before coin_app 0.2)",
        reads=UPDATE,
    )
    # guards against the saturated full-brake freeze of TD3-family actors (docs/guides/train-cig-td3.md); all off = the paper
    actor_preact_penalty: float = setting(
        0.0,
        non_negative(),
        "weight w of w * mean(max(|u| - actor_preact_threshold, 0)^2) over the actor's pre-tanh outputs u",
        reads=UPDATE,
    )
    actor_preact_threshold: float = setting(
        0.0, non_negative(), "pre-tanh magnitude the penalty starts at (0 = the plain penalty w * mean(u^2))", reads=UPDATE
    )
    critic_feature_norm: bool = setting(
        False,
        BOOL,
        "divide every critic's last hidden features by their L2 norm before its output layer (the penultimate "
        "normalization of Bjorck et al., 2022, against seed-to-seed variance; not in COIN or its code)",
        reads=NETS,
    )
    actor_start_steps: int = setting(
        0,
        non_negative("int"),
        "env steps after the warm-up before the actor's first update (the critics learn the warm-up data first)",
        reads=STEP,
    )
    exploration_noise_initial: float | None = setting(
        None,
        non_negative("float", None),
        "exploration std right after the warm-up, decaying linearly to exploration_noise (None = constant)",
        reads=NOISE,
    )
    exploration_noise_decay_steps: int = setting(0, non_negative("int"), "env steps of that decay", reads=NOISE)
    exploration_noise_decay_start: int | None = setting(
        None, non_negative("int", None), "env step at which that decay starts (None = the end of the warm-up)", reads=NOISE
    )
    # an optional late decay of every Adam learning rate (off = constant rates, the paper)
    lr_decay_start: int = setting(0, non_negative("int"), "env steps at which the learning rates start to decay linearly", reads=OPTIM)
    lr_decay_steps: int = setting(0, non_negative("int"), "env steps of that decay (0 = constant learning rates, the paper)", reads=OPTIM)
    lr_final_fraction: float = setting(
        1.0, unit(lo_open=True), "fraction of each learning rate reached at the decay's end and kept after it", reads=OPTIM
    )
    # an optional curriculum over traffic density (off = the scenario's num_agents throughout, the paper)
    curriculum_agents: int = setting(
        0,
        non_negative("int"),
        "vehicles at reset (and the respawn cap) during the curriculum's first phase, below the scenario's num_agents "
        "(0 = no curriculum, the paper)",
        reads=STEP,
    )
    curriculum_steps: int = setting(
        0,
        non_negative("int"),
        "env steps of that first phase; after it every env's next episode has the scenario's num_agents (the replay, the "
        "networks and the periodic evaluation always see the scenario's)",
        reads=STEP,
    )
    learner_threads: int = setting(
        1, positive("int"), "torch threads for updates in the learner's process (more only if a benchmark shows it helps)", reads=OPTIM
    )
    precision: str = setting(
        "fp32",
        choice(*TD3_PRECISIONS),
        "learner update precision: fp32 | bf16 | auto (bf16: every loss forward pass under torch.autocast bfloat16; auto: bf16 "
        "where the learner's device multiplies bf16 natively, a CUDA GPU with bf16 or a CPU with oneDNN bf16, else fp32; "
        "ITD3: fp32 until a learning-curve comparison backs bf16)",
        reads=UPDATE,
    )
    checkpoint_replay: bool = setting(
        True,
        BOOL,
        "keep the replay buffer in checkpoints (at its used size), so --resume continues exactly; False = small "
        "checkpoints, and a resumed run refills an empty buffer (its updates wait for a batch of new transitions)",
        reads=REPLAY,
    )
    eval_every: int = setting(
        25, non_negative("int"), "training iterations between deterministic evaluations on validation seeds (0 = off)", reads=EVAL
    )
    eval_episodes: int = setting(5, positive("int"), "validation episodes (seeds) per periodic evaluation", reads=EVAL)


DEFAULT = Td3Settings()
# the small quick scenario (CI learning test, learning curves): small networks, faster rates, and the freeze guard, the
# reduced-scale default of every TD3-family method, chosen by 5 seeds x 40k env steps of CIG-TD3 and of ITD3 with and without
# it (docs/studies/learning_curves_freeze*); the paper scale keeps the paper's setting (no guard)
QUICK = replace(
    DEFAULT,
    warmup_steps=500,
    train_batch_size_per_learner=128,
    hidden=64,
    policy_delay=2,
    actor_lr=6e-4,
    critic_lr=1e-3,
    eval_every=0,
    actor_preact_penalty=1e-3,
    actor_preact_threshold=2.0,
)
# The reduced protocol (docs/results/README.md; each lever's rule, written before its trials, and the trials:
# docs/results/journal.md). fp32: at these sizes a bf16 update takes 3.3x the fp32 time (benchmarks/learner_update.py).
# The stronger freeze guard (10x the quick weight, from |u| = 1): with the quick guard CIG-TD3 froze late in the first
# sweep. Exploration 0.1 decaying to 0.02 over the second half of the budget with the learning rates
# (tuning.experiment.reduced_decay): 0.766 -> 0.843 validation success. Minibatches of 256 (the paper's), the actor
# updated after every critic update (policy_delay 1), a time-out ends the TD target (the paper's d_i): each judged on
# CIG-TD3 by its rule ("Levers after ..." sections of the journal); the whole TD3 family gets them.
REDUCED = replace(
    QUICK,
    precision="fp32",
    actor_preact_penalty=0.01,
    actor_preact_threshold=1.0,
    exploration_noise_initial=0.1,
    exploration_noise=0.02,
    train_batch_size_per_learner=256,
    policy_delay=1,
    timeout_bootstrap=False,
)
PRESETS: dict[str, Td3Settings] = {
    "paper": DEFAULT,
    "quick": QUICK,
    # smoke sweeps (tests, CI): a short warm-up and one update per ten env steps
    "smoke": replace(QUICK, warmup_steps=200, updates_per_env_step=0.1),
    "reduced": REDUCED,
    # The dense protocol (30 vehicles; sweep seeds --scale dense): the pilots' current choice, P1 of
    # docs/studies/dense_pilots.md (its rule picks each lever, in its order; an adopted lever changes its value here):
    # reduced's networks, batch, rates, guard and time-outs, with exploration 0.1 constant (the scale decays neither it nor
    # the rates), one update per 4 env steps and a validation evaluation every 20 iterations (10k env steps)
    "dense": replace(REDUCED, exploration_noise_initial=None, exploration_noise=0.1, updates_per_env_step=0.25, eval_every=20),
    # the smallest that builds, updates and checkpoints in seconds (registry.tiny_settings)
    "tiny": replace(DEFAULT, warmup_steps=60, train_batch_size_per_learner=16, hidden=16, policy_delay=2, eval_every=0),
}
# the presets over the quick settings' small networks and faster rates: CIG-TD3's and TraCo's critics take theirs there too
SMALL_PRESETS = ("quick", "smoke", "reduced", "dense")
# RLlib's own keys among the settings: set through AlgorithmConfig.training / env_runners, not as the config's attributes
RLLIB_KEYS = tuple(k for k, d in Td3Settings.declarations().items() if d.reads == RLLIB)
CAPABILITIES = Capabilities(on_policy=False, centralized_critic=False, joint_replay=True, periodic_evaluation=True)

ITD3 = AlgorithmSpec(
    name="itd3",
    description="ITD3: independent TD3 with parameter sharing",
    build="coin_app.algorithms.td3.td3:build_itd3_config",
    capabilities=CAPABILITIES,
    settings=Td3Settings,
    presets=PRESETS,
)
