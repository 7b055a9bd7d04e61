"""Learning curves: success rate vs env steps of the algorithms (3 seeds) on one small scenario.

Usage: python benchmarks/learning_curves.py [--algos cig_td3 itd3] [--steps 20000] [--eval-every 2500]
                                            [--seeds 0 1 2] [--scenario intersection] [--set key=value ...]
                                            [--out runs/curves]

``--algos`` takes any registered driving algorithm: cig_td3, itd3, traco, ippo, cppo, mfpo, copo
(e.g. ``--algos ippo cppo mfpo copo --steps 100000 --eval-every 10000`` for the PPO family,
which samples 1600 env steps per update).

The small scenario is the algorithm's quick settings (``registry.quick_settings``: 4 agents,
horizon 300, small networks). The intersection is the default: vehicles first arrive there after
~15k env steps, while the bottleneck (the hardest COIN map; IPPO reaches 24 % after 1M steps in
CoPO's MetaDrive benchmark) gave ITD3 no arrival within 45k.

Each (algorithm, seed) run trains in its own process (``--procs`` at a time, each with an equal
share of the CPU cores as torch threads) and evaluates its deterministic actor on the
validation seeds every ``--eval-every`` env steps. Writes ``curves.csv`` (algo, seed,
env_steps, metric columns) and ``curves.png`` (mean ± std of the success rate over seeds) and
prints the final table.

Nothing finished is lost: the runs are ordered seed by seed (every variant of seed 0, then of
seed 1, ...), each finished run's rows are appended to ``curves.csv`` at once and the table and
figure are rewritten from whatever has finished; running the same command again skips the runs
already in ``curves.csv`` (a session cut mid-comparison resumes where it stopped).
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


def run_one(job: tuple[str, str, int, str, int, int, dict, int, int]) -> list[dict]:
    """Train one (algo, variant, seed) run and return its evaluation rows."""
    algo_name, variant, seed, scenario, steps, eval_every, overrides, eval_episodes, threads = job
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
        row = {
            "algo": algo_name,
            "variant": variant,
            "seed": seed,
            "env_steps": sampled,
            "wall_s": round(time.perf_counter() - t0, 1),
            **ev,
        }
        rows.append(row)
        state = "  FROZEN (every vehicle timed out)" if frozen(row) else ""
        print(f"{algo_name} {variant} seed {seed}: {sampled} steps, success {ev['success_rate']:.3f}{state}", flush=True)
    algo.stop()
    ray.shutdown()
    return rows


def frozen(row: dict) -> bool:
    """An evaluation where every vehicle timed out: no arrival, crash or exit (the TD3 full-brake freeze, or a crawl)."""
    return float(row["num_vehicles"]) > 0 and float(row["num_outcome_timeout"]) == float(row["num_vehicles"])


def parse_variants(items: list[str]) -> dict[str, dict]:
    """``NAME`` or ``NAME:KEY=VALUE,KEY=VALUE`` strings to {name: overrides}."""
    from coin_app.algorithms.checks import parse_overrides

    out = {}
    for item in items:
        name, _, spec = item.partition(":")
        if not name or name in out:
            raise ValueError(f"bad --variants entry {item!r}; expected a new NAME or NAME:KEY=VALUE,KEY=VALUE")
        out[name] = parse_overrides([kv for kv in spec.split(",") if kv])
    return out


def freeze_table(rows: list[dict]) -> str:
    """Markdown: per (algorithm, variant) the seeds frozen at the end, the share of frozen evaluations and the final success."""
    lines = [
        "| algorithm | variant | seeds | frozen at the end | frozen evaluations | final success (mean ± std) | final collision |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for algo, variant in sorted({(r["algo"], r["variant"]) for r in rows}):
        runs = [r for r in rows if r["algo"] == algo and r["variant"] == variant]
        seeds = sorted({r["seed"] for r in runs})
        final = [max((r for r in runs if r["seed"] == s), key=lambda r: int(r["env_steps"])) for s in seeds]
        success = [float(r["success_rate"]) for r in final]
        collision = [float(r["collision_rate"]) for r in final]
        lines.append(
            f"| {algo} | {variant} | {len(seeds)} | {sum(frozen(r) for r in final)} | {sum(frozen(r) for r in runs)}/{len(runs)} | "
            f"{np.mean(success):.3f} ± {np.std(success):.3f} | {np.mean(collision):.3f} |"
        )
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path, title: str) -> None:
    """Mean ± std over seeds of the success rate and of the per-vehicle return, one line per algorithm."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(10, 4), dpi=110)
    FigureCanvasAgg(fig)
    for k, (key, label) in enumerate((("success_rate", "success rate"), ("episode_return", "mean return per vehicle"))):
        ax = fig.add_subplot(1, 2, k + 1)
        for algo in sorted({r["algo"] for r in rows}):
            steps = sorted({int(r["env_steps"]) for r in rows if r["algo"] == algo})
            vals = [[float(r[key]) for r in rows if r["algo"] == algo and int(r["env_steps"]) == s] for s in steps]
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
    from coin_app.algorithms.checks import parse_overrides
    from coin_app.algorithms.registry import quick_settings

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--algos", nargs="+", default=["cig_td3", "itd3"])
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--scenario", default="intersection")
    ap.add_argument("--steps", type=int, default=20000)
    ap.add_argument("--eval-every", type=int, default=2500)
    ap.add_argument("--eval-episodes", type=int, default=5)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE")
    ap.add_argument(
        "--variants",
        nargs="+",
        default=["default"],
        metavar="NAME[:KEY=VALUE,...]",
        help="settings compared side by side, e.g. paper guard:actor_preact_penalty=1e-3,actor_preact_threshold=2",
    )
    ap.add_argument("--procs", type=int, default=2, help="runs trained at once (each gets cpu_count // procs torch threads)")
    ap.add_argument("--out", default="runs/curves")
    args = ap.parse_args()
    # runs in parallel share the cores: one torch thread each unless --set learner_threads=N
    threads = max(1, (os.cpu_count() or 1) // args.procs)
    overrides = parse_overrides(args.set)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    variants = parse_variants(args.variants)
    jobs = [
        (a, v, s, args.scenario, args.steps, args.eval_every, overrides | extra, args.eval_episodes, threads)
        for s in args.seeds
        for a in args.algos
        for v, extra in variants.items()
    ]
    csv_path = out / "curves.csv"
    rows = read_rows(csv_path)
    done = {(r["algo"], r["variant"], int(r["seed"])) for r in rows}
    todo = [j for j in jobs if (j[0], j[1], j[2]) not in done]
    (out / "settings.json").write_text(
        json.dumps(
            vars(args) | {"quick_settings": {a: quick_settings(a) for a in args.algos}, "overrides": overrides, "variants": variants},
            indent=2,
        )
    )
    print(
        f"{len(jobs)} runs of {args.steps} env steps on {args.scenario} ({args.procs} at a time, "
        f"{len(jobs) - len(todo)} already in {csv_path}); quick settings {[quick_settings(a) for a in args.algos]} + {overrides}",
        flush=True,
    )
    with mp.get_context("spawn").Pool(args.procs) as pool:
        for k, run_rows in enumerate(pool.imap_unordered(run_one, todo), 1):
            append_rows(csv_path, run_rows)
            rows = read_rows(csv_path)  # one type for every row (as read back from the CSV)
            write_summary(rows, out, args.scenario, len(variants))
            last = run_rows[-1]
            print(
                f"[{k}/{len(todo)}] finished {last['algo']} {last['variant']} seed {last['seed']}: "
                f"success {float(last['success_rate']):.3f} at {last['env_steps']} env steps",
                flush=True,
            )
    if not rows:
        print("no run finished; nothing written")
        return
    table = write_summary(rows, out, args.scenario, len(variants))
    print("\nfinal evaluation (mean ± std over seeds):")
    for label in sorted({label_of(r, len(variants)) for r in rows}):
        runs = {r["seed"] for r in rows if label_of(r, len(variants)) == label}
        final = [
            max((r for r in rows if label_of(r, len(variants)) == label and r["seed"] == s), key=lambda r: int(r["env_steps"]))
            for s in runs
        ]
        for key in ("success_rate", "collision_rate", "out_of_road_rate", "episode_return"):
            v = [float(r[key]) for r in final]
            print(f"  {label:<16} {key:<17} {np.mean(v):.3f} ± {np.std(v):.3f}")
    print("\n" + table)
    print(f"wrote {csv_path}, {out / 'curves.png'} and {out / 'freeze_table.md'}")


def label_of(row: dict, num_variants: int) -> str:
    """The curve's label: the algorithm, plus the variant when several are compared."""
    return row["algo"] if num_variants == 1 else f"{row['algo']} {row['variant']}"


def read_rows(path: Path) -> list[dict]:
    """The evaluation rows already in ``curves.csv`` (none if it does not exist)."""
    if not path.exists():
        return []
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def append_rows(path: Path, rows: list[dict]) -> None:
    """Append one finished run's rows to ``curves.csv`` (header first if new), flushed to disk."""
    new = not path.exists()
    with open(path, "a", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=list(rows[0]))
        if new:
            writer.writeheader()
        writer.writerows(rows)
        f.flush()
        os.fsync(f.fileno())


def write_summary(rows: list[dict], out: Path, scenario: str, num_variants: int) -> str:
    """Rewrite ``curves.png`` and ``freeze_table.md`` from the finished runs; returns the table."""
    seeds = len({r["seed"] for r in rows})
    plot([r | {"algo": label_of(r, num_variants)} for r in rows], out / "curves.png", f"{scenario}: success vs env steps ({seeds} seeds)")
    table = freeze_table(rows)
    (out / "freeze_table.md").write_text(table)
    return table


if __name__ == "__main__":
    main()
