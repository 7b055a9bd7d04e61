"""Time of one CIG-TD3 (and ITD3) learner update on this CPU, fp32 and bf16, with a breakdown, and of a training loop.

Usage: python benchmarks/learner_update.py [--size paper] [--updates 10] [--threads 1] [--precision both]
                                           [--loop-steps 300] [--rllib-step]

``--size paper`` (default): the update runs on a synthetic batch shaped like the intersection's
(30 agents: 38 padded "other" slots, about 29 of them present at t and 30 at t+1), B = 256, the
paper's network sizes, all modules on (CVAE, GAT, counterfactual baseline, twin critics,
targets). ``--size quick``: the quick settings of the learning curves and of the reduced-scale
protocol (``registry.quick_settings``: 4 agents, so 3 of the padded slots present, B = 128,
hidden 64, latent 8, node width 16, policy delay 2). One figure is the mean over a whole
policy-delay cycle (4 critic-only updates + 1 update with the actor step and target
updates). The breakdown times each loss's forward + backward separately. ``--precision``
``both`` (default) times the fp32 and the bf16 learner (``precision="bf16"``: loss forward
passes under bfloat16 autocast) side by side on the same batch and initial weights, one delay
cycle of each in turn (so a change in the machine's load hits both alike), and prints the
ratio bf16 / fp32. ``--loop-steps`` also times a full ``algo.train()`` loop (sampling, replay,
updates, weight sync) on the intersection and prints env-steps/s. ``--rllib-step`` also times
the fp32 learner with RLlib's own ``TorchLearner.apply_gradients`` (two finiteness checks, each a
host sync, per gradient tensor) in turn with the others, and prints the ratio.
"""

from __future__ import annotations

import argparse
import time
import types

import numpy as np
import ray
import torch
from ray.rllib.core.learner.torch.torch_learner import TorchLearner
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms import registry
from coin_app.algorithms.choices import PRECISIONS
from coin_app.algorithms.cig_td3.cig_td3 import CigTd3Config
from coin_app.algorithms.cig_td3.losses import actor_loss, central_critic_loss, td_targets
from coin_app.algorithms.registry import quick_settings
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3.learner import autocast
from coin_app.algorithms.td3.losses import local_critic_loss
from coin_app.algorithms.td3.settings import RLLIB_KEYS, Td3Settings
from coin_app.algorithms.td3.td3 import Td3Config
from coin_app.sim import schema
from coin_app.sim.scenes import env_id
from coin_app.training import build_config


