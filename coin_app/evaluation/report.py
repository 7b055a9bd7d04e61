"""``python -m coin_app report``: evaluate sweeps (or read results) and write the paper's tables and figures.

Sources are sweep directories (``coin_sweep.json``), directories holding sweeps, or results
tables written by an earlier report (``results.csv``). Every finished or unfinished trial with a
checkpoint is evaluated with :func:`~coin_app.evaluation.protocol.run_evaluation` on the fixed
test seeds at its training agent count (and, for a generalization sweep or with ``counts``,
at the other counts); methods and variants come from the data, so a new baseline appears in
every output without changes here. Outputs in ``out``:

``results.csv`` + ``evaluation.json`` (per-episode table, settings, failures), ``table_main``
and ``table_ablation`` ``.{md,csv,tex}``, ``table_paper.{md,csv}`` (the models trained at Table 5.1's density beside
the paper's figures: :mod:`coin_app.evaluation.paper_table`), ``stats.csv``, ``radar_<scenario>.png``,
``generalization_<scenario>.png``, ``learning_curves_<scenario>.png`` (and against the trials' CPU and wall
hours, ``learning_curves_cpu_s_<scenario>.png`` / ``learning_curves_wall_s_<scenario>.png``, where they recorded them,
and what the trials cost, ``table_cost.{md,csv}``),
``trajectories_<scenario>_<method>.png``, ``latent_tsne.png``, ``attention_<scenario>.png`` + ``.csv`` (where the
method's GAT looks, :mod:`~coin_app.evaluation.attention`), ``marl_eval.json``, with
``select="validation"`` each trial's checkpoint chosen on validation seeds (``selection.csv``:
:mod:`coin_app.evaluation.selection`), with
``transfer`` the same models on another backend (``transfer_results.csv``, ``table_transfer``
``.{md,csv}``: :mod:`coin_app.evaluation.transfer`) and
``report.html`` (everything above in one self-contained page, with command, versions and
configs). A figure that cannot be drawn from the data (no progress files, no CVAE model) is
named in the page with the reason instead.
"""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from coin_app.algorithms.checkpoint_files import META_FILE
from coin_app.algorithms.checkpoints import scenario_of
from coin_app.backends.metadrive import INSTALL_HINT, metadrive_available
from coin_app.evaluation import attention, paper_table, plots, statistics, tables
from coin_app.evaluation.embedding import kmeans, tsne
from coin_app.evaluation.episode_cache import EpisodeCache
from coin_app.evaluation.evaluate import run_episode
from coin_app.evaluation.html_report import write_html
from coin_app.evaluation.latents import collect_latents
from coin_app.evaluation.limits import VALIDATION_EPISODES
from coin_app.evaluation.marl_eval import run_label, write_marl_eval
from coin_app.evaluation.policies import checkpoint_policy
from coin_app.evaluation.protocol import EVALUATION_FILE, EvalRun, Evaluation, read_results, run_evaluation, write_results
from coin_app.evaluation.reference import REFERENCE_METHOD, test_seed_rows
from coin_app.evaluation.selection import (
    FINAL,
    SELECTION_FILE,
    SELECTIONS,
    VALIDATION,
    select_checkpoints,
    selection_caption,
    trial_candidates,
)
from coin_app.evaluation.sweep_results import SETTINGS_FILE, load_trials, read_settings, sweep_dirs
from coin_app.evaluation.transfer import transfer_table, write_transfer
from coin_app.sim.config import BACKENDS
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.rendering import EpisodeTrace, plot_trajectories
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.seeds import eval_test_seeds

Log = Callable[[str], None]


