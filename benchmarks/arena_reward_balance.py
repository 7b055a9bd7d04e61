"""What the arena reward (Eqs. 2–6, our constants) pays scripted behaviours on each nav_ppo stage's scenario mix.

Usage: python benchmarks/arena_reward_balance.py [--scenarios 60] [--gamma 0.99] [--seed 1]
                                                 [--reward key=value ...]

For each mix (``short``: the parking stage's 1–8 vehicles and 0–8 obstacles started near their
targets; ``short-1x0``: one vehicle alone; ``long``: the navigation stage's 4 vehicles and 3
obstacles) and each behaviour, the mean and median discounted return from the first step
(``--gamma``, PPO's discount) per vehicle, and the share that parked or collided:

* ``heuristic``: the scripted driver (``coin_app.sim.arena.heuristic``; parks, ignores the others);
* ``avoiding``: the same with a reflex away from the closest entity ahead;
* ``still``: zero actions (stays where it starts);
* ``flee``: full pedal, steering the target behind it.

A reward whose ``still`` or ``flee`` earns as much as ``heuristic`` makes not parking a local
optimum PPO can settle in (docs/arena/README.md). ``--reward`` overrides ``RewardConfig``
constants (e.g. ``--reward collision_reward=-2 sign_free_radius=1.25``) to compare balances.
"""

from __future__ import annotations

import argparse
import ast
import time
from collections.abc import Callable

import numpy as np

from coin_app.algorithms.nav_ppo.settings import STAGES
from coin_app.sim.arena.config import ArenaConfig, make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.heuristic import avoiding_actions, heuristic_actions
from coin_app.sim.arena.simulator import ArenaSimulator

MIXES = {"short": STAGES["short"], "short-1x0": STAGES["short"] | {"max_vehicles": None, "max_obstacles": None}, "long": STAGES["long"]}


def still(obs: np.ndarray) -> np.ndarray:
    """Zero steering and pedal."""
    return np.zeros((len(obs), 2))


def flee(obs: np.ndarray) -> np.ndarray:
    """Full pedal, steering so that the target (obs[:, 0:2], in the vehicle frame) falls behind."""
    away = np.arctan2(-obs[:, 1], -obs[:, 0])
    return np.stack([np.clip(1.5 * away / 0.8, -1.0, 1.0), np.ones(len(obs))], 1)


BEHAVIOURS = {"heuristic": heuristic_actions, "avoiding": avoiding_actions, "still": still, "flee": flee}


def discounted_returns(
    cfg: ArenaConfig, policy: Callable[[np.ndarray], np.ndarray], layouts: list, gamma: float
) -> tuple[np.ndarray, float, float]:
    """Per-vehicle discounted return from step 0 over ``layouts``, and the shares that parked and that collided."""
    sim = ArenaSimulator(cfg)
    returns, parked, collided = [], [], []
    for layout in layouts:
        obs = sim.reset(layout)
        total, discount = np.zeros(sim.num_vehicles), 1.0
        while sim.driving.any():
            step = sim.step(policy(obs))
            total += discount * step.reward
            discount *= gamma
            obs = step.obs
        returns.append(total)
        parked.append(sim.succeeded)
        collided.append(sim.collided)
    return np.concatenate(returns), float(np.concatenate(parked).mean()), float(np.concatenate(collided).mean())


def main() -> None:
    """Print the table of returns by mix and behaviour."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenarios", type=int, default=60, help="generated scenarios per mix")
    ap.add_argument("--gamma", type=float, default=0.99, help="discount (nav_ppo's)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--reward", nargs="*", default=[], metavar="KEY=VALUE", help="RewardConfig overrides")
    args = ap.parse_args()
    if args.scenarios < 1:
        ap.error(f"--scenarios {args.scenarios}: allowed: an integer >= 1")
    if not 0 < args.gamma <= 1:
        ap.error(f"--gamma {args.gamma}: allowed: a number in (0, 1]")
    reward = {}
    for item in args.reward:
        key, sep, value = item.partition("=")
        if not sep:
            ap.error(f"--reward {item!r}: allowed: KEY=VALUE")
        try:
            reward[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            ap.error(f"--reward {item!r}: allowed: KEY=VALUE with a Python literal VALUE")
    try:
        make_arena_config(reward=reward)  # unknown keys or bad values fail here, before any work
    except (ValueError, TypeError) as exc:
        ap.error(f"--reward: {exc}")
    t0 = time.perf_counter()
    print(f"discounted return per vehicle from step 0 (gamma {args.gamma}), {args.scenarios} scenarios per mix, reward overrides {reward}")
    print(f"{'mix':10s} {'behaviour':10s} {'mean':>8s} {'median':>8s} {'parked':>7s} {'collided':>8s}")
    best = {}
    for mix, values in MIXES.items():
        cfg = make_arena_config(**values, reward=reward)
        env = ArenaEnv(cfg)
        env.reset(seed=args.seed)
        layouts = [env.draw_layout() for _ in range(args.scenarios)]
        for name, policy in BEHAVIOURS.items():
            returns, parked, collided = discounted_returns(cfg, policy, layouts, args.gamma)
            print(f"{mix:10s} {name:10s} {returns.mean():8.1f} {np.median(returns):8.1f} {parked:7.2f} {collided:8.2f}")
            if mix not in best or returns.mean() > best[mix][1]:
                best[mix] = (name, float(returns.mean()))
    winners = ", ".join(f"{mix} {name}" for mix, (name, _) in best.items())
    print(f"summary ({time.perf_counter() - t0:.0f} s): the best-paid behaviour by mean return: {winners}")


if __name__ == "__main__":
    main()
