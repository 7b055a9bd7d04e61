"""Run, resume and summarize a sweep (``python -m coin_app sweep``).

* Everything is checked before any work: the experiment name, scenario, methods and seeds,
  every trial's full config (``training.build_config``), the storage, the cluster address
  (a TCP probe with a short timeout, so an unreachable head fails fast) and that a fresh
  sweep does not overwrite an existing one (``--resume`` continues it instead).
* A fresh sweep writes ``coin_sweep.json`` (what was asked) into its experiment directory and
  runs ``tune.Tuner(CoinTrial, ...)`` with Tune's progress table, a checkpoint every
  ``checkpoint_every`` iterations and at the end, the newest ``keep`` kept per trial.
* ``restart`` (``--resume --restart METHOD ...``) reruns these methods' trials from scratch, for a
  method changed after its trials ran: their directories move to ``replaced/<time>/``.
* ``resume=True`` runs ``Tuner.restore(..., resume_unfinished=True, resume_errored=True)``:
  finished trials stay as they are, interrupted or errored ones continue from their newest
  checkpoint; this works after ``kill -9`` of the driver because Tune's experiment state
  and every checkpoint are on disk (state saved at least every ``TUNE_GLOBAL_CHECKPOINT_S``,
  set to 5 s here unless the environment sets it).
* The generalization experiment then evaluates every final checkpoint at each agent count of
  its grid into ``generalization.csv``.
* GPU learners: ``--set num_learners=1 num_gpus_per_learner=1`` (``coin_app.algorithms.registry.LEARNER_KEYS``)
  makes every trial reserve one GPU for its learner (``trainable.trial_resources``); on a local
  Ray without that many GPUs the sweep is refused before any trial starts (a cluster may still
  start GPU nodes, so there Tune waits for them).
"""

from __future__ import annotations

import importlib.util
import json
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import partial
from pathlib import Path
from typing import Any

import ray
from ray import tune

from coin_app.algorithms import registry
from coin_app.algorithms.checkpoint_files import code_version
from coin_app.evaluation.generalization import evaluate_at_counts
from coin_app.evaluation.limits import CONNECT_TIMEOUT_S, check_timeout
from coin_app.evaluation.outputs import OutputLock, write_text_atomic
from coin_app.evaluation.sweep_results import SETTINGS_FILE, load_trials, read_settings, trial_name
from coin_app.training import check_address
from tuning import get_experiment
from tuning.experiment import PER_METHOD, expand_grid, is_per_method, trial_layers
from tuning.progress_csv import AlignedCSVLogger
from tuning.reaper import clear_mark, start_reaper
from tuning.trainable import CoinTrial, build_trial_config, trial_gpus

EXPERIMENT_STATE_GLOB = "experiment_state-*.json"
RESOLVED = "resolved"  # coin_sweep.json: every trial's resolved settings (trial name -> key -> value), what it runs with
ACCEPTED = "accepted_changes"  # coin_sweep.json: the setting changes a --resume --accept-changes continued with
RESTART_PENDING = "restart_pending"  # coin_sweep.json: methods of a --restart begun and not yet run (a plain --resume is refused)
LIVE_STATE_S = 30.0  # an experiment state written more recently than this: the sweep's driver may still be running
REPLACED_DIR = "replaced"  # restarted trials' earlier directories: replaced/<time>/<trial dir> (out of the report's reach)


def storage_root(storage: str | None) -> str:
    """An absolute storage path or a URI (``s3://...``, ``gs://...``); default ``runs/sweeps``."""
    storage = storage or "runs/sweeps"
    if "://" in storage:
        return storage
    return str(Path(storage).expanduser().resolve())


def experiment_path(storage: str, name: str) -> Path:
    """The local experiment directory (URIs are not checked locally)."""
    return Path(storage) / name


def validate_trials(space: dict[str, Any]) -> list[dict[str, Any]]:
    """Every trial config of the param space, each built once so a bad value is refused before any work."""

    trials = expand_grid(space)
    for t in trials:
        build_trial_config(t)
    return trials