@dataclass
class ReportOptions:
    """What the report evaluates and draws (defaults: the paper's protocol, smaller t-SNE sample)."""

    method: str = "cig_td3"  # the method compared with every baseline (stats, first colour)
    counts: tuple[int, ...] | None = None  # extra agent counts to evaluate at (default: a generalization sweep's grid)
    test_seeds: int | None = None  # test episodes per model and cell (default: the sweep's, 20)
    workers: int = 2  # evaluation processes
    alpha: float = 0.01  # family-wise significance level before Bonferroni
    tsne_samples: int = 500  # latent samples per scenario (the paper: 1500)
    tsne_episodes: int = 4  # test episodes the latents are drawn from
    transfer: str | None = None  # another backend every model is also evaluated on (metadrive), at its training count
    transfer_test_seeds: int = 5  # test episodes per model on that backend (the first of the native test seeds)
    select: str = FINAL  # the checkpoint of a trial scored: its final one, or the one best on validation seeds (COIN's "best_model")
    validation_episodes: int = VALIDATION_EPISODES  # validation seeds per checkpoint for select="validation"
    reference_actors: str | None = None  # the COIN authors' actors' directory: their row on the same test seeds (reference.py)
    cache: str | None = None  # evaluated episodes kept here and reused (episode_cache.py); None: every episode evaluated again
    command: str | None = None  # the command line, recorded in the page

    def check(self) -> None:
        """Refuse bad options before any work starts."""
        if self.test_seeds is not None and self.test_seeds < 1:
            raise ValueError(f"bad --test-seeds {self.test_seeds}; allowed: an integer >= 1")
        if self.workers < 1:
            raise ValueError(f"bad --workers {self.workers}; allowed: an integer >= 1")
        if not 0.0 < self.alpha < 1.0:
            raise ValueError(f"bad --alpha {self.alpha}; allowed: a number in (0, 1)")
        if self.tsne_samples < 10:
            raise ValueError(f"bad --tsne-samples {self.tsne_samples}; allowed: an integer >= 10")
        if self.tsne_episodes < 1:
            raise ValueError(f"bad --tsne-episodes {self.tsne_episodes}; allowed: an integer >= 1")
        if self.counts is not None and (not self.counts or any(c < 1 for c in self.counts)):
            raise ValueError(f"bad --counts {list(self.counts)}; allowed: one or more integers >= 1")
        others = [b for b in BACKENDS if b != "native"]
        if self.transfer is not None and self.transfer not in others:
            raise ValueError(f"bad --transfer {self.transfer!r}; allowed: {', '.join(others)}")
        if self.select not in SELECTIONS:
            raise ValueError(f"bad --select {self.select!r}; allowed: {', '.join(SELECTIONS)}")
        if self.validation_episodes < 1:
            raise ValueError(f"bad --validation-episodes {self.validation_episodes}; allowed: an integer >= 1")
        if self.transfer_test_seeds < 1:
            raise ValueError(f"bad --transfer-test-seeds {self.transfer_test_seeds}; allowed: an integer >= 1")
        if self.reference_actors is not None and not Path(self.reference_actors).is_dir():
            raise ValueError(f"bad --reference-actors {self.reference_actors!r}; allowed: a directory of the COIN authors' actors")
        if self.transfer == "metadrive" and not metadrive_available():
            raise ValueError(f"--transfer metadrive needs the metadrive-simulator package, which is not installed; {INSTALL_HINT}")


@dataclass
class Sources:
    """What the report reads: sweeps to evaluate and results tables already evaluated."""

    sweeps: list[dict[str, Any]] = field(default_factory=list)  # {"path", "settings", "runs", "candidates", "skipped", "unfinished"}
    paths: list[Path] = field(default_factory=list)  # the paths as given
    tables: list[dict[str, Any]] = field(default_factory=list)  # {"path", "table", "settings"}


def gather(paths: Sequence[Path]) -> Sources:
    """Classify every source path; a ValueError naming a path that is none of the allowed kinds."""

    out = Sources(paths=[Path(p) for p in paths])
    for raw in paths:
        path = Path(raw)
        if path.is_file():
            meta = path.parent / EVALUATION_FILE
            settings = json.loads(meta.read_text()) if meta.is_file() else {}
            out.tables.append({"path": path, "table": read_results(path), "settings": settings})
            continue
        try:
            found = sweep_dirs(path)
        except ValueError:
            raise ValueError(f"{path} is not a results file, a sweep directory (with {SETTINGS_FILE}) or a directory of sweeps") from None
        for d in found:
            runs, candidates, skipped, unfinished = [], [], [], []
            for trial in load_trials(d, unreadable=skipped):  # a corrupt trial is listed, the others reported
                if not trial.finished:
                    unfinished.append(f"{trial.name} ({trial.last.get('env_steps', 0)} of {trial.config.get('steps')} env steps)")
                ckpt = trial.final_checkpoint
                if ckpt is None:
                    skipped.append({"trial": trial.name, "path": str(trial.path), "error": "no checkpoint"})
                    continue
                found = trial_candidates(trial)
                runs.append(found.run)
                candidates.append(found)
            out.sweeps.append(
                {
                    "path": d,
                    "settings": read_settings(d),
                    "runs": runs,
                    "candidates": candidates,
                    "skipped": skipped,
                    "unfinished": unfinished,
                }
            )
    check_training_counts(out)
    return out


