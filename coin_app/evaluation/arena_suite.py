"""The seed-2 paper's evaluation suite: 24 (vehicles, obstacles) cases of fixed arena test scenarios (Tables I, II).

Test scenario ``k`` of case (n, m) is ``generate(heldout_rng(n, m, k))`` with the A-GNN test
settings (obstacles on the left of the paths, ``generator.py``): fixed forever and never
drawn in training. Every vehicle acts at once, one batch per step, deterministically, for up
to ``max_steps`` (400 = 40 s, the A-GNN evaluation's horizon). Per case:

* **success-to-goal rate**: vehicles that reached their target state (1.25 m, 0.2 rad,
  < 0.05 m/s) without any collision before, over all vehicles of the case;
* **collision rate**: collision events over metres driven, summed over the case (Table I);
* **step time**: the mean wall time of the policy call that computes every vehicle's action
  of a step in one batch, on one CPU thread (Table II).

Two success protocols (``protocol``):

* ``"arena"`` (the seed paper's, the default): the arena's success test above; a vehicle that
  passes it parks, and the run ends when every vehicle has parked or at the step limit;
* ``"agnn"`` (the A-GNN paper's own, Ma et al. 2023): no vehicle parks (the in-run test is off),
  the run stops early once every vehicle has moved less than 0.05 m and turned less than 0.1 rad
  in total over the last 10 states, and success is judged on the final state only: within
  1.25 m and 0.2 rad of the target, no speed test, and no collision at any step.

The A-GNN baseline (``"agnn"``, ``coin_app/inference/agnn.py``) reads the world state instead
of the observations and runs in its own simulator's physics (dt 0.2 s, position-first order);
its step limit keeps the same simulated time (400 steps of 0.1 s = 200 steps of 0.2 s = 40 s).

Cases run in worker processes (one CPU thread each); each loads the policy from its source.
"""

from __future__ import annotations

import multiprocessing as mp
import os
import time
from collections import deque
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from coin_app.algorithms.checkpoint_files import read_metadata
from coin_app.evaluation.limits import MAX_CASE_OBSTACLES, MAX_CASE_VEHICLES
from coin_app.evaluation.policies import as_policy
from coin_app.inference.agnn import AgnnArenaPolicy
from coin_app.inference.shipped import resolve
from coin_app.inference.switching import load_pair, observation_options
from coin_app.sim.arena.config import PROTOCOLS, ArenaConfig, make_arena_config
from coin_app.sim.arena.env import ArenaEnv, arena_metrics
from coin_app.sim.arena.generator import PAPER_CASES, generate, heldout_rng
from coin_app.sim.arena.heuristic import DRIVERS
from coin_app.sim.arena.rendering import ArenaTrace, plot_arena_episode
from coin_app.sim.arena.replay import write_arena_replay
from coin_app.sim.dynamics import wrap_angle

# the A-GNN protocol's early stop (Ma et al. 2023): every vehicle moved < 0.05 m and turned < 0.1 rad in total over the last 10 states
STILL_STATES, STILL_DISTANCE, STILL_ANGLE = 10, 0.05, 0.1

