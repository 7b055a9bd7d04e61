"""Latency of the command line: ``--help`` and one-line refusals, each in a fresh interpreter (cold, as a user types it).

Usage: python benchmarks/cli_latency.py [--repeats 5] [--tree PATH]

Each case runs ``python -m coin_app ...`` ``--repeats`` times in a new process (after one untimed run
that writes the bytecode caches) and prints the median and worst wall time, the exit code and whether
the command imported Ray or torch (``-X importtime``). The issue's target: < 2 s for ``--help`` and
for every refusal that needs no model. ``--tree`` measures another checkout (e.g. a worktree of an
older commit) beside this one.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from pathlib import Path

# every case must end at once in an older checkout too (--tree runs it there): a refusal there, never a run
CASES = {
    "--help": ["--help"],
    "train --help": ["train", "--help"],
    "demo --help": ["demo", "--help"],
    "refusal: train --algo sac": ["train", "--algo", "sac"],
    "refusal: train --scenario highway": ["train", "--scenario", "highway"],
    "refusal: demo --steps 0": ["demo", "--steps", "0"],
    "refusal: demo --policy nope": ["demo", "--policy", "nope"],
    "refusal: sweep --scenario x": ["sweep", "seeds", "--scenario", "x"],
    "refusal: train --set tau=2": ["train", "--set", "tau=2"],
    "refusal: config --scale reduced tau=2": ["config", "--scale", "reduced", "--set", "tau=2"],
    "refusal: unknown command": ["fly"],
    "policies": ["policies"],
}
TARGET_S = 2.0


def run_case(argv: list[str], tree: Path) -> tuple[float, int, str]:
    """Wall time, exit code and the heavy packages imported by one cold ``python -m coin_app`` run."""
    cmd = [sys.executable, "-X", "importtime", "-m", "coin_app", *argv]
    t0 = time.perf_counter()
    out = subprocess.run(cmd, cwd=tree, capture_output=True, text=True)
    wall = time.perf_counter() - t0
    imported = {line.rsplit("|", 1)[-1].strip().split(".")[0] for line in out.stderr.splitlines() if line.startswith("import time:")}
    heavy = ",".join(sorted({"ray", "torch"} & imported)) or "-"
    return wall, out.returncode, heavy


def main() -> None:
    """Time every case; print one row each and a summary line with the slowest case."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5, help="timed runs per case (default 5)")
    ap.add_argument("--tree", default=str(Path(__file__).resolve().parents[1]), help="the checkout to run in (default: this one)")
    args = ap.parse_args()
    if args.repeats < 1:
        raise SystemExit(f"bad --repeats {args.repeats}; allowed: an integer >= 1")
    tree = Path(args.tree)
    print(f"cli_latency: {len(CASES)} cases x {args.repeats} cold runs in {tree} ({sys.executable})")
    print(f"{'case':<38} {'median s':>9} {'worst s':>8} {'exit':>5}  imports")
    worst_case, worst_s = "", 0.0
    for name, argv in CASES.items():
        run_case(argv, tree)  # bytecode caches written, not timed
        runs = [run_case(argv, tree) for _ in range(args.repeats)]
        walls = [w for w, _, _ in runs]
        print(f"{name:<38} {statistics.median(walls):>9.2f} {max(walls):>8.2f} {runs[0][1]:>5}  {runs[0][2]}", flush=True)
        if statistics.median(walls) > worst_s:
            worst_case, worst_s = name, statistics.median(walls)
    verdict = "meets" if worst_s < TARGET_S else "misses"
    print(f"\nsummary: slowest median {worst_s:.2f} s ({worst_case}); {verdict} the < {TARGET_S:g} s target")


if __name__ == "__main__":
    main()