def tune_space(space: dict[str, Any]) -> dict[str, Any]:
    """The param space as Tune takes it: each :func:`~tuning.experiment.per_method` value as a ``tune.sample_from`` of the
    trial's method (Tune resolves the grid first, as ``expand_grid`` does)."""
    return {k: tune.sample_from(partial(_of_method, v[PER_METHOD])) if is_per_method(v) else v for k, v in space.items()}


def _of_method(values: dict[str, Any], config: dict[str, Any]) -> Any:
    """The value of the trial's method (``config``: the trial's config, its grid resolved)."""
    return values[config["algo"]]


def check_local_gpus(needed: float, started_here: bool) -> None:
    """A ValueError when each trial needs more GPUs than the local Ray has (a local Ray cannot add any)."""
    have = float(ray.cluster_resources().get("GPU", 0))
    if needed > have:
        if started_here:
            ray.shutdown()
        raise ValueError(
            f"each trial reserves {needed:g} GPU(s) (num_gpus_per_learner), but the local Ray has {have:g}; allowed: "
            f"num_gpus_per_learner <= {have:g} here, or --address of a cluster with GPU workers (docs/cluster.md)"
        )


def sweep_name(name: str | None, experiment: str, scenario: str, scale: str) -> str:
    """The experiment directory's name: ``name``, or ``<experiment>-<scenario>[-<scale>]``."""
    return name or f"{experiment}-{scenario}" + ("" if scale == "paper" else f"-{scale}")


def run_sweep(experiment: str, scenario: str = "intersection", scale: str = "paper", **kwargs: Any) -> dict[str, Any]:
    """Run (or resume) one sweep with its local experiment directory locked to this driver (see :func:`_run_sweep`)."""
    tracking_callbacks(kwargs.get("wandb_project"), kwargs.get("mlflow_uri"), experiment)  # the refusals that need no directory
    get_experiment(experiment).scale(scale)
    check_timeout(kwargs.get("connect_timeout", CONNECT_TIMEOUT_S), "--connect-timeout")
    root = storage_root(kwargs.get("storage"))
    if "://" in root:  # a remote store: Tune's own
        return _run_sweep(experiment, scenario, scale, **kwargs)
    path = experiment_path(root, sweep_name(kwargs.get("name"), experiment, scenario, scale))
    with OutputLock(path, kwargs.get("command"), "the sweep directory", "--name or --storage") as lock:
        if lock.stale_note():
            kwargs.get("log", print)(str(lock.stale_note()))
        return _run_sweep(experiment, scenario, scale, **kwargs)


def resolved_settings(trials: list[dict[str, Any]]) -> dict[str, dict[str, Any]]:
    """Every trial's settings as this code resolves them (``registry.merged_settings`` of its layers), by trial name."""
    out = {}
    for t in trials:
        merged = {s.key: s.value for s in registry.merged_settings(t["algo"], t["scenario"], trial_layers(t))}
        out[trial_name(t)] = json.loads(json.dumps(merged | {"steps": int(t["steps"])}, default=repr))
    return out


def protocol_changes(recorded: dict[str, dict[str, Any]], now: dict[str, dict[str, Any]]) -> dict[str, str]:
    """Setting key -> ``"old -> new (k trial(s))"`` for every key whose resolved value differs between the two records."""
    changed: dict[str, list[tuple[Any, Any]]] = {}
    for trial, settings in now.items():
        before = recorded.get(trial)
        if before is None:
            continue
        for key in sorted(before.keys() | settings.keys()):
            if before.get(key, "absent") != settings.get(key, "absent"):
                changed.setdefault(key, []).append((before.get(key, "absent"), settings.get(key, "absent")))
    return {k: f"{v[0][0]!r} -> {v[0][1]!r} ({len(v)} trial(s))" for k, v in changed.items()}