# Table I: (our agent success, A-GNN success, our agent collision rate, A-GNN collision rate); None where the paper has "-"
PAPER_TABLE_I: dict[tuple[int, int], tuple[float, float, float | None, float | None]] = {
    (1, 0): (0.93822, 0.9963, None, None),
    (1, 4): (0.8943, 0.6829, 1.07e-3, 6.74e-4),
    (1, 8): (0.8223, 0.8114, 3.83e-3, 4.69e-4),
    (1, 12): (0.7657, 0.792, 6.87e-3, 7.73e-4),
    (2, 0): (0.9121, 0.9974, 2.69e-4, 0.0),
    (2, 4): (0.9226, 0.6384, 2.46e-3, 3.62e-4),
    (2, 8): (0.9221, 0.3832, 2.10e-3, 9.86e-4),
    (2, 12): (0.8895, 0.2768, 4.06e-3, 1.60e-3),
    (4, 0): (0.9084, 0.9905, 5.68e-4, 5.09e-5),
    (4, 4): (0.8839, 0.8564, 2.18e-3, 8.42e-4),
    (4, 8): (0.8896, 0.7052, 1.77e-3, 1.91e-3),
    (4, 12): (0.8789, 0.5871, 2.61e-3, 3.35e-3),
    (6, 0): (0.8824, 0.9665, 9.78e-4, 3.60e-4),
    (6, 4): (0.8760, 0.8689, 1.12e-3, 1.38e-3),
    (6, 8): (0.867, 0.7654, 1.64e-3, 2.77e-3),
    (10, 0): (0.85, 0.852, 1.02e-3, 1.91e-3),
    (10, 4): (0.842, 0.7724, 1.31e-3, 3.04e-3),
    (10, 8): (0.8399, 0.6978, 1.52e-3, 4.33e-3),
    (15, 0): (0.839, 0.6029, 8.29e-4, 5.12e-3),
    (15, 4): (0.8356, 0.5231, 9.88e-4, 6.42e-3),
    (15, 8): (0.7711, 0.4689, 3.05e-3, 7.54e-3),
    (20, 0): (0.8297, 0.3161, 8.10e-4, 9.99e-3),
    (20, 4): (0.7925, 0.2563, 1.74e-3, 1.15e-2),
    (20, 8): (0.7567, 0.2153, 2.83e-3, 1.29e-2),
}
# the A-GNN paper's own success-to-goal rates (its supplementary Table II, its test sets of 4062 scenarios per case)
AGNN_SUPP_TABLE_II: dict[tuple[int, int], float] = {
    (1, 0): 1.0,
    (1, 4): 0.7361,
    (2, 0): 0.9984,
    (2, 4): 0.6781,
    (4, 0): 0.9807,
    (6, 0): 0.9209,
}
# Table II: seconds per step (our agent, A-GNN), Ryzen 7 7800X3D, batched on one CPU
PAPER_TABLE_II: dict[tuple[int, int], tuple[float, float]] = {
    (1, 0): (1.69e-4, 1.93e-3),
    (1, 8): (2.12e-4, 2.61e-3),
    (2, 0): (2.20e-4, 2.41e-3),
    (2, 8): (2.17e-4, 2.80e-3),
    (4, 0): (2.20e-4, 2.71e-3),
    (4, 8): (2.20e-4, 3.19e-3),
    (6, 0): (2.33e-4, 2.99e-3),
    (6, 8): (2.27e-4, 3.74e-3),
    (10, 0): (2.37e-4, 3.83e-3),
    (10, 8): (2.37e-4, 4.82e-3),
    (15, 0): (2.52e-4, 5.09e-3),
    (15, 8): (2.47e-4, 6.31e-3),
    (20, 0): (2.47e-4, 6.50e-3),
    (20, 8): (2.54e-4, 7.67e-3),
}


def parse_cases(spec: str) -> list[tuple[int, int]]:
    """``"all"`` (the paper's 24) or a comma list of ``VEHICLESxOBSTACLES`` such as ``"4x3,20x8"``."""
    if spec == "all":
        return list(PAPER_CASES)
    cases = []
    for part in spec.split(","):
        try:
            n, m = (int(x) for x in part.lower().split("x"))
        except ValueError:
            raise ValueError(f"bad case {part!r}; allowed: 'all' or VEHICLESxOBSTACLES like 4x3, comma separated") from None
        if not (1 <= n <= MAX_CASE_VEHICLES and 0 <= m <= MAX_CASE_OBSTACLES):
            raise ValueError(
                f"bad case {part!r}; allowed: 1 to {MAX_CASE_VEHICLES} vehicles and 0 to {MAX_CASE_OBSTACLES} obstacles (the paper's "
                "largest case: 20x8)"
            )
        cases.append((n, m))
    return cases


