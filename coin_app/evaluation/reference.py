"""The COIN authors' released actors as a reference: their evaluation protocol on every scene, natively and on MetaDrive.

The protocol is the official ``coin_eval.py``'s, with deterministic actions (docs/decisions.md §5): each
training seed's released actor drives ``episodes`` episodes seeded ``1000 + 100·i``, every scene at
COIN's vehicle count (Table 5.1: intersection 30, roundabout 40, bottleneck 20), with the settings
the authors trained on — MetaDrive's own penalties and lidar (the ``metadrive_compat`` preset),
MetaDrive's observation layout (96 numbers on the bottleneck), and their patched bottleneck, whose
neck centre line is solid (``solid_center_line``; a no-op on the other scenes).

:func:`run_reference` evaluates what ``results.csv`` in the output directory does not hold yet (one
row per episode, rewritten atomically after each task, so an interrupted run resumes) and
:func:`summary_table` reduces the rows to one line per scene and simulator: the mean over training
seeds of each seed's mean over its episodes, the standard deviation over seeds and the range.
"""

from __future__ import annotations

import contextlib
import json
import multiprocessing as mp
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pandas as pd

from coin_app.backends.metadrive import INSTALL_HINT, metadrive_available
from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.evaluation.evaluate import evaluate_policy
from coin_app.evaluation.outputs import write_text_atomic
from coin_app.evaluation.paper_table import AUTHORS, TABLE_5_1
from coin_app.evaluation.protocol import EPISODE_METRICS
from coin_app.inference.coin_actors import SOURCE, find_coin_actors, load_coin_actor
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.scenes import SCENES

EPISODE_SEED_BASE, EPISODE_SEED_STEP = 1000, 100  # coin_eval.py: episode i runs with start_seed = 1000 + 100 i
BACKENDS = ("native", "metadrive")
PRESET = "metadrive_compat"
# COIN Table 5.1, the COIN row: success, off-road and collision rates (%)
PAPER = {
    scene: tuple(TABLE_5_1[scene]["cig_td3"][m][0] for m in ("success_rate", "out_of_road_rate", "collision_rate")) for scene in TABLE_5_1
}
RATES = {"success_rate": "success", "collision_rate": "collision", "out_of_road_rate": "off-road", "timeout_rate": "time-out"}
KEY = ["scene", "backend", "train_seed", "episode_seed"]
RESULTS, TABLE_CSV, TABLE_MD, SETTINGS = "results.csv", "table.csv", "table.md", "settings.json"


def episode_seeds(n: int) -> list[int]:
    """The official evaluation's first ``n`` episode seeds: 1000, 1100, ..."""
    return [EPISODE_SEED_BASE + EPISODE_SEED_STEP * i for i in range(n)]


def reference_config(scene: str, backend: str) -> ScenarioConfig:
    """The scenario the authors trained and evaluated ``scene`` on, on ``backend`` (see the module doc)."""
    return make_config(
        scene,
        PRESET,
        backend=backend,
        obs_layout=SCENES[scene].metadrive_obs_layout,
        solid_center_line=True,
    )


@dataclass(frozen=True)
class Task:
    """One unit of work: the actor of ``train_seed`` on ``scene`` and ``backend`` over ``episode_seeds``."""

    scene: str
    backend: str
    train_seed: int
    actor: Path
    episode_seeds: tuple[int, ...]


