"""Learning curves: success rate vs env steps of the algorithms (3 seeds) on one small scenario.

Usage: python benchmarks/learning_curves.py [--algos cig_td3 itd3] [--steps 20000] [--eval-every 2500]
                                            [--seeds 0 1 2] [--scenario intersection] [--set key=value ...]
                                            [--out runs/curves]

``--algos`` takes any registered driving algorithm: cig_td3, itd3, ippo, cppo, mfpo, copo
(e.g. ``--algos ippo cppo mfpo copo --steps 100000 --eval-every 10000`` for the PPO family,
which samples 1024 env steps per update).

The small scenario is the algorithm's quick settings (``registry.quick_settings``: 4 agents,
horizon 300, small networks). The intersection is the default: vehicles first arrive there after
~15k env steps, while the bottleneck (the hardest COIN map; IPPO reaches 24 % after 1M steps in
CoPO's MetaDrive benchmark) gave ITD3 no arrival within 45k.

Each (algorithm, seed) run trains in its own process (``--procs`` at a time, each with an equal
share of the CPU cores as torch threads) and evaluates its deterministic actor on the
validation seeds every ``--eval-every`` env steps. Writes ``curves.csv`` (algo, seed,
env_steps, metric columns) and ``curves.png`` (mean ± std of the success rate over seeds) and
prints the final table.
"""

from __future__ import annotations

import argparse
import csv
import json
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np


def run_one(job: tuple[str, int, str, int, int, dict, int, int]) -> list[dict]:
    """Train one (algo, seed) run and return its evaluation rows."""
    algo_name, seed, scenario, steps, eval_every, overrides, eval_episodes, threads = job
    import ray
    import torch

    from coin_app.algorithms.registry import get, quick_settings
    from coin_app.sim.seeds import validation_seeds
    from coin_app.training import build_config, evaluate_algorithm

    torch.set_num_threads(1)
    ray.init(address="local", num_cpus=1, include_dashboard=False, log_to_driver=False, configure_logging=False)
    # the algorithm's quick settings; --set keys apply to every algorithm (unknown ones are refused)
    settings = {**quick_settings(algo_name), **overrides}
    if "learner_threads" in get(algo_name).keys():
        settings.setdefault("learner_threads", threads)
    cfg = build_config(algo_name, scenario, settings, seed).reporting(min_sample_timesteps_per_iteration=eval_every)
    algo = cfg.build_algo()
    rows = []
    sampled = 0
    t0 = time.perf_counter()
    while sampled < steps:
        res = algo.train()
        sampled = int(res["env_runners"]["num_env_steps_sampled_lifetime"])
        ev = evaluate_algorithm(algo, validation_seeds(eval_episodes))
        ev["eval_episode_steps"] = ev.pop("env_steps")  # the evaluation episodes' length, not training steps
        rows.append({"algo": algo_name, "seed": seed, "env_steps": sampled, "wall_s": round(time.perf_counter() - t0, 1), **ev})
        print(f"{algo_name} seed {seed}: {sampled} steps, success {ev['success_rate']:.3f}", flush=True)
    algo.stop()
    ray.shutdown()
    return rows


def plot(rows: list[dict], path: Path, title: str) -> None:
    """Mean ± std over seeds of the success rate and of the per-vehicle return, one line per algorithm."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(fig)
    for k, (key, label) in enumerate((("success_rate", "success rate"), ("episode_return", "mean return per vehicle"))):
        ax = fig.add_subplot(1, 2, k + 1)
        for algo in sorted({r["algo"] for r in rows}):
            steps = sorted({r["env_steps"] for r in rows if r["algo"] == algo})
            vals = [[float(r[key]) for r in rows if r["algo"] == algo and r["env_steps"] == s] for s in steps]
            mean = np.array([np.mean(v) for v in vals])
            std = np.array([np.std(v) for v in vals])
            ax.plot(steps, mean, label=algo)
            ax.fill_between(steps, mean - std, mean + std, alpha=0.2)
        ax.set_xlabel("env steps")
        ax.set_ylabel(f"{label} (validation seeds)")
        if key == "success_rate":
            ax.set_ylim(-0.02, 1.02)
        ax.legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path)


def main() -> None:
    """Run every (algorithm, seed), then write the CSV, the PNG and a summary."""
    from coin_app.algorithms.registry import parse_overrides, quick_settings

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algos", nargs="+", default=["cig_td3", "itd3"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--scenario", default="intersection")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--eval-every", type=int, default=2500)
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument("--procs", type=int, default=2, help="runs trained at once (each gets cpu_count // procs torch threads)")
    ap.add_argument("--out", default="runs/curves")
    args = ap.parse_args()
    # runs in parallel share the cores: one torch thread each unless --set learner_threads=N
    threads = max(1, (os.cpu_count() or 1) // args.procs)
    overrides = parse_overrides(args.set)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    jobs = [
        (a, s, args.scenario, args.steps, args.eval_every, overrides, args.eval_episodes, threads) for a in args.algos for s in args.seeds
    ]
    print(
        f"{len(jobs)} runs of {args.steps} env steps on {args.scenario} ({args.procs} at a time); "
        f"quick settings {[quick_settings(a) for a in args.algos]} + {overrides}"
    )
    with mp.get_context("spawn").Pool(args.procs) as pool:
        rows = [r for rows in pool.map(run_one, jobs) for r in rows]
    with open(out / "curves.csv", "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, out / "curves.png", f"{args.scenario}: success vs env steps ({len(args.seeds)} seeds)")
    (out / "settings.json").write_text(
        json.dumps(vars(args) | {"quick_settings": {a: quick_settings(a) for a in args.algos}, "overrides": overrides}, indent=2)
    )
    print("\nfinal evaluation (mean ± std over seeds):")
    for algo in args.algos:
        runs = {r["seed"] for r in rows if r["algo"] == algo}
        final = [max((r for r in rows if r["algo"] == algo and r["seed"] == s), key=lambda r: r["env_steps"]) for s in runs]
        for key in ("success_rate", "collision_rate", "out_of_road_rate", "episode_return"):
            v = [r[key] for r in final]
            print(f"  {algo:<8} {key:<17} {np.mean(v):.3f} ± {np.std(v):.3f}")
    print(f"wrote {out / 'curves.csv'} and {out / 'curves.png'}")


if __name__ == "__main__":
    main()