def check_training_counts(sources: Sources) -> None:
    """A ValueError naming a scene whose models were trained at more than one vehicle count (the tables and tests would
    pool them): one training count per scene and report. Read from the checkpoints' records, before any evaluation."""
    found: dict[str, dict[int, str]] = {}  # scene -> training count -> the first source with it
    for table in sources.tables:
        rows = table["table"]  # read_results checked its columns
        for (scene, count), _ in rows[rows["method"] != REFERENCE_METHOD].groupby(["scenario", "trained_agent_count"]):
            found.setdefault(str(scene), {}).setdefault(int(count), str(table["path"]))
    for sweep in sources.sweeps:
        for run in sweep["runs"]:
            try:  # the record alone (the evaluation verifies the whole checkpoint, replay included, later)
                meta = json.loads((Path(run.checkpoint) / META_FILE).read_text())
                trained = config_from_dict(meta["scenario"], meta.get("env_config", {}))
                scene, count = trained.scenario, int(trained.num_agents)
            except Exception:  # noqa: BLE001 - an unreadable checkpoint (or an arena's) is the evaluation's to report
                continue
            found.setdefault(scene, {}).setdefault(count, str(sweep["path"]))
    for scene, counts in found.items():
        if len(counts) > 1:
            named = ", ".join(f"{n} vehicles ({where})" for n, where in sorted(counts.items()))
            raise ValueError(
                f"the {scene}'s models were trained at {len(counts)} vehicle counts: {named}; allowed: the sources of one "
                "training count per scene in one report (report each count separately)"
            )


def episode_cache(options: ReportOptions) -> EpisodeCache | None:
    """The report's episode cache (``options.cache``), or None."""
    return None if options.cache is None else EpisodeCache(Path(options.cache))


def evaluate_sources(
    sources: Sources, options: ReportOptions, out: Path, log: Log
) -> tuple[pd.DataFrame, list[dict[str, Any]], dict[str, Any]]:
    """The combined per-episode table (new evaluations written to ``out``), failures and evaluation settings."""

    frames, failures = [t["table"] for t in sources.tables], []
    groups: dict[tuple, list[EvalRun]] = {}
    seen: set[str] = set()
    selections = []
    for sweep in sources.sweeps:
        failures += [{**s, "sweep": str(sweep["path"])} for s in sweep["skipped"]]
        settings = sweep["settings"]
        counts = options.counts or (tuple(settings.get("counts") or ()) if settings.get("experiment") == "generalization" else None)
        n_seeds = options.test_seeds or int(settings.get("test_seeds", 20))
        runs = sweep["runs"]
        if options.select == VALIDATION and sweep["candidates"]:
            runs, chosen, selection_failures = select_checkpoints(
                sweep["candidates"], options.validation_episodes, options.workers, log, episode_cache(options)
            )
            selections.append(chosen.assign(sweep=str(sweep["path"])))
            failures += [{**f, "sweep": str(sweep["path"]), "stage": "validation selection"} for f in selection_failures]
        for run in runs:
            key = str(Path(run.checkpoint).resolve())
            if key not in seen:
                seen.add(key)
                groups.setdefault((counts, n_seeds), []).append(run)
    settings: dict[str, Any] = {"groups": [], "select": options.select}
    # how each source's models were chosen: this report's rule for its sweeps, the recorded one for results tables
    rules = {(t["settings"].get("select", FINAL), t["settings"].get("validation_episodes")) for t in sources.tables}
    if sources.sweeps:
        rules.add((options.select, options.validation_episodes if options.select == VALIDATION else None))
    settings["captions"] = sorted(selection_caption(*rule) for rule in rules)
    if selections:
        pd.concat(selections, ignore_index=True).to_csv(out / SELECTION_FILE, index=False)
        settings["validation_episodes"] = options.validation_episodes
    elif sources.sweeps:  # this report chose final checkpoints: an earlier report's choice in this folder no longer applies
        (out / SELECTION_FILE).unlink(missing_ok=True)
    if groups:
        evaluations = []
        for (counts, n_seeds), runs in groups.items():
            seeds = eval_test_seeds(n_seeds)
            ev = run_evaluation(runs, seeds, counts=counts, workers=options.workers, log=log, cache=episode_cache(options))
            evaluations.append(ev)
            failures += ev.failures
            settings["groups"].append({"runs": len(runs), "counts": counts, "test_seeds": seeds, "workers": options.workers})
        table = pd.concat([e.table for e in evaluations], ignore_index=True)
        wall = sum(e.wall_s for e in evaluations)

        write_results(Evaluation(table, failures, wall), out, {**settings, "command": options.command})
        frames.append(table)
    if not frames or all(f.empty for f in frames):
        names = ", ".join(f["trial"] if "trial" in f else f.get("checkpoint", "?") for f in failures) or "none"
        raise ValueError(f"nothing to report: no episode was evaluated (failed or skipped: {names})")
    combined = pd.concat([f for f in frames if not f.empty], ignore_index=True)
    combined = combined.drop_duplicates(subset=["checkpoint", "scenario", "agent_count", "test_seed"], keep="last")
    return combined.reset_index(drop=True), failures, settings