def plan(root: Path, scenes: Sequence[str], backends: Sequence[str], train_seeds: Sequence[int] | None, episodes: int) -> list[Task]:
    """The tasks of a reference run; a ValueError names a scene without actors under ``root`` or a missing training seed.

    Native tasks hold all episodes of one actor (one batched simulator); MetaDrive tasks one episode each (one engine).
    """
    if episodes < 1:
        raise ValueError(f"bad --episodes {episodes}; allowed: an integer >= 1")
    bad = [b for b in backends if b not in BACKENDS]
    if bad:
        raise ValueError(f"unknown backend(s) {bad}; allowed: {', '.join(BACKENDS)}")
    if "metadrive" in backends and not metadrive_available():
        raise ValueError(f"backend metadrive needs the metadrive-simulator package; {INSTALL_HINT} (or pass --backends native)")
    tasks = []
    seeds = episode_seeds(episodes)
    for scene in scenes:
        actors = find_coin_actors(root, scene)
        if not actors:
            raise ValueError(f"no {scene} actors (TD3_{scene}_<seed>_best_model_*_actor) under {root}")
        chosen = list(actors) if train_seeds is None else list(train_seeds)
        missing = [s for s in chosen if s not in actors]
        if missing:
            raise ValueError(f"no {scene} actor of training seed(s) {missing} under {root}; allowed: {', '.join(map(str, actors))}")
        for backend in backends:
            for seed in chosen:
                groups = [tuple(seeds)] if backend == "native" else [(s,) for s in seeds]
                tasks += [Task(scene, backend, seed, actors[seed], g) for g in groups]
    return tasks


def run_task(task: Task) -> list[dict[str, Any]]:
    """The result rows (one per episode) of one task."""
    start = time.perf_counter()
    metrics = evaluate_policy(load_coin_actor(task.actor), reference_config(task.scene, task.backend), task.episode_seeds)
    wall = (time.perf_counter() - start) / len(metrics)
    rows = []
    for seed, m in zip(task.episode_seeds, metrics):
        n = m["num_vehicles"]
        row = {"scene": task.scene, "backend": task.backend, "train_seed": task.train_seed, "episode_seed": seed}
        row |= {k: m[k] for k in ("success_rate", "collision_rate", "out_of_road_rate")}
        row |= {"timeout_rate": m["num_timeout"] / n if n else float("nan")}
        row |= {k: int(m[k]) for k in ("num_vehicles", "num_arrived", "num_crashed", "num_out_of_road", "num_timeout", "env_steps")}
        rows.append(row | {"actor": task.actor.name, "wall_s": round(wall, 1)})
    return rows


def _done(results: pd.DataFrame, task: Task) -> bool:
    if results.empty:
        return False
    hit = results[(results.scene == task.scene) & (results.backend == task.backend) & (results.train_seed == task.train_seed)]
    hit = hit[hit.episode_seed.isin(task.episode_seeds) & (hit.actor == task.actor.name)]
    return len(hit) == len(task.episode_seeds)


def _write_csv(frame: pd.DataFrame, path: Path) -> None:
    """``frame`` to ``path`` atomically (a hidden sibling renamed over it)."""
    write_text_atomic(path, frame.to_csv(index=False))


def load_results(out: Path) -> pd.DataFrame:
    """The rows of ``out/results.csv`` (empty if there is none yet)."""
    path = out / RESULTS
    return pd.read_csv(path) if path.is_file() else pd.DataFrame(columns=KEY)


def run_reference(
    tasks: Sequence[Task],
    out: Path,
    workers: int = 1,
    progress: Callable[[str], None] | None = None,
    settings: dict[str, Any] | None = None,
) -> pd.DataFrame:
    """Run the tasks whose rows ``out/results.csv`` lacks (``workers`` processes); all rows.

    After each task its rows join ``results.csv`` and, with ``settings``, the tables are rewritten (:func:`write_tables`),
    so an interrupted run leaves a table of what finished.
    """
    if workers < 1:
        raise ValueError(f"bad --workers {workers}; allowed: an integer >= 1")
    out.mkdir(parents=True, exist_ok=True)
    results = load_results(out)
    todo = [t for t in tasks if not _done(results, t)]
    say = progress or (lambda _line: None)
    say(f"{len(tasks) - len(todo)} of {len(tasks)} tasks already in {out / RESULTS}; {len(todo)} to run")
    start = time.perf_counter()

    def add(k: int, task: Task, rows: list[dict[str, Any]]) -> None:
        nonlocal results
        new = pd.DataFrame(rows)
        results = new if results.empty else pd.concat([results, new], ignore_index=True)
        results = results.drop_duplicates(KEY, keep="last").sort_values(KEY, ignore_index=True)
        _write_csv(results, out / RESULTS)
        if settings is not None:
            write_tables(results, out, settings)
        elapsed = time.perf_counter() - start
        eta = elapsed / (k + 1) * (len(todo) - k - 1)
        success = " ".join(f"{r['success_rate']:.3f}" for r in rows)
        say(
            f"[{k + 1}/{len(todo)}] {task.scene} {task.backend} seed {task.train_seed} episodes {list(task.episode_seeds)}: "
            f"success {success}; {elapsed / 60:.1f} min, about {eta / 60:.0f} min left"
        )

    if workers == 1 or len(todo) <= 1:
        for k, task in enumerate(todo):
            add(k, task, run_task(task))
    else:
        with mp.get_context("spawn").Pool(workers, maxtasksperchild=1) as pool:
            for k, (task, rows) in enumerate(pool.imap_unordered(_run_pair, todo)):
                add(k, task, rows)
    return results


