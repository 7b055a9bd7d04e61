"""Train the seed-2 policy pair at a stated budget and score it on the paper's 24-case arena suite.

Usage: python benchmarks/arena_pair.py [--minutes 40] [--steps 30000000] [--seed 0]
                                       [--scenarios-per-case 50] [--out runs/arena_pair] [--docs docs/arena]
                                       [--set key=value ...] [--resume]

Both stages train at once (``python -m coin_app train --algo nav_ppo --scenario arena
--set stage=long|short``), one process and one CPU thread each, until ``--steps`` env steps or
``--minutes`` of wall time, whichever comes first. Then each checkpoint is exported to ``.npz``,
the two are paired (``python -m coin_app pair``, switch radius 7.5 m) and the pair, and the
scripted heuristic for reference, run the 24-case suite (``python -m coin_app evaluate-arena``).
``--resume`` continues both stages from the checkpoints of an interrupted run in ``--out``
(``train --resume``; the logs are appended to). ``--docs`` receives the case table next to the
paper's Tables I and II, the settings and budget, and trajectory plots of test scenario 0 of a
few cases.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

PLOT_CASES = "1x4,4x4,10x8,20x8"


def run(cmd: list[str], log: Path | None = None, env: dict | None = None, append: bool = False) -> subprocess.Popen:
    """Start ``python -m coin_app ...`` with output to ``log`` (or inherited)."""
    out = open(log, "a" if append else "w") if log else None
    return subprocess.Popen([sys.executable, "-m", "coin_app", *cmd], stdout=out, stderr=subprocess.STDOUT if out else None, env=env)


def main() -> None:
    """Train both stages, export, pair, evaluate; write the docs."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=40.0, help="wall-time budget of each stage")
    ap.add_argument("--steps", type=int, default=30_000_000, help="env-step budget of each stage (paper: 30M long, 40M short)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scenarios-per-case", type=int, default=50)
    ap.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE", help="nav_ppo or arena overrides for both stages")
    ap.add_argument("--out", default="runs/arena_pair")
    ap.add_argument("--docs", default=None, help="copy the table, settings and plots here")
    ap.add_argument("--resume", action="store_true", help="continue both stages from their checkpoints in --out (a new --minutes budget)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    procs = {}
    for stage in ("long", "short"):
        cmd = ["train", "--algo", "nav_ppo", "--scenario", "arena", "--seed", str(args.seed), "--steps", str(args.steps)]
        cmd += ["--max-minutes", str(args.minutes), "--out", str(out / stage), "--set", f"stage={stage}", *args.set]
        if args.resume:
            if not (out / stage / "checkpoint" / "rllib_checkpoint.json").is_file():
                sys.exit(f"--resume: no checkpoint of stage {stage} in {out / stage / 'checkpoint'}")
            cmd += ["--resume", str(out / stage / "checkpoint")]
        procs[stage] = run(cmd, out / f"train_{stage}.log", env, append=args.resume)
        print(f"training {stage}: log {out / f'train_{stage}.log'}", flush=True)
    while any(p.poll() is None for p in procs.values()):
        time.sleep(60)
        for stage in procs:
            lines = [ln for ln in (out / f"train_{stage}.log").read_text().splitlines() if ln.startswith("iter")]
            if lines:
                print(f"  {stage}: {lines[-1]}", flush=True)
    if any(p.returncode for p in procs.values()):
        sys.exit(f"training failed: see {out}/train_*.log")
    summaries = {s: json.loads((out / s / "summary.json").read_text()) for s in procs}
    for stage in procs:
        if run(["export", str(out / stage / "checkpoint"), "--out", str(out / f"nav_{stage}.npz")]).wait():
            sys.exit(f"export of {stage} failed")
    if run(
        ["pair", str(out / "nav_long.npz"), str(out / "nav_short.npz"), "--switch-radius", "7.5", "--out", str(out / "nav.json")]
    ).wait():
        sys.exit("pair failed")
    for name, policy in (("pair", out / "nav.json"), ("heuristic", "heuristic")):
        cmd = [
            "evaluate-arena",
            str(policy),
            "--cases",
            "all",
            "--scenarios-per-case",
            str(args.scenarios_per_case),
            "--out",
            str(out / f"eval_{name}"),
        ]
        if run(cmd).wait():
            sys.exit(f"evaluation of {name} failed")
    if run(
        [
            "evaluate-arena",
            str(out / "nav.json"),
            "--cases",
            PLOT_CASES,
            "--scenarios-per-case",
            "1",
            "--workers",
            "1",
            "--plots",
            "1",
            "--out",
            str(out / "plots"),
        ]
    ).wait():
        sys.exit("plots failed")
    settings = vars(args) | {"training": summaries, "wall_s": round(time.perf_counter() - t0)}
    (out / "settings.json").write_text(json.dumps(settings, indent=2))
    print(f"\ntraining: long {summaries['long']['env_steps']} env steps, short {summaries['short']['env_steps']} env steps")
    print(f"tables: {out / 'eval_pair' / 'arena_table.md'} (pair), {out / 'eval_heuristic' / 'arena_table.md'} (heuristic)")
    if args.docs:
        docs = Path(args.docs)
        docs.mkdir(parents=True, exist_ok=True)
        for name in ("pair", "heuristic"):
            shutil.copy(out / f"eval_{name}" / "arena_table.md", docs / f"arena_table_{name}.md")
            shutil.copy(out / f"eval_{name}" / "arena_cases.csv", docs / f"arena_cases_{name}.csv")
        for png in sorted((out / "plots" / "plots").glob("*.png")):
            shutil.copy(png, docs / png.name)
        (docs / "settings.json").write_text(json.dumps(settings, indent=2, default=str))
        print(f"docs: {docs}")


if __name__ == "__main__":
    main()