def with_reference_rows(
    table: pd.DataFrame, root: Path, workers: int, log: Log, cache: EpisodeCache | None = None
) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """``table`` plus the COIN authors' actors on its test seeds for every scene it has at Table 5.1's density (scenes whose
    reference rows it already holds, from an earlier report's results, are not evaluated again), and the failures: a scene
    without actors under ``root`` or whose evaluation failed is named there and left out, the rest of the report goes on."""
    dense = paper_table.at_paper_density(table[table["method"] != REFERENCE_METHOD])
    have = set(table.loc[table["method"] == REFERENCE_METHOD, "scenario"])
    scenes = {str(scene): sorted(int(s) for s in g["test_seed"].unique()) for scene, g in dense.groupby("scenario", sort=True)}
    frames, failures = reference_rows(root, {k: v for k, v in scenes.items() if k not in have}, workers, log, cache=cache)
    if not frames and not failures:
        log("  no scene at Table 5.1's density without its reference rows: the authors' actors are not evaluated")
    return pd.concat([table, *frames], ignore_index=True), failures


def reference_rows(
    root: Path,
    seeds_by_scene: dict[str, list[int]],
    workers: int,
    log: Log,
    backend: str = "native",
    cache: EpisodeCache | None = None,
) -> tuple[list[pd.DataFrame], list[dict[str, Any]]]:
    """The authors' actors' episodes per scene on its test seeds (``backend``: another simulator), and the failures: a scene
    without actors under ``root`` or whose evaluation failed is named (``{"checkpoint", "error"}``) and left out."""
    frames, failures = [], []
    for scene, seeds in sorted(seeds_by_scene.items()):
        try:
            frames.append(test_seed_rows(root, scene, seeds, workers, log, backend, cache=cache))
        except Exception as exc:  # noqa: BLE001 - the models' evaluations are kept; the reference row is named as missing
            failures.append({"checkpoint": f"{REFERENCE_METHOD} ({scene}, {root})", "error": f"{type(exc).__name__}: {exc}"})
            log(f"  the COIN authors' {scene} actors were not evaluated{'' if backend == 'native' else f' on {backend}'}: {exc}")
    return frames, failures


def ordered_labels(labels: Sequence[str], method: str) -> list[str]:
    """Labels with ``method`` (and its variants) first, then the rest in sorted order."""
    uniq = sorted(set(labels))
    first = [x for x in uniq if x == method or x.startswith(f"{method}-")]
    return first + [x for x in uniq if x not in first]


def learning_curves(table: pd.DataFrame, unreadable: list[dict[str, Any]] | None = None) -> pd.DataFrame:
    """Per run (label, seed) the Tune progress rows (env steps, return, train success) next to its checkpoint.

    A ``progress.csv`` that cannot be read is left out and, with ``unreadable``, listed there. A resumed
    trial's file repeats the env steps it ran again after its checkpoint; the last row of each is kept
    (the run that the final checkpoint continues).
    """
    parts = []
    runs = table.drop_duplicates("checkpoint")
    for r in runs.itertuples():
        progress = Path(r.checkpoint).parent / "progress.csv"
        if not progress.is_file():
            continue
        try:
            df = pd.read_csv(progress)
        except (ValueError, OSError, UnicodeDecodeError) as exc:  # pandas' ParserError and EmptyDataError are ValueErrors
            if unreadable is not None:
                unreadable.append({"path": str(progress), "error": f"unreadable progress.csv ({str(exc).splitlines()[0]})"})
            continue
        if "wall_s" not in df.columns and "time_total_s" in df.columns:  # a sweep before trials kept their clocks: Tune's own
            df = df.assign(wall_s=df["time_total_s"])
        cols = [c for c in ("env_steps", "episode_return_mean", "train_success_rate", "cpu_s", "wall_s") if c in df.columns]
        if "env_steps" not in cols:
            continue
        df = df.drop_duplicates("env_steps", keep="last").sort_values("env_steps")
        parts.append(df[cols].assign(label=run_label(r.method, r.variant), seed=r.trained_seed, scenario=r.scenario))
    return pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=["label", "seed", "scenario", "env_steps"])