def suite_config(
    max_steps: int = 400, physics: dict[str, Any] | None = None, protocol: str = "arena", generator: str = "agnn"
) -> ArenaConfig:
    """The arena settings of the test suite (the A-GNN test generator: obstacles on the left).

    ``generator="short"`` draws the parking stage's starts instead (1–7.5 m from the target, any
    heading; not the paper's suite): the same held-out seeds, to score a short-range policy alone.

    ``max_steps`` counts steps of the arena's 0.1 s; ``physics`` (a policy's own ``dt`` and
    ``update_order``, and its ``observed_entities``) keeps the same simulated time. The ``"agnn"`` protocol switches the in-run
    success test off (a speed tolerance of 0 m/s: no vehicle ever parks, as in the A-GNN simulator).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"bad protocol {protocol!r}; allowed: {', '.join(PROTOCOLS)}")
    overrides = dict(physics or {})
    if "dt" in overrides and isinstance(max_steps, int) and max_steps >= 1:
        max_steps = max(1, round(max_steps * ArenaConfig().dt / overrides["dt"]))
    if protocol == "agnn":
        overrides["success_speed"] = 0.0
    return make_arena_config(generator=generator, obstacle_side="left", max_steps=max_steps, **overrides)


def load_arena_policy(source: str | Path) -> Any:
    """A scripted driver's name (``DRIVERS``), ``"agnn"`` (the A-GNN baseline) or any policy source of ``as_policy``.

    Learned policies carry their training metadata (``meta``: scenario, env config), so that the
    suite observes as many entities as each was trained on (``observed_entities``).
    """
    if str(source) in DRIVERS:
        return DRIVERS[str(source)]
    if str(source) == "agnn":
        return AgnnArenaPolicy()
    path = Path(resolve(source))  # a shipped policy's name: its file
    if path.is_file() and path.suffix == ".json":
        return load_pair(path, load_arena_policy)
    if path.is_dir():
        return WithMeta(as_policy(path), read_metadata(path))
    return as_policy(source)


class WithMeta:
    """A policy with the metadata of the checkpoint it came from (``meta``), calls passed through."""

    def __init__(self, policy: Callable[[np.ndarray], np.ndarray], meta: dict[str, Any]):
        self.policy, self.meta = policy, dict(meta)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """The wrapped policy's actions for ``obs``."""
        return self.policy(obs)


def policy_config(policy: Any, max_steps: int, protocol: str, generator: str = "agnn", observed: int | None = None) -> ArenaConfig:
    """The suite's arena settings for ``policy``: in its own physics where it names one (the A-GNN), and observing as many
    entities as it was trained on, or ``observed`` (scripted drivers; refused if it contradicts a learned policy's own),
    with the candidate features where it was trained with them."""
    options = observation_options(policy)  # None for a scripted driver
    own = None if options is None else options["observed_entities"]
    if observed is not None and own is not None and observed != own:
        raise ValueError(f"observed entities {observed} contradict the policy's own {own}; allowed: {own} (or leave it unset)")
    overrides = dict(getattr(policy, "arena_overrides", None) or {})
    k = observed if observed is not None else own
    if k is not None and k != 1:
        overrides["observed_entities"] = k
    if options is not None and options["candidate_features"]:
        overrides["candidate_features"] = True  # the planning filter's candidate clearances, as the policy was trained
    return suite_config(max_steps, overrides, protocol, generator)


def final_state_success(sim: Any) -> tuple[np.ndarray, np.ndarray]:
    """The A-GNN protocol's test (N,) of the final state: (within the distance and angle tolerances, that and never collided)."""
    cfg = sim.config
    reached = (sim.target_distance() <= cfg.success_distance) & (sim.heading_error() <= cfg.success_angle)
    return reached, reached & ~sim.collided