def _run_pair(task: Task) -> tuple[Task, list[dict[str, Any]]]:
    """``(task, run_task(task))`` for the worker pool (one task per process: MetaDrive keeps state in its process)."""
    return task, run_task(task)


REFERENCE_METHOD = AUTHORS  # the label of the authors' actors in a report's tables: a reference row, never a baseline


def test_seed_rows(
    root: Path,
    scene: str,
    test_seeds: Sequence[int],
    workers: int = 1,
    log: Callable[[str], None] | None = None,
    backend: str = "native",
    cache: EpisodeCache | None = None,
) -> pd.DataFrame:
    """The authors' actors of ``scene`` (every training seed under ``root``) on a report's ``test_seeds`` on ``backend``: one
    row per episode in the report's results layout (method :data:`REFERENCE_METHOD`, the actor file as its checkpoint).

    The scene is the authors' (:func:`reference_config`) at COIN's vehicle count; a ValueError if ``root`` has no actors of it.
    ``cache``: tasks whose rows it holds are read from it, the others stored in it as they end (as ``run_evaluation``'s).
    """
    actors = find_coin_actors(root, scene)
    if not actors:
        raise ValueError(f"no {scene} actors (TD3_{scene}_<seed>_best_model_*_actor) under {root}")
    seeds = tuple(int(s) for s in test_seeds)
    if backend == "native":  # one batched simulator per actor; MetaDrive: one engine (process) per episode
        tasks = [Task(scene, backend, seed, path, seeds) for seed, path in actors.items()]
    else:
        tasks = [Task(scene, backend, seed, path, (s,)) for seed, path in actors.items() for s in seeds]
    say = log or (lambda _line: None)
    say(f"  the COIN authors' {scene} actors: {len(actors)} training seeds x {len(seeds)} test seeds on {backend}")
    count = reference_config(scene, backend).num_agents

    def as_run(task: Task) -> SimpleNamespace:  # the cache's view of a task: a model, its seeds (on ``backend``)
        return SimpleNamespace(
            method=REFERENCE_METHOD, variant="default", trained_seed=task.train_seed, trained_env_steps=None, checkpoint=str(task.actor)
        )

    def rows_of(task: Task, episodes: list[dict[str, Any]], wall: float) -> list[dict[str, Any]]:
        return [
            {"method": REFERENCE_METHOD, "variant": "default", "trained_seed": task.train_seed, "test_seed": seed}
            | {"scenario": scene, "agent_count": count, "trained_agent_count": count, "backend": task.backend}
            | {k: float(m[k]) for k in EPISODE_METRICS}
            | {"episode_length": int(m["env_steps"]), "wall_time_s": wall, "trained_env_steps": np.nan, "checkpoint": str(task.actor)}
            for seed, m in zip(task.episode_seeds, episodes)
        ]

    rows: list[dict[str, Any]] = []
    todo = []
    for task in tasks:
        found = cache.load(as_run(task), task.episode_seeds, None, [scene], backend) if cache is not None else None
        rows += found if found is not None else []
        todo += [task] if found is None else []
    if len(todo) < len(tasks):
        say(f"  {len(tasks) - len(todo)} of the {len(tasks)} tasks' episodes read from {getattr(cache, 'root', '')}")
    with contextlib.ExitStack() as stack:
        if workers == 1 or len(todo) <= 1:
            done = map(_episodes_of, todo)
        else:
            done = stack.enter_context(mp.get_context("spawn").Pool(min(workers, len(todo)), maxtasksperchild=1)).imap(_episodes_of, todo)
        for task, episodes, wall in done:
            new = rows_of(task, episodes, wall)
            if cache is not None:
                cache.store(as_run(task), task.episode_seeds, None, [scene], backend, new)
            rows += new
    frame = pd.DataFrame(rows)
    return frame.sort_values(["trained_seed", "test_seed"], kind="stable", ignore_index=True) if len(frame) else frame


