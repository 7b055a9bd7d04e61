"""The first progress rows of a reduced-protocol trial (seed 0 by default), as its sweep trial reports them, for a side-by-side check.

Builds the trial exactly as ``python -m coin_app sweep seeds --scale reduced`` does (``tuning``'s trial config, the
40,000-env-step budget and its decay schedule) and runs its first ``--iterations`` RLlib iterations (500 env steps each),
writing ``training.iteration_metrics`` of each (the row Tune writes to progress.csv, timings excluded) as JSON, floats
as hex. Two trees' rows are compared with ``--compare``: the refactor of issue 54 was checked this way.

    PYTHONPATH=. nice python tests/td3_progress_rows.py --algo cig_td3 --iterations 8 --out rows.json
    python tests/td3_progress_rows.py --compare old.json new.json
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path


def rows(algo: str, seed: int, iterations: int) -> list[dict[str, str]]:
    """The first ``iterations`` progress rows of the reduced protocol's ``algo`` trial of ``seed`` (floats as hex)."""
    import ray  # optional: only the recording needs Ray and the training stack
    import torch

    from coin_app.training import iteration_metrics
    from tuning import get_experiment
    from tuning.experiment import expand_grid
    from tuning.trainable import build_trial_config

    torch.set_num_threads(1)
    ray.init(num_cpus=1, include_dashboard=False, log_to_driver=False)
    try:
        (trial,) = expand_grid(get_experiment("seeds").param_space("intersection", "reduced", (algo,), (seed,)))
        algo_ = build_trial_config(trial).build_algo()
        out = []
        for _ in range(iterations):
            row = iteration_metrics(algo_.train())
            out.append({k: float(v).hex() for k, v in sorted(row.items())})
            print(f"env steps {row['env_steps']}", file=sys.stderr, flush=True)
        algo_.stop()
        return out
    finally:
        ray.shutdown()


def compare(a: list[dict[str, str]], b: list[dict[str, str]]) -> tuple[int, float, list[str]]:
    """(rows compared, max |diff| over the common entries, the entries that differ in bits or exist on one side)."""
    worst, differ = 0.0, []
    for i, (ra, rb) in enumerate(zip(a, b)):
        for k in sorted(set(ra) | set(rb)):
            if ra.get(k) != rb.get(k):
                differ.append(f"row {i}: {k} {ra.get(k)} != {rb.get(k)}")
                if k in ra and k in rb:
                    x, y = float.fromhex(ra[k]), float.fromhex(rb[k])
                    if not (math.isnan(x) and math.isnan(y)):
                        worst = max(worst, abs(x - y))
    return min(len(a), len(b)), worst, differ


def main(argv: list[str] | None = None) -> int:
    """Record the rows, or compare two recordings (exit 1 when they differ)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algo", default="cig_td3")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--iterations", type=int, default=8)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--compare", nargs=2, type=Path, metavar=("A", "B"))
    args = parser.parse_args(argv)
    if args.compare:
        n, worst, differ = compare(*(json.loads(p.read_text()) for p in args.compare))
        print(f"{n} rows compared, max |diff| {worst!r}, {len(differ)} entries differ")
        print("\n".join(differ[:20]))
        return 1 if differ else 0
    out = rows(args.algo, args.seed, args.iterations)
    text = json.dumps(out, indent=1) + "\n"
    if args.out:
        args.out.write_text(text)
    else:
        sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
