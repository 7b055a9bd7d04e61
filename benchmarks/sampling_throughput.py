"""Agent-steps per second of sampling, side by side: RLlib's MultiAgentEnvRunner, the batched env runner, and the limit.

Usage: python benchmarks/sampling_throughput.py [--agents 4 10 30] [--envs 1 8 32] [--agent-steps 20000] [--scenario intersection]

For each agent count and envs-per-runner E, three ways to collect the same experience with the
same IPPO policy module (exploration: sampled Gaussian actions), one process, one thread:

(a) ``multi_agent``: RLlib's ``MultiAgentEnvRunner`` on the ``MultiAgentEnv`` adapter (E sub-envs);
(b) ``batched``: coin_app's ``BatchedEnvRunner`` (``coin_app/adapters/batched_runner.py``);
(c) ``limit``: the bare ``DrivingSimulator(num_envs=E)`` plus one forward pass and one action
    sample of the module per step for all acting vehicles, no episodes built.

Each is timed over whole ``sample()`` calls of 50 lock steps (after one warm-up call) until at
least ``--agent-steps`` agent steps; the figures are agent steps per second, and the ratios
b/a and b/c. The issue's targets at 30 agents, E = 8: b >= 5 x a and b >= 0.7 x c.
"""

from __future__ import annotations

import argparse
import os
import time

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import torch  # noqa: E402
from ray.rllib.core.columns import Columns  # noqa: E402
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner  # noqa: E402

from coin_app.adapters.batched_runner import BatchedEnvRunner  # noqa: E402
from coin_app.algorithms.common import SHARED_MODULE_ID, scenario_config_of  # noqa: E402
from coin_app.sim.simulator import ACTIVE, DrivingSimulator  # noqa: E402
from coin_app.training import build_config  # noqa: E402

FRAGMENT = 50  # lock steps per sample() call


def runner_rate(kind: str, scenario: str, agents: int, envs: int, min_agent_steps: int) -> float:
    """Agent steps per second of env runner ``kind`` ("multi_agent" or "batched")."""
    overrides = {"num_agents": agents, "env_runner": kind, "num_envs_per_env_runner": envs, "rollout_fragment_length": FRAGMENT}
    cfg = build_config("ippo", scenario, overrides, 0)
    cls = BatchedEnvRunner if kind == "batched" else MultiAgentEnvRunner
    runner = cls(config=cfg, worker_index=0)
    runner.sample()  # warm-up (reset, first allocations)
    steps, t0 = 0, time.perf_counter()
    while steps < min_agent_steps:
        steps += sum(ep.agent_steps() for ep in runner.sample())
    return steps / (time.perf_counter() - t0)


def limit_rate(scenario: str, agents: int, envs: int, min_agent_steps: int) -> float:
    """Agent steps per second of the bare simulator plus one batched forward pass and action sample per step."""
    cfg = build_config("ippo", scenario, {"num_agents": agents}, 0)
    sim = DrivingSimulator(scenario_config_of(cfg), envs)
    module = BatchedEnvRunner(config=cfg.copy(copy_frozen=False).env_runners(num_env_runners=1), worker_index=0).module[SHARED_MODULE_ID]
    dist_cls = module.get_exploration_action_dist_cls()
    res = sim.reset(0)
    obs = res.obs.copy()
    actions = np.zeros((sim.num_slots, 2))

    def step() -> int:
        nonlocal res
        slots = np.nonzero(sim.status == ACTIVE)[0]
        with torch.no_grad():
            out = module.forward_exploration({Columns.OBS: torch.from_numpy(obs[slots])})
            dist = dist_cls.from_logits(out[Columns.ACTION_DIST_INPUTS])
            a = dist.sample()
            dist.logp(a)
        actions[slots] = np.clip(a.numpy(), -1.0, 1.0)
        res = sim.step(actions)
        fresh = res.acted | res.spawned
        obs[fresh] = res.obs[fresh]
        over = np.nonzero(res.episode_over)[0]
        if len(over):
            r = sim.reset_envs(over, [None] * len(over))
            obs[r.spawned] = r.obs[r.spawned]
        return len(slots)

    for _ in range(FRAGMENT):
        step()
    steps, t0 = 0, time.perf_counter()
    while steps < min_agent_steps:
        for _ in range(FRAGMENT):
            steps += step()
    return steps / (time.perf_counter() - t0)


def main() -> None:
    """Measure and print the table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--agents", type=int, nargs="+", default=[4, 10, 30])
    parser.add_argument("--envs", type=int, nargs="+", default=[1, 8, 32])
    parser.add_argument("--agent-steps", type=int, default=20_000, help="agent steps timed per measurement")
    parser.add_argument("--scenario", default="intersection")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(f"sampling throughput, {args.scenario}, IPPO module, 1 thread, agent steps/s (>= {args.agent_steps} agent steps each)")
    print(f"{'agents':>6} {'E':>4} {'(a) multi_agent':>16} {'(b) batched':>12} {'(c) limit':>10} {'b/a':>6} {'b/c':>6}")
    rows = []
    for agents in args.agents:
        for envs in args.envs:
            a = runner_rate("multi_agent", args.scenario, agents, envs, args.agent_steps)
            b = runner_rate("batched", args.scenario, agents, envs, args.agent_steps)
            c = limit_rate(args.scenario, agents, envs, args.agent_steps)
            rows.append((agents, envs, a, b, c))
            print(f"{agents:>6} {envs:>4} {a:>16,.0f} {b:>12,.0f} {c:>10,.0f} {b / a:>6.2f} {b / c:>6.2f}", flush=True)
    target = [r for r in rows if r[0] == 30 and r[1] == 8]
    if target:
        _, _, a, b, c = target[0]
        print(f"summary: 30 agents, E = 8: batched {b:,.0f} agent-steps/s = {b / a:.1f} x RLlib's runner (target >= 5), "
              f"{b / c:.2f} x the limit (target >= 0.7)")  # fmt: skip


if __name__ == "__main__":
    main()