def training_cost(curves: pd.DataFrame) -> pd.DataFrame:
    """Per (scenario, label) what its trials cost, read off each run's last progress row (:func:`learning_curves`):
    ``trials``, ``env_steps`` per trial (mean), CPU hours per trial (``cpu_h_mean``, ``cpu_h_min``, ``cpu_h_max``) and
    in all (``cpu_h_total``), wall-clock hours in all (``wall_h_total``); NaN where a run recorded no such clock."""
    columns = ["scenario", "label", "trials", "env_steps", "cpu_h_mean", "cpu_h_min", "cpu_h_max", "cpu_h_total", "wall_h_total"]
    if curves.empty:
        return pd.DataFrame(columns=columns)
    last = curves.sort_values("env_steps").groupby(["scenario", "label", "seed"], sort=True).tail(1)
    rows = []
    for (scenario, label), g in last.groupby(["scenario", "label"], sort=True):
        cpu, wall = (g[c] / 3600 if c in g else pd.Series(np.nan, index=g.index) for c in ("cpu_s", "wall_s"))
        rows.append(
            {
                "scenario": scenario,
                "label": label,
                "trials": len(g),
                "env_steps": g["env_steps"].mean(),
                "cpu_h_mean": cpu.mean(),
                "cpu_h_min": cpu.min(),
                "cpu_h_max": cpu.max(),
                "cpu_h_total": cpu.sum() if cpu.notna().all() else np.nan,
                "wall_h_total": wall.sum() if wall.notna().all() else np.nan,
            }
        )
    return pd.DataFrame(rows, columns=columns)


def _hours(value: float) -> str:
    return "-" if pd.isna(value) else f"{value:.2f}"


def write_cost(cost: pd.DataFrame, out: Path) -> list[Path]:
    """``table_cost.csv`` and ``table_cost.md`` (one table per scenario) of :func:`training_cost`; returns their paths."""
    cost.to_csv(out / "table_cost.csv", index=False)
    lines = ["## Training cost: each run's CPU and wall-clock hours, its processes included (the trials' own clocks)", ""]
    for scenario, g in cost.groupby("scenario", sort=True):
        lines += [
            f"### {scenario}",
            "",
            "| Method | trials | env steps per trial | CPU hours per trial: mean (range) | CPU hours in all | wall-clock hours in all |",
            "|---|---:|---:|---:|---:|---:|",
        ]
        for r in g.itertuples():
            lines.append(
                f"| {r.label} | {r.trials} | {r.env_steps:,.0f} | {_hours(r.cpu_h_mean)} ({_hours(r.cpu_h_min)}–{_hours(r.cpu_h_max)}) | "
                f"{_hours(r.cpu_h_total)} | {_hours(r.wall_h_total)} |"
            )
        total = g[["cpu_h_total", "wall_h_total"]].sum(min_count=len(g))
        lines += [f"| all | {g['trials'].sum()} | | | {_hours(total['cpu_h_total'])} | {_hours(total['wall_h_total'])} |", ""]
    (out / "table_cost.md").write_text("\n".join(lines))
    return [out / "table_cost.csv", out / "table_cost.md"]


def trajectory_plot(checkpoint: str, seed: int, path: Path, title: str) -> Path:
    """One deterministic test episode of a checkpoint drawn with every vehicle's path and outcome points."""

    config = scenario_of(Path(checkpoint))
    if config.backend != "native":
        raise ValueError(f"trajectory plots need the native backend; {checkpoint} uses {config.backend!r}")
    env, trace = DrivingEnv(config), EpisodeTrace()
    m = run_episode(env, checkpoint_policy(Path(checkpoint)), seed, config.force_stop_factor * config.horizon + 1, trace=trace)
    full = f"{title}: success {m['success_rate']:.2f}, {int(m['num_crashed'])} crashes, {int(m['num_out_of_road'])} off-road"
    return plot_trajectories(trace, env.sim.map, path, title=full, width=6.0, dpi=90)