def check_protocol(
    path: Path, settings: dict[str, Any], restart: tuple[str, ...], accept: bool, command: str | None, log: Callable[[str], None]
) -> dict[str, Any]:
    """Refuse to resume a sweep whose trials this code would run with other settings than recorded (restarted methods aside),
    unless ``accept``: then the changes are recorded in ``coin_sweep.json``; returns the settings as written."""
    configs = [t["config"] for t in _trial_states(path)[2]]
    now = resolved_settings(configs)
    kept = {trial_name(c) for c in configs if c["algo"] not in restart}  # restarted trials run this code's settings afresh
    recorded = settings.get(RESOLVED)
    if recorded is None:
        log(f"note: {path} predates recorded trial settings; this code's are recorded now and checked on the next --resume")
    else:
        changes = protocol_changes(recorded, {k: v for k, v in now.items() if k in kept})
        if changes and not accept:
            listed = "; ".join(f"{k}: {v}" for k, v in changes.items())
            raise ValueError(
                f"{path}: this code resolves other settings than the sweep ran with ({listed}); allowed: --accept-changes to "
                f"continue with them (recorded), --restart METHOD to rerun a method's trials, or the code the sweep started with "
                f"({settings.get('code_version', 'unknown')})"
            )
        if changes:
            log(f"--accept-changes: the trials continue with {len(changes)} changed setting(s): {', '.join(changes)} (recorded)")
            entry = {"time": time.strftime("%Y-%m-%d %H:%M:%S"), "command": command, "code_version": code_version(), "changes": changes}
            settings = settings | {ACCEPTED: [*settings.get(ACCEPTED, []), entry]}
    settings = settings | {RESOLVED: {**(recorded or {}), **now}}
    write_settings(path, settings)
    return settings