def _episodes_of(task: Task) -> tuple[Task, list[dict[str, Any]], float]:
    """One task's episode metrics (``evaluate_policy``'s) and its wall seconds per episode."""
    start = time.perf_counter()
    episodes = evaluate_policy(load_coin_actor(task.actor), reference_config(task.scene, task.backend), task.episode_seeds)
    return task, episodes, (time.perf_counter() - start) / len(episodes)


def summary_table(results: pd.DataFrame) -> pd.DataFrame:
    """One row per scene and backend: per rate, mean, sd and range over training seeds of each seed's episode mean (%)."""
    rows = []
    scenes = [s for s in SCENES if s in set(results.scene)]
    for scene in scenes:
        for backend in BACKENDS:
            part = results[(results.scene == scene) & (results.backend == backend)]
            if part.empty:
                continue
            per_seed = part.groupby("train_seed")[list(RATES)].mean() * 100
            row: dict[str, Any] = {"scene": scene, "vehicles": SCENES[scene].default_vehicles, "backend": backend}
            row |= {"seeds": len(per_seed), "episodes": len(part), "timeouts_per_episode": part.num_timeout.mean()}
            row |= {"wall_min": part.wall_s.sum() / 60 if "wall_s" in part else np.nan}
            for rate in RATES:
                v = per_seed[rate].to_numpy()
                row |= {f"{rate}_mean": v.mean(), f"{rate}_sd": v.std(ddof=1) if len(v) > 1 else np.nan}
                row |= {f"{rate}_min": v.min(), f"{rate}_max": v.max()}
            row["paper_success"] = PAPER[scene][0]
            rows.append(row)
    return pd.DataFrame(rows)


def gap_table(results: pd.DataFrame) -> pd.DataFrame:
    """One row per scene run on both backends: native minus MetaDrive on the episodes both ran (paired by training seed and
    episode seed), in points of success and of time-outs: the mean over training seeds of each seed's mean paired
    difference, and its standard error over seeds (sd / sqrt(seeds); NaN with one seed)."""
    rows = []
    for scene in [s for s in SCENES if s in set(results.scene)]:
        part = results[results.scene == scene]
        pair = ["train_seed", "episode_seed"]
        native = part[part.backend == "native"].set_index(pair)
        metadrive = part[part.backend == "metadrive"].set_index(pair)
        both = native.index.intersection(metadrive.index)
        if both.empty:
            continue
        row: dict[str, Any] = {"scene": scene, "vehicles": SCENES[scene].default_vehicles, "seeds": both.get_level_values(0).nunique()}
        row["episodes"] = len(both)
        for rate in ("success_rate", "timeout_rate"):
            diff = (native.loc[both, rate] - metadrive.loc[both, rate]) * 100
            per_seed = diff.groupby(level="train_seed").mean().to_numpy()
            row[f"{rate}_gap"] = per_seed.mean()
            row[f"{rate}_se"] = per_seed.std(ddof=1) / np.sqrt(len(per_seed)) if len(per_seed) > 1 else np.nan
        rows.append(row)
    return pd.DataFrame(rows)


