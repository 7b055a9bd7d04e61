"""Where one native env step's time goes: milliseconds per env step of each piece of ``DrivingSimulator.step``.

Usage: python benchmarks/sim_profile.py [--steps 400] [--scenarios intersection roundabout] [--policy forward|random]
       [--num-envs N] [--against REF]

Runs one native dict env (MetaDrive's car, the default dynamics) under the "forward" policy of
``env_throughput.py`` (steering U(-0.3, 0.3), throttle U(0.2, 1)), auto-resetting, and times each
piece by wrapping it: the car's substeps (``RaycastVehicles.step``), lane localisation, the
solid-line, sidewalk and crash tests, respawns and observations, plus the whole ``sim.step`` and
the dict env's ``step``. Times are CPU time of this process (``time.process_time``), so other
processes on the machine inflate them less than wall time; pin one core with ``taskset -c 0``.

``--against REF`` (e.g. the commit before the compiled kernels, ``515f91a``) puts the same table of the tree at git
commit ``REF`` beside this checkout's: ``REF`` is checked out into a temporary git worktree and profiled in a child
process importing ``coin_app`` from it, then this checkout in another child, one after the other (each piece
wrapped by the same names in both trees).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from coin_app.backends.factory import make_driving_env  # noqa: E402
from coin_app.sim.config import make_config  # noqa: E402
from coin_app.sim.simulator import DrivingSimulator  # noqa: E402
from coin_app.sim.vehicle import RaycastVehicles  # noqa: E402

PIECES = {
    "car substeps": (RaycastVehicles, "step"),
    "localisation": (DrivingSimulator, "_localize"),
    "solid lines": (DrivingSimulator, "_touches_solid_line"),
    "sidewalks": (DrivingSimulator, "_on_sidewalk"),
    "crashes": (DrivingSimulator, "_crashes"),
    "respawns": (DrivingSimulator, "_respawn"),
    "observations": (DrivingSimulator, "observe"),
    "sim.step (all)": (DrivingSimulator, "step"),
}


def _timed(totals: dict[str, float], name: str, fn: Callable) -> Callable:
    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        t0 = time.process_time()
        try:
            return fn(*args, **kwargs)
        finally:
            totals[name] += time.process_time() - t0

    return wrapper


def profile(scenario: str, policy: str, steps: int, seed: int = 0, num_envs: int = 0) -> tuple[dict[str, float], float]:
    """(ms per env step of each piece, mean acting agents) over ``steps`` steps of one dict env, or with ``num_envs`` > 0 of
    the vectorized core stepping that many envs at once (auto-resetting finished envs)."""
    totals: dict[str, float] = defaultdict(float)
    originals = {name: getattr(cls, attr) for name, (cls, attr) in PIECES.items()}
    for name, (cls, attr) in PIECES.items():
        setattr(cls, attr, _timed(totals, name, originals[name]))
    try:
        if num_envs:
            return _profile_core(totals, scenario, policy, steps, seed, num_envs)
        env = make_driving_env(make_config(scenario))
        rng = np.random.default_rng(seed)
        env.reset(seed)
        for _ in range(20):  # warm-up (compilation, caches), not counted
            n = len(env.agents)
            env.step(dict(zip(env.agents, np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(0.2, 1.0, n)], 1))))
            if env.episode_over:
                env.reset(seed + 1)
        totals.clear()
        acting = 0
        for k in range(steps):
            n = len(env.agents)
            if policy == "random":
                acts = rng.uniform(-1.0, 1.0, (n, 2))
            else:
                acts = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(0.2, 1.0, n)], 1)
            t0 = time.process_time()
            env.step(dict(zip(env.agents, acts)))
            totals["dict env step"] += time.process_time() - t0
            acting += n
            if env.episode_over:
                env.reset(seed + k + 1)
    finally:
        for name, (cls, attr) in PIECES.items():
            setattr(cls, attr, originals[name])
    return {name: 1000 * t / steps for name, t in totals.items()}, acting / steps


def _profile_core(
    totals: dict[str, float], scenario: str, policy: str, steps: int, seed: int, num_envs: int
) -> tuple[dict[str, float], float]:
    sim = DrivingSimulator(make_config(scenario), num_envs=num_envs)
    sim.reset(seed)
    rng = np.random.default_rng(seed)
    resets, acting = seed + num_envs, 0
    for k in range(steps + 20):
        if k == 20:  # warm-up (compilation, caches), not counted
            totals.clear()
            acting = 0
        if policy == "random":
            acts = rng.uniform(-1.0, 1.0, (sim.num_slots, 2))
        else:
            acts = np.stack([rng.uniform(-0.3, 0.3, sim.num_slots), rng.uniform(0.2, 1.0, sim.num_slots)], 1)
        res = sim.step(acts)
        acting += int(res.acted.sum())
        over = np.nonzero(res.episode_over)[0]
        if len(over):
            t0 = time.process_time()
            sim.reset_envs(over, list(range(resets, resets + len(over))))
            totals["resets"] += time.process_time() - t0
            resets += len(over)
    return {name: 1000 * t / steps for name, t in totals.items()}, acting / steps


def _child_results(tree: Path, args: argparse.Namespace) -> list:
    """The per-scenario results of ``profile`` for the ``coin_app`` of ``tree``, from a child process."""
    env = os.environ | {"PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    cmd = [sys.executable, str(Path(__file__).resolve()), "--json", "--steps", str(args.steps), "--policy", args.policy]
    cmd += ["--num-envs", str(args.num_envs), "--scenarios", *args.scenarios]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        raise SystemExit(f"--against: the child for {tree} failed:\n{out.stderr}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    """Print the per-piece table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--scenarios", nargs="+", default=["intersection", "roundabout"])
    ap.add_argument("--policy", default="forward", choices=["forward", "random"])
    ap.add_argument("--num-envs", type=int, default=0, help="profile the vectorized core with this many envs (0: one dict env)")
    ap.add_argument("--against", metavar="REF", help="also profile git commit REF's tree, side by side (see module doc)")
    ap.add_argument("--json", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.steps < 1 or args.num_envs < 0:
        ap.error(f"--steps {args.steps} --num-envs {args.num_envs}: allowed: --steps >= 1, --num-envs >= 0")
    if args.json:
        print(json.dumps([profile(sc, args.policy, args.steps, num_envs=args.num_envs) for sc in args.scenarios]))
        return
    names = [*PIECES, "resets" if args.num_envs else "dict env step"]
    what = f"the vectorized core with {args.num_envs} envs" if args.num_envs else "one native dict env"
    print(f"ms per env step (CPU time), {what}, {args.policy} policy, {args.steps} steps")
    root = Path(__file__).resolve().parents[1]
    if not args.against:
        columns = {"": [profile(sc, args.policy, args.steps, num_envs=args.num_envs) for sc in args.scenarios]}
    else:
        sha = subprocess.run(
            ["git", "-C", str(root), "rev-parse", "--verify", f"{args.against}^{{commit}}"], capture_output=True, text=True
        )
        if sha.returncode != 0:
            ap.error(f"--against {args.against!r} is not a commit of {root}; allowed: a git revision (a sha, branch or tag)")
        with tempfile.TemporaryDirectory() as tmp:
            old = Path(tmp) / "ref"
            subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", "--quiet", str(old), sha.stdout.strip()], check=True)
            try:
                columns = {f" {args.against}": _child_results(old, args), " this": _child_results(root, args)}
            finally:
                subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(old)], check=False)
    print(f"{'piece':<16}" + "".join(f"{sc + tag:>{max(14, len(sc + tag) + 2)}}" for sc in args.scenarios for tag in columns))
    cells = [(len(sc + tag), columns[tag][k]) for k, sc in enumerate(args.scenarios) for tag in columns]
    for name in names:
        print(f"{name:<16}" + "".join(f"{r[0].get(name, 0.0):>{max(14, w + 2)}.3f}" for w, r in cells))
    print(f"{'acting agents':<16}" + "".join(f"{r[1]:>{max(14, w + 2)}.1f}" for w, r in cells))


if __name__ == "__main__":
    main()