def _run_sweep(
    experiment: str,
    scenario: str = "intersection",
    scale: str = "paper",
    methods: tuple[str, ...] | None = None,
    seeds: tuple[int, ...] | None = None,
    steps: int | None = None,
    overrides: dict[str, Any] | None = None,
    storage: str | None = None,
    name: str | None = None,
    address: str | None = None,
    max_concurrent: int | None = None,
    resume: bool = False,
    restart: tuple[str, ...] = (),
    num_cpus: int | None = None,
    log: Callable[[str], None] = print,
    command: str | None = None,
    wandb_project: str | None = None,
    mlflow_uri: str | None = None,
    accept_changes: bool = False,
    connect_timeout: float = CONNECT_TIMEOUT_S,
) -> dict[str, Any]:
    """Run (or resume) one sweep; returns its summary (experiment directory, trials, generalization CSV).

    A local sweep directory has one driver (:class:`~coin_app.evaluation.outputs.OutputLock`). It
    records every trial's resolved settings (``RESOLVED``); ``resume`` refuses when this code
    resolves other settings for a trial that is not restarted (:func:`protocol_changes`), unless
    ``accept_changes``, which continues and records the changes (``ACCEPTED``).

    ``restart`` (with ``resume``): these methods' trials run again from scratch (``restart_trials``).
    ``wandb_project`` / ``mlflow_uri``: also log every trial's results with Tune's W&B / MLflow
    logger callbacks (the package must be installed; refused with one line before any work if not).
    """

    extra_loggers = tracking_callbacks(wandb_project, mlflow_uri, name or experiment)
    exp = get_experiment(experiment)
    sc = exp.scale(scale, scenario)
    if max_concurrent is not None and max_concurrent < 1:
        raise ValueError(f"bad --max-concurrent {max_concurrent}; allowed: an integer >= 1")
    if steps is not None and steps < 1:
        raise ValueError(f"bad --steps {steps}; allowed: an integer >= 1")
    root, name = storage_root(storage), sweep_name(name, experiment, scenario, scale)
    path = experiment_path(root, name)
    local = "://" not in root
    gpus = 0.0  # GPUs each trial reserves (fresh sweeps with learner settings)
    if resume:
        if local and not list(path.glob(EXPERIMENT_STATE_GLOB)):
            raise ValueError(f"nothing to resume at {path}: no Tune experiment state there (start it without --resume)")
        settings = read_settings(path) if local else {}
        if settings and settings["experiment"] != experiment:
            raise ValueError(f"{path} holds experiment {settings['experiment']!r}, not {experiment!r}")
        pending = settings.get(RESTART_PENDING) or []
        if pending and not set(pending) <= set(restart):
            raise ValueError(
                f"{path} has an unfinished --restart of {' '.join(pending)}; allowed: --resume --restart {' '.join(pending)} (finishes it)"
            )
        if restart:
            check_restart(path, restart, settings, local)
        if local:
            settings = check_protocol(path, settings, restart, accept_changes, command, log)
        space = None
    else:
        if restart:
            raise ValueError(f"--restart {' '.join(restart)} without --resume; allowed: --restart only with --resume")
        if accept_changes:
            raise ValueError("--accept-changes without --resume; allowed: --accept-changes only with --resume")
        if local and path.exists() and any(path.iterdir()):
            raise ValueError(f"experiment directory {path} already exists; continue it with --resume or pick another --name")
        space = exp.param_space(scenario, scale, methods, seeds, steps, overrides)
        trials = validate_trials(space)
        gpus = max(map(trial_gpus, trials)) if any(k in (overrides or {}) for k in registry.LEARNER_KEYS) else 0.0
        settings = {
            "experiment": experiment,
            "scenario": scenario,
            "scale": scale,
            "methods": list(methods or exp.methods),
            "seeds": list(seeds or sc.seeds),
            "variants": list(exp.variant_names(scale)),
            "steps": space["steps"],
            "overrides": overrides or {},
            "checkpoint_every": sc.checkpoint_every,
            "keep": sc.keep,
            "counts": list(sc.counts.get(scenario, ())),
            "test_seeds": sc.test_seeds,
            "trials": len(trials),
            "started": time.strftime("%Y-%m-%d %H:%M:%S"),
            "command": command,
            "code_version": code_version(),
            RESOLVED: resolved_settings(trials),
        }
        log(f"sweep {experiment} on {scenario} ({scale} scale): {len(trials)} trials -> {path}")
        if gpus:
            log(f"each trial reserves {gpus:g} GPU(s) for its learner")
    check_address(address, connect_timeout)
    os.environ.setdefault("TUNE_GLOBAL_CHECKPOINT_S", "5")
    # the frequent state saves above are deliberate (resume after kill -9); Tune's warning about them is noise
    os.environ.setdefault("TUNE_WARN_EXCESSIVE_EXPERIMENT_CHECKPOINT_SYNC_THRESHOLD_S", "0")
    local_ray = address == "local" or (address is None and not os.environ.get("RAY_ADDRESS"))
    started_here = not ray.is_initialized()
    if started_here:
        if local_ray:
            start_reaper()  # this sweep's Ray processes go with its driver, even after kill -9 (tuning/reaper.py)
            try:
                ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, configure_logging=False)
            finally:
                clear_mark()
        else:  # an explicit cluster, or the one a Ray job runs in (RAY_ADDRESS)
            ray.init(address=address)
    if local_ray and gpus:
        check_local_gpus(gpus, started_here)
    if resume:
        if restart:
            moved, replaced = restart_trials(path, restart, command)
            log(f"restarting {len(moved)} trial(s) of {', '.join(restart)} from scratch; their earlier directories -> {replaced}")
        log(f"resuming {path}: finished trials stay, the others continue from their newest checkpoint")
        tuner = tune.Tuner.restore(
            str(path), trainable=CoinTrial, resume_unfinished=True, resume_errored=not restart, restart_errored=bool(restart)
        )
    else:
        if local:
            path.mkdir(parents=True, exist_ok=True)
            write_settings(path, settings)
        tuner = tune.Tuner(
            CoinTrial,
            param_space=tune_space(space),
            tune_config=tune.TuneConfig(
                max_concurrent_trials=max_concurrent,
                trial_name_creator=lambda t: trial_name(t.config),
                trial_dirname_creator=lambda t: f"{trial_name(t.config)}_{t.trial_id}",
            ),
            run_config=tune.RunConfig(
                name=name,
                storage_path=root,
                checkpoint_config=tune.CheckpointConfig(
                    checkpoint_frequency=sc.checkpoint_every,
                    checkpoint_at_end=True,
                    num_to_keep=sc.keep,
                    checkpoint_score_attribute=sc.keep_best,
                    checkpoint_score_order="max",
                ),
                failure_config=tune.FailureConfig(max_failures=1),
                callbacks=[AlignedCSVLogger(), *extra_loggers],  # progress.csv keeps one column order across restores
            ),
        )
    t0 = time.perf_counter()
    try:
        with terminate_as_interrupt():  # SIGTERM stops Tune as Ctrl-C does: experiment state saved, trials resumable
            grid = tuner.fit()
    finally:
        if resume and restart:
            tidy_restarted(path, moved, replaced)
            write_settings(path, {k: v for k, v in read_settings(path).items() if k != RESTART_PENDING})
        if started_here:  # no Ray process of this sweep outlives it (raylet, GCS, dashboard and runtime-env agents)
            ray.shutdown()
    summary: dict[str, Any] = {"experiment_dir": str(path), "wall_s": round(time.perf_counter() - t0, 1), "errors": grid.num_errors}
    if not local:
        return summary
    settings = read_settings(path)
    records = load_trials(path)
    summary["trials"] = [
        {
            "name": r.name,
            "finished": r.finished,
            "env_steps": r.last.get("env_steps", 0),
            "train_success_rate": r.last.get("train_success_rate", float("nan")),
            "eval_success_rate": r.last.get("eval/success_rate", float("nan")),
            "checkpoint": str(r.final_checkpoint) if r.final_checkpoint else None,
        }
        for r in records
    ]
    if settings["experiment"] == "generalization" and settings["counts"]:
        done = [r for r in records if r.finished and r.final_checkpoint]
        if done:
            summary["generalization_csv"] = str(write_generalization(path, records=done, log=log))
    return summary


