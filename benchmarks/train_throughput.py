"""End-to-end training speed, side by side: RLlib's MultiAgentEnvRunner vs the batched env runner (and CIG-TD3 fp32 vs bf16).

Usage: python benchmarks/train_throughput.py [--cases ippo nav_ppo cig_td3] [--iterations 2]

* ``ippo``: IPPO on the intersection with 30 agents, the reference settings (1600 env steps per
  update in 200-step chunks, 5 epochs of 512-row minibatches), sampling in the training process;
* ``nav_ppo``: nav_ppo's long stage on the arena (4 vehicles, 3 obstacles), its defaults;
  each PPO case three ways: RLlib's runner with fp32 updates (before fast training), the batched
  runner with fp32 updates, the batched runner with bf16 updates (``precision=bf16``);
* ``cig_td3``: CIG-TD3's full loop (sample 1 env step, one update per env step) at 4 and 30
  agents after a short warm-up, with ``precision`` fp32 and bf16 where the algorithm has it.

Each case builds the algorithm with ``coin_app.training.build_config``, runs one warm-up
iteration, then times ``--iterations`` ``algo.train()`` calls and prints env steps per second.
``benchmarks/ppo_update.py`` and ``benchmarks/learner_update.py`` time the updates alone. One torch thread, a local
Ray session over all cores (the runners sample in the training process, ``num_env_runners=0``).
"""

from __future__ import annotations

import argparse
import os
import time

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import ray  # noqa: E402
import torch  # noqa: E402

from coin_app.algorithms import registry  # noqa: E402
from coin_app.training import build_config  # noqa: E402


def timed_train(name: str, scenario: str, overrides: dict, iterations: int, min_steps: int | None = None) -> dict[str, float]:
    """Env steps/s and wall seconds over ``iterations`` timed ``train()`` calls (after one warm-up iteration)."""
    cfg = build_config(name, scenario, overrides, 0)
    if min_steps is not None:
        cfg = cfg.copy(copy_frozen=False).reporting(min_sample_timesteps_per_iteration=min_steps)
    algo = cfg.build_algo()
    try:
        algo.train()
        start = algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"))
        t0 = time.perf_counter()
        for _ in range(iterations):
            result = algo.train()
        wall = time.perf_counter() - t0
        steps = result["env_runners"]["num_env_steps_sampled_lifetime"] - start
    finally:
        algo.stop()
    return {"env_steps_per_s": steps / wall, "wall_s": wall}


def show(label: str, r: dict[str, float]) -> None:
    """One line of the table."""
    print(f"  {label:<44} {r['env_steps_per_s']:>9.1f} env steps/s  ({r['wall_s']:.0f} s)", flush=True)


def main() -> None:
    """Run the cases and print the comparisons."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--cases", nargs="+", default=["ippo", "nav_ppo", "cig_td3"], choices=["ippo", "nav_ppo", "cig_td3"])
    parser.add_argument("--iterations", type=int, default=2, help="timed iterations per PPO measurement")
    parser.add_argument("--td3-steps", type=int, default=60, help="env steps per timed CIG-TD3 iteration")
    args = parser.parse_args()
    torch.set_num_threads(1)
    ray.init(address="local", include_dashboard=False, log_to_driver=False, configure_logging=False)
    print(f"train throughput, 1 torch thread, {int(ray.cluster_resources()['CPU'])} CPUs, {args.iterations} timed iterations")
    summary = []
    for case, scenario, overrides in (
        ("ippo", "intersection", {"num_agents": 30}),
        ("nav_ppo", "arena", {"stage": "long"}),
    ):
        if case not in args.cases:
            continue
        print(f"{case} on {scenario} {overrides}:")
        rates = {}
        for runner, precision in (("multi_agent", "fp32"), ("batched", "fp32"), ("batched", "bf16")):
            label = f"env_runner={runner} precision={precision}"
            rates[label] = timed_train(case, scenario, {**overrides, "env_runner": runner, "precision": precision}, args.iterations)
            show(label, rates[label])
        base, runner_only, both = (r["env_steps_per_s"] for r in rates.values())
        print(f"  batched / multi_agent: {runner_only / base:.2f}x; with bf16 updates too: {both / base:.2f}x")
        summary.append(f"{case}: {runner_only / base:.2f}x env steps/s with the batched runner, {both / base:.2f}x with bf16 updates too")
    if "cig_td3" in args.cases:
        precisions = ("fp32", "bf16") if "precision" in registry.get("cig_td3").hyperparameters else ("fp32",)
        for agents in (4, 30):
            print(f"cig_td3 on the intersection, {agents} agents, full loop after a 200-step warm-up:")
            rates = {}
            for precision in precisions:
                overrides = {"num_agents": agents, "warmup_steps": 200, "eval_every": 0}
                if len(precisions) > 1:
                    overrides["precision"] = precision
                rates[precision] = timed_train("cig_td3", "intersection", overrides, 1, min_steps=200 + args.td3_steps)
                show(f"precision={precision}", rates[precision])
            if len(rates) > 1:
                ratio = rates["bf16"]["env_steps_per_s"] / rates["fp32"]["env_steps_per_s"]
                summary.append(f"cig_td3 {agents} agents: bf16 {ratio:.2f}x fp32 env steps/s")
    print("summary: " + "; ".join(summary))
    ray.shutdown()


if __name__ == "__main__":
    main()
