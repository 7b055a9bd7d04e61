"""The TD3 family's weight sync, side by side: the in-place copy vs RLlib's ``sync_weights``, in the reduced protocol's loop.

Usage: python benchmarks/weight_sync.py [--algo cig_td3] [--blocks 6] [--steps 100]

Builds one trial of the reduced-scale protocol (``sweep seeds --scale reduced``: the intersection
with 4 agents, batch 256, one update and one actor update per env step), trains it past its
warm-up, then times blocks of ``--steps`` training steps (1 env step and 1 update each), the two
ways of sending the actor to the env runner in turn, block by block, so that a change in the
machine's load hits both alike:

* ``in-place``: ``CigTd3._sync_actor``, the learner's actor tensors copied into the runner's;
* ``rllib``: ``CigTd3.sync_actor_through_rllib``, RLlib's ``EnvRunnerGroup.sync_weights`` (module state -> object store -> load).

It prints the seconds per training step of each, their ratio, and the mean time of one sync call
of each way. Both give the runner the same weights (``tests/test_cig_td3_algorithm.py``).
"""

from __future__ import annotations

import argparse
import os
import time
from collections.abc import Callable

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import ray  # noqa: E402
import torch  # noqa: E402

from tuning import get_experiment  # noqa: E402
from tuning.experiment import expand_grid  # noqa: E402
from tuning.trainable import build_trial_config  # noqa: E402


def main() -> None:
    """Print seconds per training step with each sync, their ratio and the sync calls' own times."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algo", default="cig_td3", choices=("cig_td3", "itd3", "traco"))
    ap.add_argument("--blocks", type=int, default=6, help="timed blocks per way, alternating")
    ap.add_argument("--steps", type=int, default=100, help="training steps (env step + update) per block")
    args = ap.parse_args()
    torch.set_num_threads(1)
    ray.init(include_dashboard=False, log_to_driver=False)  # a local session over the machine's cores; the trial samples in-process
    (trial,) = expand_grid(get_experiment("seeds").param_space("intersection", "reduced", (args.algo,), (0,)))
    cfg = build_trial_config(trial).reporting(min_sample_timesteps_per_iteration=1)
    algo = cfg.build_algo()
    print(f"{args.algo}, the reduced protocol's trial (seed 0): warm-up of {cfg.warmup_steps} env steps ...", flush=True)
    while algo.learner_updates() == 0:
        algo.training_step()
    ways = {"in-place": algo._sync_actor, "rllib": algo.sync_actor_through_rllib}
    step_times: dict[str, list[float]] = {w: [] for w in ways}
    sync_times: dict[str, list[float]] = {w: [] for w in ways}
    for block in range(args.blocks):
        for way, sync in ways.items():

            def timed_sync(sync: Callable[[], None] = sync, way: str = way) -> None:
                t = time.perf_counter()
                sync()
                sync_times[way].append(time.perf_counter() - t)

            algo._sync_actor = timed_sync
            t = time.perf_counter()
            for _ in range(args.steps):
                algo.training_step()
            step_times[way].append((time.perf_counter() - t) / args.steps)
        print(f"  block {block + 1}/{args.blocks}: " + ", ".join(f"{w} {step_times[w][-1] * 1000:.1f} ms" for w in ways), flush=True)
    per = {w: float(np.mean(v)) for w, v in step_times.items()}
    for way in ways:
        print(f"{way:>9}: {per[way] * 1000:.1f} ms per training step; one sync {np.mean(sync_times[way]) * 1000:.2f} ms")
    print(f"in-place / rllib time per training step: {per['in-place'] / per['rllib']:.3f}")
    algo.stop()
    ray.shutdown()


if __name__ == "__main__":
    main()