def synthetic_batch(b: int, n: int, obs_dim: int, present: int, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """A batch with ``present`` of ``n`` other slots filled at t and t+1."""
    mask = np.zeros((b, n), bool)
    mask[:, :present] = True
    next_mask = np.zeros((b, n), bool)
    next_mask[:, : present + 1] = True
    f = np.float32
    S, A = schema.STATE_DIM, schema.ACT_DIM
    return {
        col.OBS: rng.random((b, obs_dim), dtype=f),
        col.STATE: rng.standard_normal((b, S)).astype(f),
        col.ACTIONS: rng.uniform(-1, 1, (b, A)).astype(f),
        col.REWARDS: rng.standard_normal(b).astype(f),
        col.GLOBAL_REWARDS: rng.standard_normal(b).astype(f),
        col.TERMINATEDS: rng.random(b) < 0.05,
        col.TRUNCATEDS: np.zeros(b, bool),
        col.NEXT_OBS: rng.random((b, obs_dim), dtype=f),
        col.NEXT_STATE: rng.standard_normal((b, S)).astype(f),
        col.OTHERS_STATE: rng.standard_normal((b, n, S)).astype(f) * mask[..., None],
        col.OTHERS_ACTIONS: rng.uniform(-1, 1, (b, n, A)).astype(f) * mask[..., None],
        col.OTHERS_MASK: mask,
        col.NEXT_OTHERS_STATE: rng.standard_normal((b, n, S)).astype(f) * next_mask[..., None],
        col.NEXT_OTHERS_OBS: rng.random((b, n, obs_dim), dtype=f) * next_mask[..., None],
        col.NEXT_OTHERS_MASK: next_mask,
    }


RLLIB_STEP = "fp32, RLlib's gradient step"  # the label of the --rllib-step comparison


def time_updates(cfgs: dict[str, Td3Config], updates: int, present: int) -> dict[str, tuple[float, dict[str, float]]]:
    """Per precision: (mean seconds per learner update over whole delay cycles, breakdown in seconds).

    The learners of ``cfgs`` (same seed, so the same initial weights) run one delay cycle each in
    turn on the same batch, whose rows have ``present`` other agents at t (one more at t+1).
    """
    first = next(iter(cfgs.values()))
    env = CoinMultiAgentEnv(first.env_config)
    batch_np = synthetic_batch(first.train_batch_size_per_learner, first.max_others, env.config.obs_dim, present, np.random.default_rng(0))
    batch = MultiAgentBatch({"shared": SampleBatch(batch_np)}, env_steps=first.train_batch_size_per_learner)
    ts = {"num_env_steps_sampled_lifetime": 0}
    learners = {name: cfg.build_learner(env=env) for name, cfg in cfgs.items()}
    if RLLIB_STEP in learners:  # RLlib's own TorchLearner.apply_gradients (two finiteness checks per tensor)
        learners[RLLIB_STEP].apply_gradients = types.MethodType(TorchLearner.apply_gradients, learners[RLLIB_STEP])
    for learner in learners.values():
        learner.update(batch=batch, timesteps=ts)  # warm-up
    cycles = max(1, updates // first.policy_delay)
    spent = dict.fromkeys(cfgs, 0.0)
    for _ in range(cycles):
        for name, learner in learners.items():
            t0 = time.perf_counter()
            for _ in range(first.policy_delay):
                learner.update(batch=batch, timesteps=ts)
            spent[name] += time.perf_counter() - t0
    n_updates = cycles * first.policy_delay
    return {name: (spent[name] / n_updates, breakdown(learners[name], cfg, batch_np)) for name, cfg in cfgs.items()}


def breakdown(learner: object, cfg: Td3Config, batch_np: dict[str, np.ndarray]) -> dict[str, float]:
    """Seconds of each loss's forward (under the learner's autocast) + backward on ``batch_np``."""
    m = learner.module["shared"].unwrapped()
    central, central_target = getattr(m, "central", None), getattr(m, "central_target", None)  # None: ITD3
    tb = {k: torch.as_tensor(v) for k, v in batch_np.items()}
    lc = learner.loss_config(m, cfg)
    parts: dict[str, float] = {}

    def clock(name: str, fn: object) -> None:
        t = time.perf_counter()
        for _ in range(3):
            fn()
        parts[name] = (time.perf_counter() - t) / 3

    def fwd(fn: object) -> object:
        with autocast(m, cfg.precision):
            return fn()

    clock("targets (no grad)", lambda: fwd(lambda: td_targets(tb, m.actor_target, m.local_q_target, central_target, lc)))
    y_l, y_g = fwd(lambda: td_targets(tb, m.actor_target, m.local_q_target, central_target, lc))
    clock("local critic fwd+bwd", lambda: fwd(lambda: local_critic_loss(m.local_q, tb, y_l)[0]).backward())
    if central is not None:
        clock("central critic fwd+bwd", lambda: fwd(lambda: central_critic_loss(central, tb, y_g, lc)[0]).backward())
    clock("actor fwd+bwd (1 in policy_delay)", lambda: fwd(lambda: actor_loss(m.actor, m.local_q, central, tb, lc)[0]).backward())
    return parts


def time_loop(cfg: Td3Config, steps: int) -> float:
    """Env steps per second of ``algo.train()`` after the warm-up (updates every env step)."""
    ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    cfg = cfg.copy(copy_frozen=False).training(warmup_steps=steps, learner_threads=torch.get_num_threads())
    cfg = cfg.reporting(min_sample_timesteps_per_iteration=steps)
    algo = cfg.build_algo()
    algo.train()  # warm-up iteration fills the buffer
    t0 = time.perf_counter()
    r = algo.train()
    dt = time.perf_counter() - t0
    algo.stop()
    return float(r["env_runners"]["num_env_steps_sampled"]) / dt


SIZES = ("paper", "quick", "reduced-dense")


def base_config(size: str, threads: int) -> tuple[CigTd3Config, int]:
    """The CIG-TD3 config timed at ``size`` and the number of other agents present per batch row."""
    if size == "paper":
        env_config = {"scenario": "intersection"}
        cfg = CigTd3Config().environment(env_id("intersection"), env_config=env_config).debugging(seed=0)
        return cfg.training(learner_threads=threads), 29
    if size == "reduced-dense":  # the reduced protocol's networks and batch at the paper's density (issue 56's pilots)
        settings = {**registry.get("cig_td3").presets["reduced"].changes(), "learner_threads": threads}
        cfg = build_config("cig_td3", "intersection", settings, 0)
        return cfg, cfg.scenario_config().num_agents - 1
    settings = {**quick_settings("cig_td3"), "learner_threads": threads}
    cfg = build_config("cig_td3", "intersection", settings, 0)
    return cfg, cfg.scenario_config().num_agents - 1


def itd3_config(cig: CigTd3Config) -> Td3Config:
    """ITD3 (the TD3 base) with ``cig``'s scenario, seed and TD3 settings."""
    own = {k: getattr(cig, k) for k in Td3Settings.keys() if k not in ("precision", *RLLIB_KEYS)}  # ITD3 keeps its own precision
    cfg = Td3Config().environment(cig.env, env_config=cig.env_config).debugging(seed=cig.seed)
    return cfg.training(**own, train_batch_size_per_learner=cig.train_batch_size_per_learner)


def main() -> None:
    """Print the update times per precision, their ratio, the breakdown and the loop throughput."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument(
        "--size",
        choices=SIZES,
        default="paper",
        help="paper: 30 agents, paper sizes; quick: the reduced-scale settings; reduced-dense: those settings at 30 agents",
    )
    ap.add_argument("--updates", type=int, default=10)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--precision", choices=(*PRECISIONS, "both"), default="both", help="learner precision(s) to time")
    ap.add_argument("--loop-steps", type=int, default=0, help="also time a training loop of this many env steps (0 = skip)")
    ap.add_argument("--rllib-step", action="store_true", help="also time fp32 with RLlib's own gradient step, side by side")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    register_envs()
    precisions = PRECISIONS if args.precision == "both" else (args.precision,)
    base, present = base_config(args.size, args.threads)
    print(
        f"{args.size} size: B={base.train_batch_size_per_learner}, intersection ({base.scenario_config().num_agents} agents, "
        f"{base.max_others} other slots, {present} present), torch threads {args.threads}"
    )
    for name, algo_cfg in (("CIG-TD3 (all modules)", base), ("ITD3", itd3_config(base))):
        cfgs = {p: algo_cfg.copy(copy_frozen=False).training(precision=p) for p in precisions}
        if args.rllib_step:
            cfgs[RLLIB_STEP] = algo_cfg.copy(copy_frozen=False).training(precision="fp32")
        for cfg in cfgs.values():
            cfg.validate()
        timed = time_updates(cfgs, args.updates, present)
        print(f"\n{name}:")
        for precision, (per, parts) in timed.items():
            print(f"  {precision}: {per * 1000:.0f} ms per update (mean over delay cycles)")
            for k, v in parts.items():
                print(f"    {k:<36}{v * 1000:8.1f} ms")
        if "bf16" in timed and "fp32" in timed:
            print(f"  bf16 / fp32 update time: {timed['bf16'][0] / timed['fp32'][0]:.2f}")
        if RLLIB_STEP in timed and "fp32" in timed:
            print(f"  fp32 update time, this learner's gradient step / RLlib's: {timed['fp32'][0] / timed[RLLIB_STEP][0]:.2f}")
        if args.loop_steps:
            for precision, cfg in ((p, c) for p, c in cfgs.items() if p != RLLIB_STEP):
                print(f"  training loop, {precision}: {time_loop(cfg, args.loop_steps):.1f} env steps/s (1 update per env step)")


if __name__ == "__main__":
    main()