def newest_state(path: Path) -> Path:
    """The experiment-state file Tune restores from: the newest by name (Tune's own rule)."""
    return max(path.glob(EXPERIMENT_STATE_GLOB), key=lambda p: p.name)


def _trial_states(path: Path) -> tuple[Path, dict[str, Any], list[dict[str, Any]]]:
    """The newest Tune experiment-state file of a local sweep, its content and each trial's decoded state."""
    state_file = newest_state(path)
    state = json.loads(state_file.read_text())
    return state_file, state, [json.loads(trial_json) for trial_json, _ in state["trial_data"]]


def check_restart(path: Path, methods: tuple[str, ...], settings: dict[str, Any], local: bool) -> None:
    """Refuse a ``--restart`` that names a method the sweep lacks, needs a remote sweep edited, or would restart others' errored trials."""
    if not local:
        raise ValueError(f"--restart on {path}; allowed: a sweep in a local directory (it edits Tune's experiment state there)")
    age = time.time() - newest_state(path).stat().st_mtime
    if age < LIVE_STATE_S:
        raise ValueError(
            f"--restart on {path}: its experiment state was written {age:.0f} s ago, so its sweep may still be running; "
            f"allowed: --restart once that sweep's driver has stopped (state older than {LIVE_STATE_S:g} s)"
        )
    swept = settings.get("methods", [])
    for m in methods:
        if m not in swept:
            raise ValueError(f"--restart {m}: not a method of {path}; allowed: {', '.join(swept)}")
    others = [t["relative_logdir"] for t in _trial_states(path)[2] if t["status"] == "ERROR" and t["config"]["algo"] not in methods]
    if others:
        raise ValueError(
            f"--restart with errored trials of other methods ({', '.join(others)}); allowed: resume them first without --restart"
        )


def write_settings(path: Path, settings: dict[str, Any]) -> None:
    """Write a sweep's ``coin_sweep.json`` atomically."""
    write_text_atomic(path / SETTINGS_FILE, json.dumps(settings, indent=2))


