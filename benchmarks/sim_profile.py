"""Where one native env step's time goes: milliseconds per env step of each piece of ``DrivingSimulator.step``.

Usage: python benchmarks/sim_profile.py [--steps 400] [--scenarios intersection roundabout] [--policy forward|random]

Runs one native dict env (MetaDrive's car, the default dynamics) under the "forward" policy of
``env_throughput.py`` (steering U(-0.3, 0.3), throttle U(0.2, 1)), auto-resetting, and times each
piece by wrapping it: the car's substeps (``RaycastVehicles.step``), lane localisation, the
solid-line, sidewalk and crash tests, respawns and observations, plus the whole ``sim.step`` and
the dict env's ``step``. Times are CPU time of this process (``time.process_time``), so other
processes on the machine inflate them less than wall time; pin one core with ``taskset -c 0``.
"""

from __future__ import annotations

import argparse
import functools
import os
import time
from collections import defaultdict
from collections.abc import Callable

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


def profile(scenario: str, policy: str, steps: int, seed: int = 0) -> tuple[dict[str, float], float]:
    """(ms per env step of each piece, mean acting agents) over ``steps`` steps of one dict env."""
    totals: dict[str, float] = defaultdict(float)
    originals = {name: getattr(cls, attr) for name, (cls, attr) in PIECES.items()}
    for name, (cls, attr) in PIECES.items():
        setattr(cls, attr, _timed(totals, name, originals[name]))
    try:
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


def main() -> None:
    """Print the per-piece table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=400)
    ap.add_argument("--scenarios", nargs="+", default=["intersection", "roundabout"])
    ap.add_argument("--policy", default="forward", choices=["forward", "random"])
    args = ap.parse_args()
    if args.steps < 1:
        ap.error(f"--steps {args.steps}: allowed: an integer >= 1")
    names = [*PIECES, "dict env step"]
    print(f"ms per env step (CPU time), one native dict env, {args.policy} policy, {args.steps} steps")
    print(f"{'piece':<16}" + "".join(f"{sc:>14}" for sc in args.scenarios))
    results = [profile(sc, args.policy, args.steps) for sc in args.scenarios]
    for name in names:
        print(f"{name:<16}" + "".join(f"{r[0].get(name, 0.0):>14.3f}" for r in results))
    print(f"{'acting agents':<16}" + "".join(f"{r[1]:>14.1f}" for r in results))


if __name__ == "__main__":
    main()
