"""How close nav_ppo's warm-start clone gets to its scripted driver, and whether the clone parks.

Usage: python benchmarks/arena_clone_quality.py [--driver heuristic|avoiding|planning] [--stage short|long]
                                                [--episodes 200] [--epochs 10] [--cases 1x0,4x4]
                                                [--scenarios-per-case 20] [--seed 0] [--lone-fraction 0]
                                                [--observed-entities 1] [--candidate-features] [--rounds 1] [--weight 1]

Runs exactly the warm start of ``--set warm_start=<driver>`` (``coin_app/algorithms/nav_ppo/warm_start.py``)
on a fresh ``[256, 256]`` nav_ppo module, without PPO: demonstrations of the stage's scenario mix,
then the clone. Prints the clone's action MSE on its training demonstrations and on 20 held-out
noiseless scenarios, then the success-to-goal rate of the clone (deterministic) and of the driver
on the test suite's held-out seeds (``evaluate-arena --generator short`` for the short stage, the
paper's suite for the long one). ``--lone-fraction`` is the arena option of that name for the
demonstrations' mix (``--set lone_fraction=...`` in training); ``--rounds R`` adds R - 1 DAgger
rounds (``--set warm_start_rounds=R``); ``--weight W`` weighs the rows where the driver's filter acted
(``--set warm_start_weight=W``); ``--observed-entities K`` the arena
option ``observed_entities`` (the K closest entities in every observation, for the driver, its
demonstrations, the clone and both scores; 1 is the paper's); ``--candidate-features`` the arena option
``candidate_features`` (the clearance of the planning filter's candidate rollouts in every observation).
"""

from __future__ import annotations

import argparse
import time

import torch

import coin_app.evaluation.arena_suite as suite
from coin_app.algorithms.checkpoints import actor_policy
from coin_app.algorithms.nav_ppo.config import progress
from coin_app.algorithms.nav_ppo.settings import DEFAULT, STAGES
from coin_app.algorithms.nav_ppo.warm_start import heuristic_demonstrations, warm_start
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.heuristic import DRIVERS
from coin_app.training import fresh_module

LOG_STD = -1.5  # the initial std e^-1.5 = 0.22 of the warm-start runs in docs/arena/README.md


def main() -> None:
    """Clone, then score the clone and its driver."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--driver", choices=tuple(DRIVERS), default="heuristic")
    ap.add_argument("--stage", choices=tuple(STAGES), default="short")
    ap.add_argument("--episodes", type=int, default=DEFAULT.warm_start_episodes)
    ap.add_argument("--epochs", type=int, default=DEFAULT.warm_start_epochs)
    ap.add_argument("--cases", default="1x0,4x4", help="suite cases to score, e.g. 1x0,4x4,8x8")
    ap.add_argument("--scenarios-per-case", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lone-fraction", type=float, default=0.0, help="share of 1-vehicle, 0-obstacle demonstration scenarios")
    ap.add_argument("--observed-entities", type=int, default=1, help="entities each vehicle observes (1: the paper's)")
    ap.add_argument("--candidate-features", action="store_true", help="the arena option candidate_features=True (not the paper's)")
    ap.add_argument("--rounds", type=int, default=1, help="warm-start rounds: 1 = cloning, R > 1 adds R - 1 DAgger rounds")
    ap.add_argument("--weight", type=float, default=1.0, help="warm_start_weight: weight of the rows where the driver's filter acted")
    args = ap.parse_args()
    if args.episodes < 1 or args.epochs < 0 or args.scenarios_per_case < 1 or args.rounds < 1 or not args.weight > 0:
        ap.error(
            f"--episodes {args.episodes}, --epochs {args.epochs}, --scenarios-per-case {args.scenarios_per_case}, --rounds {args.rounds}, "
            f"--weight {args.weight}: allowed >= 1, >= 0, >= 1, >= 1, > 0"
        )
    try:
        cases = suite.parse_cases(args.cases)
        arena = {"lone_fraction": args.lone_fraction, "observed_entities": args.observed_entities}
        arena |= {"candidate_features": True} if args.candidate_features else {}
        cfg = make_arena_config(**STAGES[args.stage], **arena)
    except ValueError as exc:
        ap.error(str(exc))
    torch.set_num_threads(1)
    t0 = time.perf_counter()
    module = fresh_module("nav_ppo", "arena", {"stage": args.stage, "log_std_init": LOG_STD, **arena}, seed=args.seed)
    noise = DEFAULT.warm_start_noise
    losses, rounds = warm_start(
        module, cfg, args.driver, args.episodes, noise, args.epochs, LOG_STD, args.seed, 0.99, args.rounds, log=progress, weight=args.weight
    )
    rows = sum(len(r.obs) for r in rounds)
    held_out = heuristic_demonstrations(cfg, 20, args.seed + 10_000, 0.0, 0.99, args.driver)
    policy = suite.WithMeta(actor_policy(module), {"scenario": "arena", "env_config": arena})  # the suite observes as it trained
    held_mse = float(((policy(held_out.obs) - held_out.actions) ** 2).mean())
    print(
        f"{args.driver} driver, stage {args.stage}: {rows} rows from {args.rounds} x {args.episodes} scenarios "
        f"(lone fraction {args.lone_fraction}, {args.observed_entities} observed entities"
        f"{', candidate features' if args.candidate_features else ''}), {args.epochs} epochs, "
        f"intervention weight {args.weight}"
    )
    weighted = " (weighted)" if args.weight != 1.0 else ""
    print(
        f"  clone action MSE: {losses['action_mse']:.3f} on its demonstrations{weighted}, {held_mse:.3f} on 20 held-out noiseless scenarios"
    )
    print(
        "  success while collecting, by round (round 0 the driver, then the clone; half the scenarios noisy): "
        + ", ".join(f"{r.success_rate:.3f}" for r in rounds)
    )
    generator = "short" if args.stage == "short" else "agnn"
    load = suite.load_arena_policy
    suite.load_arena_policy = lambda source: policy if source == "clone" else load(source)  # the suite's policy loader, in-process
    try:
        scores = {}
        for name in ("clone", args.driver):
            rows = suite.evaluate_suite(
                name, cases, args.scenarios_per_case, workers=1, log=lambda s: None, generator=generator, observed=args.observed_entities
            )
            scores[name] = {f"{int(r.vehicles)}x{int(r.obstacles)}": r.success_to_goal_rate for r in suite.summarize(rows).itertuples()}
    finally:
        suite.load_arena_policy = load
    for name, by_case in scores.items():
        print(f"  {name:9s} success-to-goal ({generator} scenarios): " + " ".join(f"{c} {v:.2f}" for c, v in by_case.items()))
    print(
        f"summary ({time.perf_counter() - t0:.0f} s): clone {held_mse:.3f} held-out MSE; success clone/driver "
        + ", ".join(f"{c} {scores['clone'][c]:.2f}/{scores[args.driver][c]:.2f}" for c in scores["clone"])
    )


if __name__ == "__main__":
    main()
