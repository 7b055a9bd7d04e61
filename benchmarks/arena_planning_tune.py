"""How the planning driver's horizon and margin were chosen: its success on arena *training* scenarios.

Usage: python benchmarks/arena_planning_tune.py [--horizons 10 15 25] [--margins 0.1 0.3 0.6]
                                                [--cases 1x4,2x8,4x4,6x8,10x0,15x4,20x8]
                                                [--scenarios-per-case 10] [--reference avoiding]
                                                [--observed-entities 1]

Scores ``planning_actions`` (``coin_app/sim/arena/heuristic.py``) for every (horizon, margin) of
the grid on training scenarios only (``generator.training_rng``, one stream per case; never the
suite's held-out scenarios), with the suite's settings (``arena_suite.suite_config``: 400 steps,
the seed paper's success test). Each row prints the success-to-goal rate averaged over the cases,
then per case success / share of vehicles that collided / share that timed out without a
collision. ``--reference`` adds a row for another scripted driver. ``--observed-entities K`` lets
every driver observe the K closest entities (the arena option; 1, the paper's, by default), which
the planning driver's filter then checks all. The defaults are the grid that
chose the driver's defaults (horizon 25, margin 0.6) on 2026-11-27; larger horizons (40) and
margins (1.0, 1.5) scored lower there.
"""

from __future__ import annotations

import argparse
import functools
import itertools
import time
from collections.abc import Callable

import numpy as np

from coin_app.evaluation.arena_suite import parse_cases, run_scenario, suite_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.generator import generate, training_rng
from coin_app.sim.arena.heuristic import DRIVERS, planning_actions

DEFAULT_CASES = "1x4,2x8,4x4,6x8,10x0,15x4,20x8"


def case_outcomes(
    driver: Callable[[np.ndarray], np.ndarray], env: ArenaEnv, case: tuple[int, int], scenarios: int
) -> tuple[float, float, float]:
    """(success-to-goal, collided, timed out without collision) shares of the case's vehicles over its training scenarios."""
    n, m = case
    rng = training_rng(1000 + 31 * n + m)  # one fixed training stream per case
    success = collided = timeout = 0
    for _ in range(scenarios):
        run_scenario(driver, env, generate(rng, env.config, n, m))
        sim = env.sim
        success += int((sim.succeeded & ~sim.collided).sum())
        collided += int(sim.collided.sum())
        timeout += int((~sim.succeeded & ~sim.collided).sum())
    total = n * scenarios
    return success / total, collided / total, timeout / total


def main() -> None:
    """Print one row per driver setting: mean success over the cases, then each case's outcome shares."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--horizons", type=int, nargs="+", default=[10, 15, 25])
    ap.add_argument("--margins", type=float, nargs="+", default=[0.1, 0.3, 0.6])
    ap.add_argument("--cases", default=DEFAULT_CASES, help="cases as vehicles x obstacles, e.g. 1x4,10x0")
    ap.add_argument("--scenarios-per-case", type=int, default=10)
    ap.add_argument("--reference", choices=(*DRIVERS, "none"), default="avoiding", help="another scripted driver to print beside")
    ap.add_argument("--observed-entities", type=int, default=1, help="entities each vehicle observes (1: the paper's)")
    args = ap.parse_args()
    bad = [h for h in args.horizons if h < 1] + [m for m in args.margins if not np.isfinite(m) or m < 0]
    if bad or args.scenarios_per_case < 1:
        ap.error(f"bad value(s) {bad or args.scenarios_per_case}; allowed: horizons >= 1, margins >= 0 (metres), --scenarios-per-case >= 1")
    try:
        cases = parse_cases(args.cases)
    except ValueError as exc:
        ap.error(str(exc))
    try:
        env = ArenaEnv(suite_config(400, {"observed_entities": args.observed_entities}, "arena"))
    except ValueError as exc:
        ap.error(str(exc))
    rows: list[tuple[str, Callable[[np.ndarray], np.ndarray]]] = []
    if args.reference != "none":
        rows.append((args.reference, DRIVERS[args.reference]))
    for h, m in itertools.product(args.horizons, args.margins):
        rows.append((f"planning h{h} m{m:g}", functools.partial(planning_actions, horizon=h, margin=m)))
    print(
        f"{len(cases)} cases x {args.scenarios_per_case} training scenarios, {args.observed_entities} observed entities; "
        "per case: success / collided / timed out"
    )
    print(f"{'driver':<20}{'mean':>7}  " + "  ".join(f"{n}x{m:<13}" for n, m in cases))
    t_all, best = time.perf_counter(), ("", -1.0)
    for name, driver in rows:
        t0 = time.perf_counter()
        out = [case_outcomes(driver, env, case, args.scenarios_per_case) for case in cases]
        mean = float(np.mean([o[0] for o in out]))
        cells = "  ".join(f"{s:.2f}/{c:.2f}/{t:.2f}" for s, c, t in out)
        print(f"{name:<20}{mean:>7.3f}  {cells}  ({time.perf_counter() - t0:.0f} s)", flush=True)
        if name.startswith("planning") and mean > best[1]:
            best = (name, mean)
    print(f"\nbest planning setting: {best[0]} ({best[1]:.3f}); {len(rows)} rows in {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
