"""Agent-steps per second of the native simulator (and of MetaDrive side by side), per scenario, on one core.

Usage: python benchmarks/env_throughput.py [--steps 300] [--num-envs 1 16] [--scaling] [--no-compile-cost]
       python benchmarks/env_throughput.py --backend metadrive|both [--steps 300] [--scenarios ...]
       python benchmarks/env_throughput.py --against REF [--repeats 5] [--steps 300] [--scenarios ...]

Runs each scenario at its default agent count with uniform random actions and with the
heuristic driver's traffic, for a single env and for a batch of envs stepped together (the
vectorized core), auto-resetting finished envs. Agent-steps/s counts env time only (the
policy's time is printed apart). ``--scaling`` adds the step time from 10 to 48 agents
(48 = the maps' spawn capacity, as in MetaDrive). Pin one core with ``taskset -c 0``.

``--backend metadrive`` times MetaDrive 0.4.3 (optional extra) through coin_app's dict env;
``--backend both`` runs the native dict env (with MetaDrive's car, the default, and with the
fitted bicycle) in this process and MetaDrive in a child process (one engine per process), one
after the other so they never share a core, with the same agent count, seeds and policies
("random": uniform actions; "forward": steering U(-0.3, 0.3), throttle U(0.2, 1), dense crashes
and respawns), and prints the ratio native (MetaDrive's car) / MetaDrive. ``--model bicycle``
times the vectorized core with the fitted bicycle instead of MetaDrive's car.
The native vectorized core (``--num-envs``) is faster still; its table is printed first
unless the backend is metadrive.

The arena (the shipped pair's observation: six entities and the candidate features, 20 vehicles among
8 obstacles, the planning driver or random actions) is timed in the same table: its env time per step
and, apart, the candidate features' share of it (``ArenaSimulator.feature_time``).

The simulator's kernels are compiled by Numba and cached on disk (``cache=True``); the first lines printed
are the compile cost: a fresh process importing the simulator and taking one driving step and one arena
step, with an empty cache (the first run after a checkout or a change: everything compiles) and again with
that cache filled (every later run), run in child processes with their own ``NUMBA_CACHE_DIR`` so that the
measurement leaves the real cache alone. ``--no-compile-cost`` skips it.

``--against REF`` compares this checkout's native dict env with the same env at a git commit
(old against new): ``REF`` is checked out into a temporary git worktree, and each measurement runs
in a fresh child process that imports ``coin_app`` from one tree or the other, the two trees
alternating ``--repeats`` times per (scenario, policy) so that both see the same machine load. It
prints each side's median agent-steps/s, the ratio this / REF, and whether the two trees gave the
same observations, rewards and terminations over the measured steps (a digest of every step).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from coin_app.sim.config import DEFAULT_NUM_AGENTS, make_config  # noqa: E402
from coin_app.sim.heuristic import HeuristicDriver  # noqa: E402
from coin_app.sim.simulator import DrivingSimulator  # noqa: E402


def measure(
    scenario: str, num_agents: int, num_envs: int, policy: str, steps: int, seed: int = 0, model: str = "raycast"
) -> tuple[float, float, float, float]:
    """(env agent-steps/s, env ms per batched step, policy ms per step, env agent-steps per CPU second) over ``steps`` steps.

    Only ``sim.step`` (and the auto-resets) count as env time; computing the actions is
    timed apart, so the heuristic rows measure the simulator under the heuristic's traffic.
    The CPU-time rate (this process's ``time.process_time``) is what other work on the machine inflates least.
    """
    sim = DrivingSimulator(make_config(scenario, num_agents=num_agents, dynamics={"model": model}), num_envs=num_envs)
    sim.reset(seed)
    rng = np.random.default_rng(seed)
    driver = HeuristicDriver(sim) if policy == "heuristic" else None
    agent_steps = 0
    resets = seed + num_envs
    env_time = policy_time = cpu_time = 0.0
    for _ in range(steps):
        t0 = time.perf_counter()
        if driver is not None:
            actions = driver.act_all()
        elif policy == "forward":
            actions = np.stack([rng.uniform(-0.3, 0.3, sim.num_slots), rng.uniform(0.2, 1.0, sim.num_slots)], 1)
        else:
            actions = rng.uniform(-1.0, 1.0, (sim.num_slots, 2))
        t1, c1 = time.perf_counter(), time.process_time()
        res = sim.step(actions)
        agent_steps += int(res.acted.sum())
        over = np.nonzero(res.episode_over)[0]
        if len(over):
            sim.reset_envs(over, list(range(resets, resets + len(over))))
            resets += len(over)
        t2 = time.perf_counter()
        cpu_time += time.process_time() - c1
        env_time += t2 - t1
        policy_time += t1 - t0
    return agent_steps / env_time, 1000 * env_time / steps, 1000 * policy_time / steps, agent_steps / cpu_time


def measure_dict_env(
    scenario: str, backend: str, policy: str, steps: int, seed: int = 0, digest: hashlib._Hash | None = None
) -> tuple[float, float, float]:
    """(agent-steps/s, mean acting agents, agent-steps per CPU second of this process) of one env of ``backend`` through
    the dict API, auto-resetting.

    ``backend``: ``metadrive``, ``native`` (its default vehicle, MetaDrive's car) or ``native-bicycle``.
    With ``digest``, every step's observations, rewards and terminations are fed to it (outside the timed time).
    """
    from coin_app.backends.factory import make_driving_env

    extra = {"dynamics": {"model": "bicycle"}} if backend == "native-bicycle" else {"backend": backend}
    env = make_driving_env(make_config(scenario, **extra))
    rng = np.random.default_rng(seed)
    agent_steps = 0
    hashing = cpu_hashing = 0.0
    try:
        env.reset(seed)
        t0, c0 = time.perf_counter(), time.process_time()
        for k in range(steps):
            n = len(env.agents)
            if policy == "random":
                acts = rng.uniform(-1.0, 1.0, (n, 2))
            else:
                acts = np.stack([rng.uniform(-0.3, 0.3, n), rng.uniform(0.2, 1.0, n)], 1)
            out = env.step(dict(zip(env.agents, acts)))
            agent_steps += n
            if digest is not None:
                t_hash, c_hash = time.perf_counter(), time.process_time()
                _feed(digest, out)
                hashing += time.perf_counter() - t_hash
                cpu_hashing += time.process_time() - c_hash
            if env.episode_over:
                env.reset(seed + k + 1)
        elapsed = time.perf_counter() - t0 - hashing
        cpu = time.process_time() - c0 - cpu_hashing
    finally:
        env.close()
    return agent_steps / elapsed, agent_steps / steps, agent_steps / cpu


def _feed(digest: hashlib._Hash, step_out: tuple) -> None:
    """Feed a dict-env step's observations, rewards and terminations (each dict's agents in sorted order) to ``digest``."""
    obs, rewards, terminated = step_out[0], step_out[1], step_out[2]
    for agent in sorted(obs):  # a vehicle spawned in this step has an observation and no reward yet
        digest.update(agent.encode())
        digest.update(np.ascontiguousarray(obs[agent], dtype=np.float64).tobytes())
    for agent in sorted(rewards):
        digest.update(agent.encode())
        digest.update(np.float64(rewards[agent]).tobytes())
        digest.update(bytes([bool(terminated.get(agent, False))]))


def _child(scenario: str, policy: str, steps: int) -> None:
    """Print one native measurement of the ``coin_app`` on ``sys.path`` as a JSON line (``--against``'s child)."""
    digest = hashlib.sha256()
    rate, live, _ = measure_dict_env(scenario, "native", policy, steps, digest=digest)
    print(json.dumps({"rate": rate, "live": live, "digest": digest.hexdigest()}))


def against(ref: str, scenarios: list[str], steps: int, repeats: int) -> None:
    """Print this checkout's native dict env against the same env at git commit ``ref`` (see module doc)."""
    root = Path(__file__).resolve().parents[1]
    sha = subprocess.run(["git", "-C", str(root), "rev-parse", "--verify", f"{ref}^{{commit}}"], capture_output=True, text=True)
    if sha.returncode != 0:
        raise SystemExit(f"--against: {ref!r} is not a commit of {root}; allowed: a git revision (a sha, branch or tag)")
    with tempfile.TemporaryDirectory() as tmp:
        old = Path(tmp) / "ref"
        subprocess.run(["git", "-C", str(root), "worktree", "add", "--detach", "--quiet", str(old), sha.stdout.strip()], check=True)
        try:
            head = f"native dict env, this checkout against {ref} ({sha.stdout.strip()[:10]})"
            print(f"{head}: {steps} steps per run, {repeats} runs each, alternating")
            print(f"{'scenario':<13}{'agents':>7}{'policy':>9}{'this steps/s':>15}{'ref steps/s':>15}{'ratio':>8}  same results")
            for sc in scenarios:
                for pol in ("random", "forward"):
                    runs: dict[Path, list[dict]] = {root: [], old: []}
                    for _ in range(repeats):
                        for tree in (root, old):
                            env = os.environ | {"PYTHONPATH": str(tree), "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
                            cmd = [sys.executable, str(Path(__file__).resolve()), "--child", sc, pol, str(steps)]
                            out = subprocess.run(cmd, env=env, capture_output=True, text=True)
                            if out.returncode != 0:
                                raise SystemExit(f"--against: the child for {tree} failed:\n{out.stderr}")
                            runs[tree].append(json.loads(out.stdout.strip().splitlines()[-1]))
                    this, base = (statistics.median(r["rate"] for r in runs[t]) for t in (root, old))
                    same = len({r["digest"] for r in runs[root] + runs[old]}) == 1
                    cells = f"{this:>15,.0f}{base:>15,.0f}{this / base:>7.2f}x  {'yes' if same else 'NO'}"
                    print(f"{sc:<13}{DEFAULT_NUM_AGENTS[sc]:>7}{pol:>9}{cells}", flush=True)
        finally:
            subprocess.run(["git", "-C", str(root), "worktree", "remove", "--force", str(old)], check=False)


def _metadrive_child(job: tuple[str, str, int]) -> tuple[float, float, float]:
    scenario, policy, steps = job
    return measure_dict_env(scenario, "metadrive", policy, steps)


def side_by_side(scenarios: list[str], steps: int, backends: tuple[str, ...]) -> None:
    """Print agent-steps/s of the native and MetaDrive dict envs and their ratio (of wall time, and of CPU time)."""
    import multiprocessing as mp

    head = "".join(f"{b + ' steps/s':>20}{'live':>6}" for b in backends)
    print(f"\n{'scenario':<13}{'agents':>7}{'policy':>9}{head}   ratio (of CPU time)")
    for sc in scenarios:
        for pol in ("random", "forward"):
            row = {}
            for b in backends:
                if b == "metadrive":  # one MetaDrive engine per process: measure it in a child
                    with mp.get_context("spawn").Pool(1) as pool:
                        row[b] = pool.apply(_metadrive_child, ((sc, pol, steps),))
                else:
                    row[b] = measure_dict_env(sc, b, pol, steps)
            cells = "".join(f"{row[b][0]:>20,.0f}{row[b][1]:>6.1f}" for b in backends)
            ratio = ""
            if {"native", "metadrive"} <= set(row):
                ratio = f"{row['native'][0] / row['metadrive'][0]:7.1f}x ({row['native'][2] / row['metadrive'][2]:.1f}x)"
            print(f"{sc:<13}{DEFAULT_NUM_AGENTS[sc]:>7}{pol:>9}{cells}   {ratio}", flush=True)


ARENA_VEHICLES, ARENA_OBSTACLES = 20, 8


def measure_arena(policy: str, steps: int, seed: int = 0) -> tuple[float, float, float, float, float]:
    """(agent-steps/s, env ms per step, candidate-feature ms per step, agent-steps per CPU second, candidate-feature CPU ms per
    step) of one arena env with the shipped pair's observation.

    20 vehicles among 8 obstacles (new scenario when every vehicle is done); ``policy``: ``planning`` (the planning
    driver, timed apart) or ``random``. The feature time is part of the env time.
    """
    import coin_app.sim.arena.simulator as arena_sim
    from coin_app.sim.arena.config import make_arena_config
    from coin_app.sim.arena.env import ArenaEnv
    from coin_app.sim.arena.generator import generate, training_rng
    from coin_app.sim.arena.heuristic import planning_actions

    cfg = make_arena_config(observed_entities=6, candidate_features=True)
    env = ArenaEnv(cfg)
    rng = np.random.default_rng(seed)
    episode = 0

    def new_layout() -> dict:
        nonlocal episode
        episode += 1
        return {"layout": generate(training_rng(seed + episode), cfg, ARENA_VEHICLES, ARENA_OBSTACLES)}

    obs, _ = env.reset(options=new_layout())
    agent_steps, env_time, feature_time, cpu_time = 0, 0.0, 0.0, 0.0
    feature_cpu = [0.0]
    features = arena_sim.candidate_features

    def timed_features(*args: object, **kwargs: object) -> np.ndarray:
        c0 = time.process_time()
        try:
            return features(*args, **kwargs)
        finally:
            feature_cpu[0] += time.process_time() - c0

    arena_sim.candidate_features = timed_features  # the simulator's call, timed in CPU time too
    for _ in range(steps):
        rows = np.stack([obs[a] for a in env.agents])
        acts = planning_actions(rows) if policy == "planning" else rng.uniform(-1.0, 1.0, (len(rows), 2))
        t0, c0 = time.perf_counter(), time.process_time()
        obs = env.step(dict(zip(env.agents, acts)))[0]
        if env.episode_over:
            obs, _ = env.reset(options=new_layout())
        env_time += time.perf_counter() - t0
        cpu_time += time.process_time() - c0
        feature_time += env.sim.feature_time
        agent_steps += len(rows)
    arena_sim.candidate_features = features
    rates = agent_steps / env_time, agent_steps / cpu_time
    return rates[0], 1000 * env_time / steps, 1000 * feature_time / steps, rates[1], 1000 * feature_cpu[0] / steps


_COLD_START = """
import json, time
t0, c0 = time.perf_counter(), time.process_time()
import numpy as np
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.config import make_config
from coin_app.sim.simulator import DrivingSimulator
t1, c1 = time.perf_counter(), time.process_time()
sim = DrivingSimulator(make_config("intersection"))
sim.reset(0)
sim.step(np.zeros((sim.num_slots, 2)))
env = ArenaEnv(make_arena_config(observed_entities=6, candidate_features=True, num_vehicles=20, num_obstacles=8))
obs, _ = env.reset(seed=0)
env.step({a: np.zeros(2) for a in env.agents})
t2, c2 = time.perf_counter(), time.process_time()
print(json.dumps({"import": t1 - t0, "first_steps": t2 - t1, "import_cpu": c1 - c0, "first_steps_cpu": c2 - c1}))
"""


def warm_up() -> None:
    """Load (or compile) every kernel in this process before anything is timed: a few steps of each simulator."""
    for model in ("raycast", "bicycle"):
        measure("intersection", 10, 2, "random", 5, model=model)
        measure_dict_env("intersection", "native" if model == "raycast" else "native-bicycle", "random", 5)
    measure_arena("planning", 3)


def compile_cost() -> None:
    """Print the cold (empty Numba cache: compile) and warm (cache filled) start of a fresh process (see module doc)."""
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as cache:
        env = os.environ | {"NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(root)}
        runs = []
        for _ in range(2):
            out = subprocess.run([sys.executable, "-c", _COLD_START], env=env, capture_output=True, text=True)
            if out.returncode != 0:
                raise SystemExit(f"the compile-cost child failed:\n{out.stderr}")
            runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    (cold, warm) = runs
    print("compile cost (a fresh process: import the simulator, one driving step and one arena step with the features):")
    for name, run in (("empty Numba cache (first run, compiles)", cold), ("cache filled (every later run)", warm)):
        wall = f"import {run['import']:.2f} s + first steps {run['first_steps']:.2f} s"
        print(f"  {name:<40} {wall} (CPU time {run['import_cpu']:.2f} s + {run['first_steps_cpu']:.2f} s)")


def main() -> None:
    """Print the throughput table."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300)
    ap.add_argument("--num-envs", type=int, nargs="+", default=[1, 16])
    ap.add_argument("--scenarios", nargs="+", default=list(DEFAULT_NUM_AGENTS))
    ap.add_argument("--scaling", action="store_true", help="also time one env from 10 to 48 agents")
    ap.add_argument("--backend", default="native", choices=["native", "metadrive", "both"], help="metadrive needs the optional extra")
    ap.add_argument("--model", default="raycast", choices=["raycast", "bicycle"], help="the native vehicle model of the core's table")
    ap.add_argument("--against", metavar="REF", help="compare this checkout's native dict env with git commit REF's (old vs new)")
    ap.add_argument("--repeats", type=int, default=5, help="--against: runs per tree and (scenario, policy), alternating")
    ap.add_argument("--child", nargs=3, metavar=("SCENARIO", "POLICY", "STEPS"), help=argparse.SUPPRESS)
    ap.add_argument("--no-compile-cost", action="store_true", help="skip the compile-cost lines (two child processes)")
    args = ap.parse_args()
    for name in ("steps", "repeats"):
        if getattr(args, name) < 1:
            ap.error(f"--{name} {getattr(args, name)}: allowed: an integer >= 1")
    bad = [s for s in args.scenarios if s not in DEFAULT_NUM_AGENTS]
    if bad:
        ap.error(f"--scenarios {' '.join(bad)}: allowed: {', '.join(DEFAULT_NUM_AGENTS)}")
    if args.child:
        _child(args.child[0], args.child[1], int(args.child[2]))
        return
    if args.against:
        against(args.against, args.scenarios, args.steps, args.repeats)
        return
    if not args.no_compile_cost:
        compile_cost()
    if args.backend != "metadrive":
        warm_up()
    if args.backend != "native":
        backends = ("native", "native-bicycle", "metadrive") if args.backend == "both" else ("metadrive",)
        print(f"dict-API env, one env per backend, {args.steps} steps per row ('live' = mean acting agents):")
        side_by_side(args.scenarios, args.steps, backends)
        if args.backend == "metadrive":
            return
        print("\nnative vectorized core:")
    print(f"vehicle model: {args.model}")
    head = f"{'agent-steps/s':>15}{'env ms/step':>13}{'policy ms':>11}{'per CPU s':>11}"
    print(f"{'scenario':<13}{'agents':>7}{'envs':>6}{'policy':>11}{head}")
    for sc in args.scenarios:
        for ne in args.num_envs:
            for pol in ("random", "forward", "heuristic"):
                rate, ms, pms, cpu = measure(sc, DEFAULT_NUM_AGENTS[sc], ne, pol, args.steps, model=args.model)
                cells = f"{rate:>15,.0f}{ms:>13.2f}{pms:>11.2f}{cpu:>11,.0f}"
                print(f"{sc:<13}{DEFAULT_NUM_AGENTS[sc]:>7}{ne:>6}{pol:>11}{cells}", flush=True)
    for pol in ("random", "planning"):
        rate, ms, fms, cpu, fcpu = measure_arena(pol, args.steps)
        cells = f"{rate:>15,.0f}{ms:>13.2f}{'':>11}{cpu:>11,.0f}   (candidate features {fms:.2f} ms/step, CPU {fcpu:.2f} ms)"
        print(f"{'arena':<13}{ARENA_VEHICLES:>7}{1:>6}{pol:>11}{cells}", flush=True)
    if args.scaling:
        print("\nenv step time vs agent count (heuristic traffic, intersection, one env and a batch of 32):")
        for n in (10, 20, 30, 40, 48):
            rate1, ms1, _, _ = measure("intersection", n, 1, "heuristic", args.steps)
            rate32, ms32, _, _ = measure("intersection", n, 32, "heuristic", args.steps)
            print(
                f"  {n:>3} agents: 1 env {ms1:6.2f} ms/step ({rate1:>7,.0f} agent-steps/s)   32 envs {ms32:6.2f} ms/step ({rate32:>7,.0f})",
                flush=True,
            )


if __name__ == "__main__":
    main()