def run_scenario(policy: Any, env: ArenaEnv, layout: Any, trace: Any = None, protocol: str = "arena") -> dict[str, float]:
    """One deterministic episode on ``layout``: the paper's metrics and the mean policy time per step (``trace`` records it).

    ``policy`` maps the observations (N, 13) of the driving vehicles to their actions, or has
    ``from_sim(sim)``: the actions of every vehicle from the world state (the A-GNN). With the
    candidate features in the observation, the time the simulator spent computing them counts
    as the policy's (they are its inputs, computed for it).
    """
    if protocol not in PROTOCOLS:
        raise ValueError(f"bad protocol {protocol!r}; allowed: {', '.join(PROTOCOLS)}")
    obs, _ = env.reset(options={"layout": layout})
    sim = env.sim
    if trace is not None:
        trace.start(sim)
    from_sim = getattr(policy, "from_sim", None)
    moved: deque[np.ndarray] = deque(maxlen=STILL_STATES - 1)
    turned: deque[np.ndarray] = deque(maxlen=STILL_STATES - 1)
    times = []
    while env.agents:
        t0 = time.perf_counter()
        if from_sim is not None:
            actions = np.asarray(from_sim(sim))[sim.driving]
        else:
            actions = np.asarray(policy(np.stack([obs[a] for a in env.agents])))
        times.append(time.perf_counter() - t0 + sim.feature_time)  # the policy's inputs: the candidate features' time too
        pos, heading = sim.pos.copy(), sim.heading.copy()
        obs, _, _, _, _ = env.step(dict(zip(env.agents, actions)))
        if trace is not None:
            trace.record(sim.last_new_collisions)
        if protocol == "agnn":
            moved.append(np.linalg.norm(sim.pos - pos, axis=1))
            turned.append(np.abs(wrap_angle(sim.heading - heading)))
            if len(times) >= STILL_STATES and (np.sum(moved, 0) < STILL_DISTANCE).all() and (np.sum(turned, 0) < STILL_ANGLE).all():
                break
    out = {**arena_metrics(sim), "step_time_s": float(np.mean(times)), "policy_calls": len(times)}
    if protocol == "agnn":
        reached, success = final_state_success(sim)
        out.update(success_to_goal_rate=float(success.mean()), success_rate_any=float(reached.mean()))
    return out


def plot_scenarios(
    source: str | Path,
    cases: list[tuple[int, int]],
    count: int,
    out: Path,
    max_steps: int = 400,
    protocol: str = "arena",
    generator: str = "agnn",
    observed: int | None = None,
    replays: bool = False,
) -> list[Path]:
    """Trajectory plots of the first ``count`` test scenarios of each case (the same episodes the suite scores), and with
    ``replays`` an HTML replay page of each beside its plot (``coin_app.sim.arena.replay``)."""

    policy = load_arena_policy(source)
    cfg = policy_config(policy, max_steps, protocol, generator, observed)
    env = ArenaEnv(cfg)
    paths = []
    for n, m in cases:
        for k in range(count):
            trace = ArenaTrace()
            res = run_scenario(policy, env, generate(heldout_rng(n, m, k), cfg, n, m), trace, protocol)
            title = (
                f"{n} vehicles, {m} obstacles, test scenario {k}: success {res['success_to_goal_rate']:.2f}, {res['collisions']} collisions"
            )
            paths.append(plot_arena_episode(trace, out / f"arena_{n}x{m}_{k}.png", title))
            if replays:
                paths.append(write_arena_replay(trace, out / f"arena_{n}x{m}_{k}.html", title=title))
    return paths


def evaluate_case(job: tuple[str, tuple[int, int], list[int], int, str, str, int | None]) -> list[dict[str, Any]]:
    """Rows (one per scenario) of test scenarios ``indices`` of one case (a worker job)."""
    source, (n, m), indices, max_steps, protocol, generator, observed = job
    try:
        torch.set_num_threads(1)
    except ImportError:
        pass
    policy = load_arena_policy(source)
    cfg = policy_config(policy, max_steps, protocol, generator, observed)
    env = ArenaEnv(cfg)
    rows = []
    for k in indices:
        layout = generate(heldout_rng(n, m, k), cfg, n, m)
        rows.append({"case": f"{n}x{m}", "scenario": k, "protocol": protocol, **run_scenario(policy, env, layout, protocol=protocol)})
    return rows


