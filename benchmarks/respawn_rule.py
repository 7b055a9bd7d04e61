"""The COIN authors' actors natively under two respawn rules, side by side: success and time-outs per ``respawns_per_step``.

Usage (the authors' actors, see ``python -m coin_app evaluate-reference --help``)::

    python benchmarks/respawn_rule.py [--scene intersection] [--episodes 25] [--values 0 1]

Each of the 8 actors drives ``--episodes`` episodes (seeds 1000 + 100 i) of the reference scenario with each value of
``respawns_per_step`` (0: every free entry place at once, the native rule before 2026-12-02; 1: MetaDrive's); printed:
the mean over actors of the success rate (and its standard error over actors) and of the time-out rate.
"""

from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np
from threadpoolctl import threadpool_limits

from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.reference import episode_seeds, reference_config
from coin_app.inference.coin_actors import actors_root, find_coin_actors, load_coin_actor


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actors", default=None, help="the authors' actors (default: $COIN_OFFICIAL_ACTORS)")
    ap.add_argument("--scene", default="intersection", choices=("intersection", "roundabout", "bottleneck"))
    ap.add_argument("--episodes", type=int, default=25, help="episodes per actor")
    ap.add_argument("--values", type=int, nargs="+", default=[0, 1], help="respawns_per_step values to compare")
    args = ap.parse_args()
    if args.episodes < 1 or any(v < 0 for v in args.values):
        ap.error(f"bad --episodes {args.episodes} or --values {args.values}; allowed: episodes >= 1, values >= 0")
    actors = find_coin_actors(actors_root(args.actors), args.scene)
    with threadpool_limits(limits=1, user_api="blas"):
        for value in args.values:
            cfg = dataclasses.replace(reference_config(args.scene, "native"), respawns_per_step=value)
            start, success, timeout = time.perf_counter(), [], []
            for _, path in sorted(actors.items()):
                episodes = evaluate_policy(load_coin_actor(path), cfg, episode_seeds(args.episodes))
                success.append(np.mean([e["success_rate"] for e in episodes]))
                timeout.append(np.mean([e["num_timeout"] / e["num_vehicles"] for e in episodes]))
            se = 100 * np.std(success, ddof=1) / np.sqrt(len(success))
            print(
                f"{args.scene} respawns_per_step={value}: success {100 * np.mean(success):.2f} % (SE over actors {se:.2f}); "
                f"time-out {100 * np.mean(timeout):.2f} %; {len(success)} x {args.episodes} episodes, {time.perf_counter() - start:.0f} s",
                flush=True,
            )


if __name__ == "__main__":
    main()
