"""Agent-steps per second of the native simulator, per scenario, on one core.

Usage: python benchmarks/env_throughput.py [--steps 300] [--num-envs 1 16] [--scaling]

Runs each scenario at its default agent count with uniform random actions and with the
heuristic driver, for a single env and for a batch of envs stepped together (the
vectorized core), auto-resetting finished envs. ``--scaling`` adds the step time of one
env from 10 to 48 agents (48 = the maps' spawn capacity, as in MetaDrive).
"""

from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from coin_app.envs.config import DEFAULT_NUM_AGENTS, make_config  # noqa: E402
from coin_app.envs.driving_env import DrivingEnv  # noqa: E402
from coin_app.envs.heuristic import HeuristicDriver  # noqa: E402
from coin_app.envs.simulator import ACTIVE, DrivingSimulator  # noqa: E402


def measure(scenario: str, num_agents: int, num_envs: int, policy: str, steps: int, seed: int = 0) -> tuple[float, float]:
    """(agent-steps/s, ms per batched step) over ``steps`` steps of ``num_envs`` envs."""
    sim = DrivingSimulator(make_config(scenario, num_agents=num_agents), num_envs=num_envs)
    sim.reset(seed)
    rng = np.random.default_rng(seed)
    driver = None
    if policy == "heuristic":
        shell = DrivingEnv(sim.cfg)
        shell.sim = sim
        driver = HeuristicDriver(shell)
    agent_steps = 0
    resets = seed + num_envs
    t0 = time.perf_counter()
    for _ in range(steps):
        active = np.nonzero(sim.status == ACTIVE)[0]
        actions = np.zeros((sim.num_slots, 2))
        if driver is None:
            actions[active] = rng.uniform(-1.0, 1.0, (len(active), 2))
        else:
            actions[active] = driver.act_slots(active)
        res = sim.step(actions)
        agent_steps += int(res.acted.sum())
        over = np.nonzero(res.episode_over)[0]
        if len(over):
            sim.reset_envs(over, list(range(resets, resets + len(over))))
            resets += len(over)
    dt = time.perf_counter() - t0
    return agent_steps / dt, 1000 * dt / steps


def main() -> None:
    """Print the throughput table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--num-envs", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--scenarios", nargs="+", default=list(DEFAULT_NUM_AGENTS))
    ap.add_argument("--scaling", action="store_true", help="also time one env from 10 to 48 agents")
    args = ap.parse_args()
    print(f"{'scenario':<13}{'agents':>7}{'envs':>6}{'policy':>11}{'agent-steps/s':>15}{'ms/step':>9}")
    for sc in args.scenarios:
        for ne in args.num_envs:
            for pol in ("random", "heuristic"):
                rate, ms = measure(sc, DEFAULT_NUM_AGENTS[sc], ne, pol, args.steps)
                print(f"{sc:<13}{DEFAULT_NUM_AGENTS[sc]:>7}{ne:>6}{pol:>11}{rate:>15,.0f}{ms:>9.2f}", flush=True)
    if args.scaling:
        print("\nstep time of one env vs agent count (heuristic driver, intersection):")
        for n in (10, 20, 30, 40, 48):
            rate, ms = measure("intersection", n, 1, "heuristic", args.steps)
            print(f"  {n:>3} agents: {ms:6.2f} ms/step, {rate:>9,.0f} agent-steps/s", flush=True)


if __name__ == "__main__":
    main()