def evaluate_suite(
    source: str | Path,
    cases: list[tuple[int, int]],
    scenarios_per_case: int,
    max_steps: int = 400,
    workers: int = 2,
    log: Callable[[str], None] = print,
    protocol: str = "arena",
    generator: str = "agnn",
    observed: int | None = None,
) -> list[dict[str, Any]]:
    """Per-scenario rows of every case under ``protocol`` (``PROTOCOLS``; deterministic: the same rows on every run).

    ``generator="short"`` scores the parking stage's starts instead of the paper's suite (``suite_config``);
    ``observed`` sets the entities a scripted driver observes (``policy_config``).
    """

    if scenarios_per_case < 1:
        raise ValueError(f"bad scenarios per case {scenarios_per_case}; allowed: an integer >= 1")
    if workers < 1:
        raise ValueError(f"bad workers {workers}; allowed: an integer >= 1")
    suite_config(max_steps, protocol=protocol, generator=generator)  # a bad step limit, protocol or generator fails here, before any work
    policy_config(load_arena_policy(source), max_steps, protocol, generator, observed)  # and so do a bad source or entity count
    chunk = max(1, min(scenarios_per_case, 25))
    jobs = [
        (str(source), case, list(range(i, min(i + chunk, scenarios_per_case))), max_steps, protocol, generator, observed)
        for case in cases
        for i in range(0, scenarios_per_case, chunk)
    ]
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        os.environ.setdefault(var, "1")  # one CPU thread per worker (the step times of Table II)
    rows: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    if workers == 1:
        results = map(evaluate_case, jobs)
    else:
        pool = mp.get_context("spawn").Pool(workers)
        results = pool.imap(evaluate_case, jobs)
    try:
        for i, part in enumerate(results, 1):
            rows.extend(part)
            if i % max(1, len(jobs) // 10) == 0 or i == len(jobs):
                log(f"  {i}/{len(jobs)} jobs, {len(rows)} scenarios, {time.perf_counter() - t0:.0f} s")
    finally:
        if workers > 1:
            pool.close()
            pool.join()
    return rows


def summarize(rows: list[dict[str, Any]]) -> Any:
    """Per case: scenarios, vehicles, success-to-goal rate, collision rate (events / metres), mean step time; next to the paper's."""

    df = pd.DataFrame(rows)
    out = []
    for case, g in df.groupby("case", sort=False):
        n, m = (int(x) for x in str(case).split("x"))
        paper = PAPER_TABLE_I.get((n, m), (np.nan,) * 4)
        paper_time = PAPER_TABLE_II.get((n, m), (np.nan, np.nan))
        vehicles = int(g["vehicles"].sum())
        metres = float(g["distance"].sum())
        out.append(
            {
                "vehicles": n,
                "obstacles": m,
                "scenarios": len(g),
                "success_to_goal_rate": float((g["success_to_goal_rate"] * g["vehicles"]).sum() / vehicles),
                "collision_rate": float(g["collisions"].sum() / metres) if metres > 0 else np.nan,
                "step_time_s": float((g["step_time_s"] * g["policy_calls"]).sum() / g["policy_calls"].sum()),
                "paper_success": paper[0],
                "paper_agnn_success": paper[1],
                "agnn_supp_success": AGNN_SUPP_TABLE_II.get((n, m), np.nan),
                "paper_collision_rate": np.nan if paper[2] is None else paper[2],
                "paper_agnn_collision_rate": np.nan if paper[3] is None else paper[3],
                "paper_step_time_s": paper_time[0],
                "paper_agnn_step_time_s": paper_time[1],
            }
        )
    return pd.DataFrame(out)


def markdown_table(summary: Any) -> str:
    """The per-case summary as a Markdown table, ours next to the paper's Table I / II."""
    lines = [
        "| vehicles | obstacles | scenarios | success (ours) | success (paper) | A-GNN (paper) | A-GNN (own paper) "
        "| collisions/m (ours) | collisions/m (paper) | step time ms (ours) | step time ms (paper) |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]

    def f(x: float, fmt: str) -> str:
        return "–" if x is None or (isinstance(x, float) and np.isnan(x)) else format(x, fmt)

    for r in summary.to_dict("records"):
        lines.append(
            f"| {r['vehicles']} | {r['obstacles']} | {r['scenarios']} | {f(r['success_to_goal_rate'], '.3f')} | "
            f"{f(r['paper_success'], '.3f')} | {f(r['paper_agnn_success'], '.3f')} | {f(r['agnn_supp_success'], '.3f')} | "
            f"{f(r['collision_rate'], '.2e')} | "
            f"{f(r['paper_collision_rate'], '.2e')} | {f(r['step_time_s'] * 1e3, '.3f')} | {f(r['paper_step_time_s'] * 1e3, '.3f')} |"
        )
    return "\n".join(lines) + "\n"
