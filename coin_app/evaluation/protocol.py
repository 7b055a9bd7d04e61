"""The paper's evaluation protocol as a parallel evaluator writing one tidy results table.

Every trained model (a :class:`EvalRun`: method, variant, trained seed, checkpoint) is run with
its deterministic actor on the fixed test seeds (``TEST_SEED_BASE + k``, disjoint from the
training and validation seeds), on its training scenario or on other ``scenarios``, at its
training agent count and at any other ``counts``, on the native simulator or, with ``backend``,
on another backend (MetaDrive: the transfer evaluation). One task is one run: it loads the checkpoint once
and evaluates every (scenario, count) of the grid, all test seeds of one cell in one batched
simulator. Tasks run in ``workers`` spawned processes (one torch thread each) or, with
``workers=1``, in this process.

The result is one row per episode (:data:`RESULT_COLUMNS`): method, variant, trained seed,
test seed, scenario, agent count, the training agent count, the backend, every metric of
:func:`~coin_app.evaluation.metrics.episode_metrics` in :data:`EPISODE_METRICS`, the episode
length in env steps, the wall time (the batched cell's wall time divided by its episodes),
the trained env steps and the checkpoint path. A checkpoint that is missing or cannot be
loaded does not stop the others: it lands in :attr:`Evaluation.failures` with its path and
the error.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import pandas as pd
import torch

from coin_app.algorithms.checkpoint_files import read_metadata
from coin_app.algorithms.checkpoints import scenario_of
from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.metrics import METRIC_KEYS
from coin_app.evaluation.policies import checkpoint_policy
from coin_app.sim.config import BACKENDS, DEFAULT_NUM_AGENTS
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.seeds import TEST_SEED_BASE, VALIDATION_SEED_BASE

EPISODE_METRICS = (*METRIC_KEYS, "avg_travel_steps_arrived", "episode_return", "num_vehicles")
KEYS = ("method", "variant", "trained_seed", "test_seed", "scenario", "agent_count", "trained_agent_count")
RESULT_COLUMNS = (*KEYS, "backend", *EPISODE_METRICS, "episode_length", "wall_time_s", "trained_env_steps", "checkpoint")

EVALUATION_FILE = "evaluation.json"  # beside results.csv: the evaluation's settings and failures


@dataclass(frozen=True)
class EvalRun:
    """One trained model to evaluate."""

    method: str
    variant: str
    trained_seed: int
    checkpoint: str
    trained_env_steps: int | None = None

    @property
    def label(self) -> str:
        """``<method>[-<variant>] seed <k>``, for logs and failure reports."""
        variant = "" if self.variant == "default" else f"-{self.variant}"
        return f"{self.method}{variant} seed {self.trained_seed}"


@dataclass
class Evaluation:
    """The tidy per-episode table and the runs that could not be evaluated."""

    table: pd.DataFrame
    failures: list[dict[str, Any]] = field(default_factory=list)
    wall_s: float = 0.0


def check_grid(test_seeds: Sequence[int], counts: Sequence[int] | None, scenarios: Sequence[str] | None) -> None:
    """Refuse a bad evaluation grid before any work starts (ValueError naming the value)."""

    if not test_seeds:
        raise ValueError("no test seeds; allowed: one or more integers (the fixed test seeds)")
    bad = [c for c in counts or () if not (isinstance(c, int) and c >= 1)]
    if bad or (counts is not None and not counts):
        raise ValueError(f"bad agent counts {list(counts or [])}; allowed: one or more integers >= 1")
    unknown = [s for s in scenarios or () if s not in DEFAULT_NUM_AGENTS]
    if unknown or (scenarios is not None and not scenarios):
        raise ValueError(f"unknown scenarios {unknown or list(scenarios or [])}; allowed: {', '.join(DEFAULT_NUM_AGENTS)}")


def evaluate_run(
    run: EvalRun,
    test_seeds: Sequence[int],
    counts: Sequence[int] | None = None,
    scenarios: Sequence[str] | None = None,
    backend: str | None = None,
) -> list[dict[str, Any]]:
    """Per-episode rows of one run over the (scenario, count) grid; raises if its checkpoint cannot be loaded.

    ``counts`` are agent counts evaluated in addition to the training count (always evaluated);
    ``backend`` replaces the training backend (None: the checkpoint's own).
    """

    meta = read_metadata(Path(run.checkpoint))
    policy = checkpoint_policy(Path(run.checkpoint))
    trained = scenario_of(Path(run.checkpoint))
    env_steps = run.trained_env_steps if run.trained_env_steps is not None else meta.get("env_steps")
    rows = []
    for scenario in scenarios or [trained.scenario]:
        for count in sorted({*(counts or ()), trained.num_agents}):
            env = {**meta.get("env_config", {}), "num_agents": int(count), **({"backend": backend} if backend else {})}
            config = config_from_dict(scenario, env)
            t0 = time.perf_counter()
            episodes = evaluate_policy(policy, config, test_seeds)
            wall = (time.perf_counter() - t0) / len(episodes)
            for seed, m in zip(test_seeds, episodes):
                rows.append(
                    {
                        "method": run.method,
                        "variant": run.variant,
                        "trained_seed": int(run.trained_seed),
                        "test_seed": int(seed),
                        "scenario": config.scenario,
                        "agent_count": int(count),
                        "trained_agent_count": trained.num_agents,
                        "backend": config.backend,
                        **{k: float(m[k]) for k in EPISODE_METRICS},
                        "episode_length": int(m["env_steps"]),
                        "wall_time_s": wall,
                        "trained_env_steps": env_steps,
                        "checkpoint": str(run.checkpoint),
                    }
                )
    return rows


def _task(
    run: EvalRun, test_seeds: list[int], counts: list[int] | None, scenarios: list[str] | None, backend: str | None
) -> tuple[list[dict], str | None]:
    """One run in a worker: (rows, None) or ([], error message)."""
    try:
        return evaluate_run(run, test_seeds, counts, scenarios, backend), None
    except Exception as exc:  # noqa: BLE001 - a broken checkpoint is reported, the others still run
        return [], f"{type(exc).__name__}: {exc}"


def _init_worker() -> None:

    torch.set_num_threads(1)


def run_evaluation(
    runs: Sequence[EvalRun],
    test_seeds: Sequence[int],
    counts: Sequence[int] | None = None,
    scenarios: Sequence[str] | None = None,
    workers: int = 1,
    log: Callable[[str], None] = print,
    backend: str | None = None,
    cache: EpisodeCache | None = None,
) -> Evaluation:
    """Evaluate every run on the test seeds x scenarios x agent counts grid (on ``backend``); one row per episode.

    ``cache``: runs whose episodes it holds for this grid are read from it, every other run's are stored in it as the run
    ends (:mod:`~coin_app.evaluation.episode_cache`), so an interrupted evaluation repeated does only what is left.
    """

    seeds = [int(s) for s in test_seeds]
    check_grid(seeds, None if counts is None else list(counts), None if scenarios is None else list(scenarios))
    if workers < 1:
        raise ValueError(f"bad workers {workers}; allowed: an integer >= 1")
    if backend not in (None, *BACKENDS):
        raise ValueError(f"bad backend {backend!r}; allowed: {', '.join(BACKENDS)}")
    counts = None if counts is None else [int(c) for c in counts]
    scenarios = None if scenarios is None else list(scenarios)
    grid = f"agent counts {counts} and the training count" if counts else "the training agent count"
    where = f"scenarios {scenarios}" if scenarios else "the training scenario"
    on = f" on the {backend} backend" if backend else ""
    kind = "test" if min(seeds) >= TEST_SEED_BASE else "validation" if min(seeds) >= VALIDATION_SEED_BASE else "episode"
    t0 = time.perf_counter()
    rows: list[dict[str, Any]] = []
    failures: list[dict[str, Any]] = []
    todo = []
    for run in runs:
        found = cache.load(run, seeds, counts, scenarios, backend) if cache is not None else None
        if found is None:
            todo.append(run)
        else:
            rows.extend(found)
    n_workers = min(workers, max(len(todo), 1))
    log(f"evaluating {len(runs)} runs{on} on {where} at {grid}, {len(seeds)} {kind} seeds, {n_workers} workers")
    if cache is not None and len(todo) < len(runs):
        log(f"  {len(runs) - len(todo)} of the {len(runs)} runs' episodes read from {cache.root}")

    def collect(i: int, run: EvalRun, out: list[dict], error: str | None) -> None:
        if error is not None:
            failures.append({**asdict(run), "error": error})
            log(f"  [{i}/{len(todo)}] FAILED {run.label}: {run.checkpoint}: {error}")
            return
        rows.extend(out)
        if cache is not None:
            cache.store(run, seeds, counts, scenarios, backend, out)
        success = sum(r["success_rate"] for r in out) / max(len(out), 1)
        log(f"  [{i}/{len(todo)}] {run.label}: {len(out)} episodes, mean success {success:.3f} ({time.perf_counter() - t0:.0f} s)")

    if workers == 1 or len(todo) <= 1:
        for i, run in enumerate(todo, 1):
            collect(i, run, *_task(run, seeds, counts, scenarios, backend))
    else:
        with ProcessPoolExecutor(max_workers=n_workers, mp_context=get_context("spawn"), initializer=_init_worker) as pool:
            futures = {pool.submit(_task, run, seeds, counts, scenarios, backend): run for run in todo}
            for i, fut in enumerate(as_completed(futures), 1):
                run = futures[fut]
                try:
                    out, error = fut.result()
                except Exception as exc:  # noqa: BLE001 - a worker that died (e.g. out of memory) fails only its run
                    out, error = [], f"{type(exc).__name__}: {exc}"
                collect(i, run, out, error)
    table = pd.DataFrame(rows, columns=list(RESULT_COLUMNS))
    table = table.sort_values(list(KEYS), kind="stable").reset_index(drop=True)
    return Evaluation(table, failures, time.perf_counter() - t0)


def read_results(path: Path) -> pd.DataFrame:
    """A results table written by :func:`write_results` (CSV); a ValueError naming missing columns."""
    path = Path(path)
    if not path.is_file():
        raise ValueError(f"results file {path} does not exist")
    table = pd.read_csv(path)
    missing = [c for c in (*KEYS, "success_rate", "safety", "efficiency") if c not in table.columns]
    if missing:
        raise ValueError(f"{path} is not a coin_app results table: missing columns {missing}")
    if "backend" not in table.columns:  # tables written before the transfer evaluation: all native
        table.insert(list(table.columns).index("trained_agent_count") + 1, "backend", "native")
    others = sorted(set(table["backend"]) - {"native"})
    if others:
        raise ValueError(f"{path} holds {', '.join(others)} episodes (a transfer table); allowed: a results table of native episodes")
    return table


def write_results(evaluation: Evaluation, out_dir: Path, settings: dict[str, Any]) -> Path:
    """Write ``results.csv`` (one row per episode) and ``evaluation.json`` (settings, failures) into ``out_dir``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "results.csv"
    evaluation.table.to_csv(path, index=False)
    meta = {**settings, "failures": evaluation.failures, "wall_s": round(evaluation.wall_s, 1), "episodes": len(evaluation.table)}
    (out_dir / EVALUATION_FILE).write_text(json.dumps(meta, indent=2, default=str))
    return path