def restart_trials(path: Path, methods: tuple[str, ...], command: str | None = None) -> tuple[list[str], Path]:
    """Mark these methods' trials for a restart from scratch and move their directories aside; their names and where they went.

    Tune restarts errored trials from scratch (``Tuner.restore(..., restart_errored=True)``, a new
    trial id and directory), so the trials of ``methods`` are marked errored in the newest
    experiment state (written atomically) and their directories go to ``replaced/<time>/``, where
    nothing is lost and ``load_trials`` (the report) does not look. For a method rerun after a fix.
    ``coin_sweep.json`` records the restart (``restarts``) and marks it pending until the run ends,
    so that a crash in between is finished by the same command, not by a plain ``--resume``.
    """
    settings = read_settings(path)
    stamp = time.strftime("%Y%m%d-%H%M%S")
    record = {"methods": list(methods), "time": stamp, "command": command}
    write_settings(path, settings | {RESTART_PENDING: list(methods), "restarts": [*settings.get("restarts", []), record]})
    state_file, state, trials = _trial_states(path)
    names = []
    for i, trial in enumerate(trials):
        if trial["config"]["algo"] in methods:
            trial["status"] = "ERROR"
            state["trial_data"][i][0] = json.dumps(trial, indent=2)
            names.append(trial["relative_logdir"])
    tmp = state_file.with_name(state_file.name + ".tmp")
    tmp.write_text(json.dumps(state))
    os.replace(tmp, state_file)
    dest = path / REPLACED_DIR / stamp
    for name in names:
        if (path / name).is_dir():
            dest.mkdir(parents=True, exist_ok=True)
            os.replace(path / name, dest / name)
    return names, dest


def tidy_restarted(path: Path, names: list[str], dest: Path) -> None:
    """Move restarted trials' old directories that Tune re-created during the run (empty, or re-synced) to ``dest``."""
    for name in names:
        old = path / name
        if not old.is_dir():
            continue
        if not any(old.iterdir()):
            old.rmdir()
        else:
            dest.mkdir(parents=True, exist_ok=True)
            os.replace(old, dest / f"{name}.resynced")


def tracking_callbacks(wandb_project: str | None, mlflow_uri: str | None, experiment_name: str) -> list[Any]:
    """Tune's W&B and MLflow logger callbacks for the flags given; a ValueError if a package is not installed."""
    out: list[Any] = []
    if wandb_project is not None:
        if importlib.util.find_spec("wandb") is None:
            raise ValueError(f"--wandb {wandb_project} needs the wandb package; allowed: pip install wandb, or leave out --wandb")
        from ray.air.integrations.wandb import WandbLoggerCallback  # optional: imports wandb

        # the logging actors get only the API key from this environment: WANDB_MODE (offline, disabled) is passed on
        mode = {"mode": os.environ["WANDB_MODE"]} if os.environ.get("WANDB_MODE") else {}
        out.append(WandbLoggerCallback(project=wandb_project, **mode))  # each trial's run files: <trial dir>/wandb
    if mlflow_uri is not None:
        if importlib.util.find_spec("mlflow") is None:
            raise ValueError(f"--mlflow {mlflow_uri} needs the mlflow package; allowed: pip install mlflow, or leave out --mlflow")
        from ray.air.integrations.mlflow import MLflowLoggerCallback  # optional: imports mlflow

        out.append(MLflowLoggerCallback(tracking_uri=mlflow_uri, experiment_name=experiment_name))
    return out


@contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """While inside (main thread only), SIGTERM is turned into SIGINT, which Tune handles by stopping gracefully."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: os.kill(os.getpid(), signal.SIGINT))
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def write_generalization(
    path: Path,
    counts: list[int] | None = None,
    test_seeds: int | None = None,
    records: list[Any] | None = None,
    log: Callable[[str], None] = print,
) -> Path:
    """Evaluate every finished trial's final checkpoint at each agent count; write ``generalization.csv`` in ``path``."""

    settings = read_settings(path)
    counts = list(counts or settings["counts"])
    test_seeds = int(test_seeds or settings["test_seeds"])
    records = records if records is not None else [r for r in load_trials(path) if r.finished and r.final_checkpoint]
    if not records:
        raise ValueError(f"no finished trial with a checkpoint in {path}; nothing to evaluate")
    runs = [
        {"method": r.config["algo"], "variant": r.config["variant"], "seed": r.config["seed"], "checkpoint": r.final_checkpoint}
        for r in records
    ]
    log(f"generalization: {len(runs)} checkpoints x agent counts {counts} x {test_seeds} test seeds")
    table = evaluate_at_counts(runs, counts, test_seeds, log)
    out = Path(path) / "generalization.csv"
    write_text_atomic(out, table.to_csv(index=False))
    return out
