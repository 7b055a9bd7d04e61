"""Throughput of the parallel evaluator: the same sweep evaluated with 1 and with N worker processes, side by side.

    python benchmarks/evaluation_throughput.py runs/sweeps/seeds-intersection --test-seeds 20 --workers 2

Prints episodes/s for each worker count, the speed-up, and checks that both give the same results.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))


def main() -> int:
    """Evaluate every final checkpoint of a sweep with 1 and ``--workers`` processes; print both rates."""
    import pandas as pd

    from coin_app.evaluation.protocol import RESULT_COLUMNS, EvalRun, run_evaluation
    from coin_app.evaluation.sweep_results import load_trials
    from coin_app.sim.seeds import eval_test_seeds

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sweep_dir")
    parser.add_argument("--test-seeds", type=int, default=20)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--counts", type=int, nargs="*", default=None)
    args = parser.parse_args()
    runs = [
        EvalRun(t.config["algo"], t.config["variant"], int(t.config["seed"]), str(t.final_checkpoint))
        for t in load_trials(Path(args.sweep_dir))
        if t.final_checkpoint
    ]
    seeds = eval_test_seeds(args.test_seeds)
    results = {}
    for workers in (1, args.workers):
        ev = run_evaluation(runs, seeds, counts=args.counts, workers=workers, log=lambda _: None)
        results[workers] = ev
        rate = len(ev.table) / ev.wall_s
        print(f"workers {workers}: {len(ev.table)} episodes of {len(runs)} models in {ev.wall_s:.1f} s = {rate:.1f} episodes/s")
    one, many = results[1], results[args.workers]
    print(f"speed-up with {args.workers} workers: {one.wall_s / many.wall_s:.2f}x (includes process start and imports)")
    cols = [c for c in RESULT_COLUMNS if c != "wall_time_s"]
    pd.testing.assert_frame_equal(one.table[cols], many.table[cols])
    print("results identical: yes")
    return 0


if __name__ == "__main__":
    sys.exit(main())