def latent_figure(table: pd.DataFrame, method: str, options: ReportOptions, path: Path, log: Log) -> Path:
    """t-SNE of CVAE latents of ``method``'s lowest-seed model per scenario (App. B.1)."""

    rows = statistics.main_rows(statistics.at_training_count(table))
    rows = rows[rows["method"] == method].sort_values("trained_seed")
    if rows.empty:
        raise ValueError(f"no {method} model in the results")
    rng = np.random.default_rng(0)
    samples: dict[str, np.ndarray] = {}
    for scenario, g in rows.groupby("scenario", sort=True):
        checkpoint = g["checkpoint"].iloc[0]
        lat = collect_latents(Path(checkpoint), eval_test_seeds(options.tsne_episodes))
        if len(lat.z) < 10:
            log(f"  latents: only {len(lat.z)} pairs in {scenario}; skipped")
            continue
        pick = rng.choice(len(lat.z), size=min(options.tsne_samples, len(lat.z)), replace=False)
        samples[scenario] = lat.z[np.sort(pick)]
        log(f"  latents: {len(pick)} of {len(lat.z)} pairs from {checkpoint}")
    if not samples:
        raise ValueError("too few latent pairs (< 10) in every scenario")
    perp = lambda n: float(min(30.0, max(2.0, (n - 1) / 3.0)))  # noqa: E731 - perplexity must stay below n
    embeddings, clusters = {}, {}
    for name, z in samples.items():
        embeddings[name] = tsne(z, perplexity=perp(len(z)), seed=0)
        clusters[name] = kmeans(z, min(6, len(z)), seed=0)[0]
    joint = np.concatenate(list(samples.values()))
    joint_names = np.concatenate([np.full(len(z), name) for name, z in samples.items()])
    joint_y = tsne(joint, perplexity=perp(len(joint)), seed=0) if len(samples) > 1 else embeddings[joint_names[0]]
    return plots.plot_latent_tsne(embeddings, clusters, joint_y, joint_names, path)


def attention_figure(table: pd.DataFrame, method: str, scenario: str, options: ReportOptions, out: Path, log: Log) -> Path:
    """Where the GAT of ``method``'s lowest-seed model on ``scenario`` looks (``attention.py``), on the t-SNE's test episodes:
    ``attention_<scenario>.png`` and the mean share per distance bin, partners and other neighbours, in ``attention_<scenario>.csv``."""

    rows = statistics.main_rows(statistics.at_training_count(table))
    rows = rows[(rows["method"] == method) & (rows["scenario"] == scenario)].sort_values(["trained_seed", "test_seed"])
    if rows.empty:
        raise ValueError(f"no {method} model on {scenario} in the results")
    first = rows.iloc[0]
    sample = attention.collect_attention(Path(first["checkpoint"]), eval_test_seeds(options.tsne_episodes))
    summary = attention.conflict_summary(sample.edges)
    summary.to_csv(out / f"attention_{scenario}.csv", index=False)
    pairs = sample.edges[sample.edges["distance"] < 15.0].groupby("conflict")["share"].mean()
    log(
        f"  attention: {len(sample.edges)} edges of seed {first['trained_seed']}'s model; mean share within 15 m: crossing partners "
        f"{pairs.get(True, float('nan')):.3f}, other neighbours {pairs.get(False, float('nan')):.3f} (1 = uniform)"
    )
    title = f"{scenario}, {method} (seed {first['trained_seed']}): the Q1 critic's GAT attention, layer 2, ego row"
    return plots.plot_attention(sample.edges, summary, sample.snapshot, sample.road_map, out / f"attention_{scenario}.png", title)


def _attempt(name: str, figures: dict[str, Any], log: Log, fn: Callable[[], Path]) -> None:
    """Draw one figure; record its path or the reason it could not be drawn."""
    try:
        figures[name] = fn()
        log(f"  wrote {figures[name].name}")
    except (ValueError, KeyError, OSError, RuntimeError) as exc:
        figures[name] = f"not drawn: {exc}"
        log(f"  {name}: not drawn ({exc})")