def gap_markdown(gaps: pd.DataFrame) -> str:
    """The paired gaps as a markdown table, with whether the success gap is within 2 points (issue 57's bar)."""
    lines = [
        "| scene (vehicles) | paired episodes (seeds × episodes) | native − MetaDrive, success points (SE) "
        "| time-out points (SE) | within 2 points |",
        "|---|---:|---:|---:|---|",
    ]
    for _, row in gaps.iterrows():
        cells = []
        for rate in ("success_rate", "timeout_rate"):
            se = row[f"{rate}_se"]
            cells.append(f"{row[f'{rate}_gap']:+.1f}" + (f" ({se:.1f})" if np.isfinite(se) else ""))
        within = "yes" if abs(row["success_rate_gap"]) <= 2 else "no"
        lines.append(
            f"| {row['scene']} ({row['vehicles']}) | {row['episodes']} ({row['seeds']} seed{'s' if row['seeds'] > 1 else ''}) "
            f"| {cells[0]} | {cells[1]} | {within} |"
        )
    return "\n".join(lines) + "\n"


def _cell(row: pd.Series, rate: str, spread: bool) -> str:
    text = f"{row[f'{rate}_mean']:.1f}"
    if spread and row["seeds"] > 1:
        text += f" ± {row[f'{rate}_sd']:.1f} ({row[f'{rate}_min']:.1f}–{row[f'{rate}_max']:.1f})"
    return text


def to_markdown(table: pd.DataFrame) -> str:
    """The summary as a markdown table: success with its spread over seeds, then collision, off-road and time-out (%)."""
    names = {"native": "native", "metadrive": "MetaDrive 0.4.3"}
    lines = [
        "| scene (vehicles) | simulator | success % (± sd, range over seeds) | collision % | off-road % | time-out % "
        "| seeds × episodes | wall (min) | paper |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for _, row in table.iterrows():
        cells = [_cell(row, "success_rate", True)] + [_cell(row, r, False) for r in list(RATES)[1:]]
        per_seed = row["episodes"] / row["seeds"]
        count = f"{row['seeds']} × {per_seed:g}" if per_seed == int(per_seed) else f"{row['episodes']} episodes"
        lines.append(
            f"| {row['scene']} ({row['vehicles']}) | {names[row['backend']]} | {' | '.join(cells)} | {count} "
            f"| {row['wall_min']:.0f} | {row['paper_success']:.2f} |"
        )
    return "\n".join(lines) + "\n"


def write_tables(results: pd.DataFrame, out: Path, settings: dict[str, Any]) -> list[Path]:
    """``table.csv``, ``table.md`` (with the protocol and the actors' source and licence) and ``settings.json`` in ``out``."""
    table = summary_table(results)
    _write_csv(table, out / TABLE_CSV)
    gaps = gap_table(results)
    text = (
        "# The COIN authors' actors (reference)\n\n"
        f"{to_markdown(table)}\n"
        "Deterministic actions; episode seeds 1000 + 100·i; `metadrive_compat` preset, MetaDrive's observation, the "
        "bottleneck's solid neck centre line (the authors' patched MetaDrive). Rates are the mean over training seeds of "
        "each seed's mean over its episodes; time-outs are vehicles that reached their own step limit; wall: the "
        "episodes' wall time on the machine that ran them; paper: COIN's Table 5.1 success.\n\n"
    )
    if not gaps.empty:
        text += (
            "Native minus MetaDrive on the episodes both simulators ran, paired by training seed and episode seed (the "
            "mean over seeds of each seed's mean difference; SE: its standard error over seeds):\n\n"
            f"{gap_markdown(gaps)}\n"
        )
    text += f"Actors: {SOURCE}.\n\nCommand: `{settings.get('command', '')}`\n"
    write_text_atomic(out / TABLE_MD, text)
    write_text_atomic(out / SETTINGS, json.dumps(settings, indent=2) + "\n")
    return [out / TABLE_CSV, out / TABLE_MD, out / SETTINGS]
