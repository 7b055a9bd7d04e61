"""Per-step latency of computing every agent's action in one batch, for each export format, on one CPU thread.

Usage: python benchmarks/inference_latency.py [--batches 1 20 30 40] [--calls 3000] [--repeats 5]
                                              [--algos cig_td3 nav_ppo] [--out FILE.md]

For each algorithm's paper-size actor (CIG-TD3: 91 -> 256 -> 256 -> 2; nav_ppo: 13 -> 256 ->
256 -> 2), freshly built by its RLlib config, the script exports the actor in every format
(``coin_app.inference``), loads it back the Ray-free way, and times ``policy(obs)`` for a batch
of N observations (N = one per agent). The torch actor called directly (eager, under
``torch.inference_mode``) is the reference. Formats and batch sizes are timed interleaved, round
robin, ``--repeats`` rounds of ``--calls`` calls each, so every figure of one run saw the same
machine; the figure is the median call time over all calls, in milliseconds. All libraries run
one thread (``OMP_NUM_THREADS=1`` etc. are set before numpy loads, ``torch.set_num_threads(1)``,
onnxruntime ``intra_op_num_threads=1``).

Targets: the COIN paper reports about 0.26 ms per step, the seed-2 paper 0.17-0.25 ms for 1-20
vehicles; our target is <= 0.05 ms for 40 agents with the fastest format.
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import platform  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402
import torch  # noqa: E402

from coin_app.inference import FORMATS, export_policy, load_policy  # noqa: E402
from coin_app.training import fresh_module  # noqa: E402

TARGET_MS = 0.05


def eager(actor: torch.nn.Module) -> Callable[[np.ndarray], np.ndarray]:
    """The torch actor called directly (the reference)."""

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.inference_mode():
            return actor(torch.from_numpy(obs)).numpy()

    return policy


def time_round(policy: Callable[[np.ndarray], np.ndarray], obs: np.ndarray, calls: int) -> np.ndarray:
    """Seconds of each of ``calls`` calls of ``policy(obs)``."""
    out = np.empty(calls)
    clock = time.perf_counter
    for i in range(calls):
        t = clock()
        policy(obs)
        out[i] = clock() - t
    return out


def main() -> None:
    """Export, load and time every format; print the table (and write it with --out)."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 20, 30, 40], help="observations per call (agents)")
    ap.add_argument("--calls", type=int, default=3000, help="calls per format, batch and round")
    ap.add_argument("--repeats", type=int, default=5, help="interleaved rounds")
    ap.add_argument("--algos", nargs="+", default=["cig_td3", "nav_ppo"])
    ap.add_argument("--out", default=None, help="also write the table as markdown here")
    args = ap.parse_args()
    if min(args.batches) < 1 or args.calls < 1 or args.repeats < 1:
        sys.exit(f"bad sizes: batches {args.batches}, calls {args.calls}, repeats {args.repeats}; allowed: integers >= 1")
    torch.set_num_threads(1)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for algo in args.algos:
            actor = fresh_module(algo).deterministic_actor().eval()
            obs_dim = next(m for m in actor.modules() if isinstance(m, torch.nn.Linear)).in_features
            policies = {"torch eager": eager(actor)}
            for fmt, (suffix, _, _) in FORMATS.items():
                policies[fmt] = load_policy(export_policy(actor, Path(tmp) / f"{algo}{suffix}", fmt))
            sizes = " -> ".join([str(obs_dim)] + [str(m.out_features) for m in actor.modules() if isinstance(m, torch.nn.Linear)])
            print(f"{algo}: actor {sizes}; {args.repeats} rounds x {args.calls} calls per format and batch", flush=True)
            rng = np.random.default_rng(0)
            obs = {n: rng.uniform(0, 1, (n, obs_dim)).astype(np.float32) for n in args.batches}
            times = {(f, n): [] for f in policies for n in args.batches}
            for r in range(args.repeats):
                for n in args.batches:
                    for f, p in policies.items():
                        p(obs[n])  # warm-up of this shape
                        times[f, n].append(time_round(p, obs[n], args.calls))
                print(f"  round {r + 1}/{args.repeats} done", flush=True)
            for f in policies:
                rows.append((algo, sizes, f, [1e3 * float(np.median(np.concatenate(times[f, n]))) for n in args.batches]))
    head = "| actor | format | " + " | ".join(f"batch {n} (ms)" for n in args.batches) + " |"
    lines = [head, "|---|---|" + "---:|" * len(args.batches)]
    for algo, sizes, f, ms in rows:
        lines.append(f"| {algo} ({sizes}) | {f} | " + " | ".join(f"{m:.4f}" for m in ms) + " |")
    table = "\n".join(lines)
    print("\nmedian time per call (all agents' actions in one batch), one CPU thread:\n")
    print(table)
    if 40 in args.batches:
        k = args.batches.index(40)
        for algo in args.algos:
            best = min((r for r in rows if r[0] == algo and r[2] != "torch eager"), key=lambda r: r[3][k])
            ok = "meets" if best[3][k] <= TARGET_MS else "misses"
            print(f"{algo}: fastest export format for 40 agents: {best[2]} {best[3][k]:.4f} ms ({ok} the {TARGET_MS} ms target)")
    info = f"{platform.processor() or platform.machine()}, Python {platform.python_version()}, torch {torch.__version__}"
    print(f"machine: {info}")
    if args.out:
        Path(args.out).write_text(f"Made by `python benchmarks/inference_latency.py` ({info}).\n\n{table}\n")
        print(f"table: {args.out}")


if __name__ == "__main__":
    main()