def build_report(
    paths: Sequence[Path] | Sources, out: Path, options: ReportOptions | None = None, log: Log = print, shown_as: Path | None = None
) -> dict[str, Any]:
    """Evaluate the sources (paths, or what :func:`gather` made of them) and write every table, figure, the marl-eval
    JSON and report.html into ``out``.

    ``shown_as``: where ``out`` will be once complete (the CLI builds a report in a staging directory,
    :func:`~coin_app.evaluation.outputs.staged_outputs`): the paths logged and returned name it. A report
    redrawn from one results table (no sweep) keeps that table's evaluation record beside it
    (``evaluation.json``, ``selection.csv``).
    """

    options = options or ReportOptions()
    options.check()
    t0 = time.perf_counter()
    sources = paths if isinstance(paths, Sources) else gather(paths)
    out = Path(out)
    shown = Path(shown_as) if shown_as is not None else out
    out.mkdir(parents=True, exist_ok=True)
    n_runs = sum(len(s["runs"]) for s in sources.sweeps)
    log(f"report: {len(sources.sweeps)} sweeps ({n_runs} models) and {len(sources.tables)} results tables -> {shown}")
    if not sources.sweeps and len(sources.tables) == 1:  # a redraw: the table's record of how it was evaluated stays with it
        record_dir = Path(sources.tables[0]["path"]).parent
        for name in (EVALUATION_FILE, SELECTION_FILE):
            if (record_dir / name).is_file() and not (out / name).exists():
                shutil.copy2(record_dir / name, out / name)
    for sweep in sources.sweeps:
        if sweep["unfinished"]:
            log(f"  note: unfinished trials in {sweep['path']}, their newest checkpoints are evaluated: {', '.join(sweep['unfinished'])}")
    table, failures, eval_settings = evaluate_sources(sources, options, out, log)
    if options.reference_actors is not None:
        table, reference_failures = with_reference_rows(table, Path(options.reference_actors), options.workers, log, episode_cache(options))
        failures += reference_failures
    table.to_csv(out / "results.csv", index=False)  # new evaluations and read tables together
    table = table.assign(label=[run_label(m, v) for m, v in zip(table["method"], table["variant"])])
    colors = plots.label_colors(ordered_labels(list(table["label"]) + list(table["method"]), options.method))
    trained = statistics.at_training_count(table)

    main = statistics.main_rows(trained)
    main_summary = statistics.rank_marks(statistics.summarize(main))
    models = "; ".join(eval_settings["captions"])
    caption = f"Results at the training agent count ({models}): mean (std) over test episodes"
    files = tables.write_tables(main_summary, out, "table_main", caption)
    dense = paper_table.at_paper_density(main)
    beside = paper_table.beside_paper(statistics.summarize(dense)) if len(dense) else pd.DataFrame()
    if len(beside):
        files += paper_table.write_beside(beside, out, f"Beside COIN's Table 5.1 ({models}): ours (std over test episodes) / the paper's")
    if (out / SELECTION_FILE).is_file() and options.select == VALIDATION:
        files.append(out / SELECTION_FILE)
    ablation = statistics.ablation_rows(trained, options.method)
    ablation_summary = statistics.rank_marks(statistics.summarize(ablation)) if len(ablation) else None
    if ablation_summary is not None:
        files += tables.write_tables(ablation_summary, out, "table_ablation", f"Ablations of {options.method}", "Variant")
    learned = main[main["method"] != REFERENCE_METHOD]  # the authors' actors are a reference row, not a baseline
    stats = statistics.paired_tests_all_units(learned, options.method, alpha=options.alpha)
    stats.to_csv(out / "stats.csv", index=False)
    files += [out / "stats.csv", write_marl_eval(table, out / "marl_eval.json")]
    transfer = None
    if options.transfer:
        transfer_rows, transfer_failures = evaluate_transfer(table, options, out, log)
        failures += transfer_failures
        transfer = transfer_table(table, transfer_rows)
        files += [out / "transfer_results.csv", *write_transfer(transfer, out, options.transfer)]

    figures: dict[str, Any] = {}
    unreadable: list[dict[str, Any]] = []  # files read after the evaluation that could not be read (named, not fatal)
    curves = learning_curves(table, unreadable)
    for u in unreadable:
        log(f"  unreadable, left out of the learning curves: {u['path']}: {u['error']}")
    cost = training_cost(curves)
    if len(cost):
        files += write_cost(cost, out)
    for scenario in sorted(table["scenario"].unique()):
        s_sum = main_summary[main_summary["scenario"] == scenario]
        _attempt(f"radar_{scenario}", figures, log, lambda s=s_sum, n=scenario: plots.plot_radar(s, out / f"radar_{n}.png", n, colors))
        s_rows = table[table["scenario"] == scenario]
        _attempt(
            f"generalization_{scenario}",
            figures,
            log,
            lambda r=s_rows, n=scenario: plots.plot_generalization(r, out / f"generalization_{n}.png", n, colors),
        )
        s_curves = curves[curves["scenario"] == scenario]
        _attempt(
            f"learning_curves_{scenario}",
            figures,
            log,
            lambda c=s_curves, n=scenario: _curves(c, out / f"learning_curves_{n}.png", n, colors),
        )
        for x in plots.curve_axes(s_curves):  # compute efficiency beside sample efficiency
            _attempt(
                f"learning_curves_{x}_{scenario}",
                figures,
                log,
                lambda c=s_curves, n=scenario, x=x: plots.plot_learning_curves(c, out / f"learning_curves_{x}_{n}.png", n, colors, x),
            )
        for method, g in learned[learned["scenario"] == scenario].groupby("method", sort=True):
            first = g.sort_values(["trained_seed", "test_seed"]).iloc[0]
            _attempt(
                f"trajectories_{scenario}_{method}",
                figures,
                log,
                lambda f=first, n=scenario, m=method: trajectory_plot(
                    f["checkpoint"],
                    int(f["test_seed"]),
                    out / f"trajectories_{n}_{m}.png",
                    f"{n}, {m} (seed {f['trained_seed']}, test seed {f['test_seed']})",
                ),
            )
    _attempt("latent_tsne", figures, log, lambda: latent_figure(table, options.method, options, out / "latent_tsne.png", log))
    for scenario in sorted(set(learned["scenario"])):
        _attempt(f"attention_{scenario}", figures, log, lambda n=scenario: attention_figure(table, options.method, n, options, out, log))

    context = {
        "options": asdict(options),
        "sources": [str(p) for p in sources.paths],
        "sweeps": [{"path": str(s["path"]), "settings": s["settings"], "unfinished": s["unfinished"]} for s in sources.sweeps],
        "tables": [{"path": str(t["path"]), "settings": t["settings"]} for t in sources.tables],
        "evaluation": eval_settings,
        "failures": failures + unreadable,
    }
    html = write_html(out / "report.html", table, main_summary, ablation_summary, stats, figures, context, transfer, beside, cost)
    summary = {
        "out": str(shown),
        "episodes": len(table),
        "models": int(table["checkpoint"].nunique()),
        "failures": failures,
        "unreadable": unreadable,
        "files": [str(shown / Path(f).relative_to(out)) for f in [*files, html]],
        "figures": {k: str(shown / v.relative_to(out)) if isinstance(v, Path) else str(v) for k, v in figures.items()},
        "success": {f"{r.scenario}/{r.label}": r.mean for r in main_summary[main_summary["metric"] == "success_rate"].itertuples()},
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    return summary


def evaluate_transfer(table: pd.DataFrame, options: ReportOptions, out: Path, log: Log) -> tuple[pd.DataFrame, list[dict[str, Any]]]:
    """The main table's models on ``options.transfer`` at their training count; the episodes (also in ``out``) and failures.

    The test seeds are the first ``transfer_test_seeds`` of the native ones, so every episode has its native partner.
    """
    trained = statistics.main_rows(statistics.at_training_count(table)).drop_duplicates("checkpoint")
    trained = trained[trained["method"] != REFERENCE_METHOD]  # the authors' actors are not checkpoints (evaluate-reference)
    steps = trained["trained_env_steps"] if "trained_env_steps" in trained else pd.Series(np.nan, index=trained.index)
    runs = [
        EvalRun(r.method, r.variant, int(r.trained_seed), r.checkpoint, None if pd.isna(n) else int(n))
        for r, n in zip(trained.itertuples(), steps)
    ]
    seeds = sorted(int(s) for s in table["test_seed"].unique())[: options.transfer_test_seeds]
    ev = run_evaluation(runs, seeds, workers=options.workers, log=log, backend=options.transfer, cache=episode_cache(options))
    frames, failures = [ev.table], list(ev.failures)
    if options.reference_actors is not None:  # the authors' actors on the same seeds, on the other simulator too
        scenes = {str(scene): seeds for scene in set(table.loc[table["method"] == REFERENCE_METHOD, "scenario"])}
        more, missing = reference_rows(
            Path(options.reference_actors), scenes, options.workers, log, options.transfer, episode_cache(options)
        )
        frames, failures = frames + more, failures + missing
    other = pd.concat([f for f in frames if not f.empty], ignore_index=True) if len(frames) > 1 else ev.table
    other.to_csv(out / "transfer_results.csv", index=False)
    return other, [{**f, "backend": options.transfer} for f in failures]


def _curves(curves: pd.DataFrame, path: Path, scenario: str, colors: dict[str, str]) -> Path:
    if curves.empty:
        raise ValueError("no Tune progress.csv next to any checkpoint of this scenario")
    return plots.plot_learning_curves(curves, path, scenario, colors)
