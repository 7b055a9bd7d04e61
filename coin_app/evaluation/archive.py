"""A sweep's finished trials as a small directory that a repository can hold, and that ``report`` reads as it reads the sweep.

A dense trial costs about an hour of CPU and its checkpoints hold its replay (hundreds of MB):
neither survives a change of machine. :func:`archive_sweep` keeps, per finished trial, what the
report reads: ``params.json``, ``result.json`` and ``progress.csv`` without Tune's bookkeeping
(host, PID, dates, the config repeated per line), and two of its checkpoints as actor-only copies
(metadata and the deterministic actor as TorchScript, ``ACTOR_FILE``), or for the methods named in
``modules`` as module-only copies (the shared module with its critics, for the report's latent
figure): the final one and the one best on the validation seeds (:func:`~coin_app.evaluation.selection.select_checkpoints`, the
report's ``--select validation``), with every kept checkpoint's validation score in
``selection.csv``. Layout: ``<out>/<sweep name>/`` with the sweep's ``coin_sweep.json``,
:data:`ARCHIVE_FILE` and one ``<algo>[-<variant>]-s<seed>/`` per trial. Archiving again adds the
trials finished since; a trial already archived stays as it is.
"""

from __future__ import annotations

import csv
import io
import json
import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coin_app.algorithms.checkpoint_files import (
    ACTOR_FILE,
    ACTOR_ONLY,
    META_FILE,
    MODULE_ONLY,
    MODULE_PATH,
    PARTIAL_SUFFIX,
    code_version,
    verify,
    write_manifest,
)
from coin_app.algorithms.checkpoints import export_actor, export_metadata, load_module
from coin_app.algorithms.choices import ALGORITHM_NAMES
from coin_app.evaluation.outputs import fsync_dir, write_text_atomic
from coin_app.evaluation.selection import SELECTION_FILE, select_checkpoints, trial_candidates
from coin_app.evaluation.sweep_results import SETTINGS_FILE, TrialRecord, load_trials, read_settings
from coin_app.inference import export_policy

ARCHIVE_FILE = "coin_archive.json"  # beside coin_sweep.json: what was archived, from where, by which code
BOOKKEEPING = ("config", "date", "timestamp", "pid", "hostname", "node_ip", "trial_id", "time_since_restore", "iterations_since_restore")
RESOLVED = "resolved"  # coin_sweep.json: every trial's resolved settings (tuning.sweep writes it)
# what a sweep run records of itself: two runs of one protocol (other seeds, another machine) differ only in these
RUN_KEYS = ("seeds", "trials", "started", "command", RESOLVED, "accepted_changes", "restart_pending", "restarts")
STORAGE_MARK = "<storage>"  # stands for the sweep's storage directory in the archived settings' command (no machine paths)
STATUS_FILE = "table.md"  # in the archive directory: every archived trial's cost and validation scores (archive_table)


def is_archive(path: Path) -> bool:
    """Whether ``path`` is an archived sweep (it has :data:`ARCHIVE_FILE`)."""
    return (Path(path) / ARCHIVE_FILE).is_file()


def _without_bookkeeping(line: dict[str, Any]) -> dict[str, Any]:
    """A result line without Tune's per-line bookkeeping (:data:`BOOKKEEPING`)."""
    return {k: v for k, v in line.items() if k not in BOOKKEEPING}


def _progress_without_bookkeeping(path: Path) -> str:
    """``progress.csv``'s text without the :data:`BOOKKEEPING` columns ("" when there is none)."""
    if not path.is_file():
        return ""
    rows = list(csv.reader(io.StringIO(path.read_text())))
    if not rows:
        return ""
    keep = [i for i, name in enumerate(rows[0]) if name not in BOOKKEEPING]
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerows([[row[i] for i in keep if i < len(row)] for row in rows])
    return out.getvalue()


def actor_only_copy(checkpoint: Path, dest: Path) -> Path:
    """Write ``checkpoint``'s metadata and its evaluation actor (TorchScript, as ``export`` writes it) to ``dest``, with a
    manifest of its own (``"contents": "actor"``); the critics, replay and optimizer stay behind, so it cannot resume."""
    meta = verify(checkpoint)
    actor, _, extra = export_actor(load_module(checkpoint))
    dest.mkdir(parents=True)
    export_policy(actor, dest / ACTOR_FILE, "torchscript", meta=export_metadata(meta, extra, Path(checkpoint).name))
    shutil.copy2(Path(checkpoint) / META_FILE, dest / META_FILE)
    write_manifest(dest, meta, contents=ACTOR_ONLY)
    return dest


def module_only_copy(checkpoint: Path, dest: Path) -> Path:
    """Copy ``checkpoint``'s metadata and shared module (actor and critics) to ``dest``, with a manifest of its own
    (``"contents": "module"``); the replay, optimizer and env-runner state stay behind, so it cannot resume."""
    meta = verify(checkpoint)
    shutil.copytree(Path(checkpoint).joinpath(*MODULE_PATH), dest.joinpath(*MODULE_PATH))
    shutil.copy2(Path(checkpoint) / META_FILE, dest / META_FILE)
    write_manifest(dest, meta, contents=MODULE_ONLY)
    return dest


def archive_trial(
    trial: TrialRecord, dest: Path, validation_episodes: int, log: Callable[[str], None], module: bool = False
) -> dict[str, Any]:
    """Write one finished trial's archive to ``dest`` (which must not exist), whole or not at all; returns its record.

    ``module``: module-only copies of the two checkpoints (critics included) instead of actor-only ones."""
    partial = dest.with_name("." + dest.name + PARTIAL_SUFFIX)
    shutil.rmtree(partial, ignore_errors=True)
    partial.mkdir(parents=True)
    final = trial.final_checkpoint
    assert final is not None  # archive_sweep archives trials with a checkpoint only
    cfg = trial.config
    chosen, table, failures = select_checkpoints([trial_candidates(trial)], validation_episodes, log=log)
    if failures or not chosen:
        raise ValueError(
            f"{trial.name}: a checkpoint failed its validation evaluation ({failures[:1]}); allowed: a trial whose checkpoints load"
        )
    selected = Path(chosen[0].checkpoint)
    for checkpoint in sorted({selected, final}, key=lambda c: int(c.name.split("_")[-1])):
        (module_only_copy if module else actor_only_copy)(checkpoint, partial / checkpoint.name)
    table.assign(checkpoint=[Path(c).name for c in table["checkpoint"]]).to_csv(partial / SELECTION_FILE, index=False)
    (partial / "params.json").write_text(json.dumps(cfg, indent=2, sort_keys=True))
    (partial / "result.json").write_text("".join(json.dumps(_without_bookkeeping(r)) + "\n" for r in trial.results))
    (partial / "progress.csv").write_text(_progress_without_bookkeeping(trial.path / "progress.csv"))
    partial.rename(dest)
    fsync_dir(dest.parent)
    return {
        "source": trial.path.name,
        "final": final.name,
        "selected": selected.name,
        "contents": MODULE_ONLY if module else ACTOR_ONLY,
        "kept": [c.name for c in trial.checkpoints],
        "validation_episodes": validation_episodes,
        "env_steps": int(trial.last.get("env_steps", 0)),
        "cpu_s": trial.last.get("cpu_s"),
        "archived": time.strftime("%Y-%m-%d %H:%M:%S"),
        "code_version": code_version(),
    }


def _scrubbed(settings: dict[str, Any], storage: Path) -> dict[str, Any]:
    """The sweep's settings with its storage directory in the command replaced by :data:`STORAGE_MARK`."""
    command = settings.get("command")
    if not isinstance(command, str):
        return settings
    for form in {str(storage), str(storage.resolve())}:
        command = command.replace(form, STORAGE_MARK)
    return settings | {"command": command}


def not_ready(trial: TrialRecord) -> str | None:
    """Why a trial cannot be archived yet (None: it can): unfinished, or its final checkpoint not yet saved whole (Tune
    saves it after the last result is written, so a running sweep's finished trial may lag it by a moment)."""
    steps = int(trial.last.get("env_steps", 0))
    if not trial.finished:
        return f"{steps} of {trial.config.get('steps')} env steps"
    final = trial.final_checkpoint
    saved = None if final is None else trial.checkpoint_env_steps(final)
    if saved is None or saved < steps:
        return f"finished at {steps} env steps, its final checkpoint not saved yet"
    try:
        verify(final)
    except ValueError:
        return f"finished at {steps} env steps, its final checkpoint being written"
    return None


def merged_settings(earlier: dict[str, Any], now: dict[str, Any], dest: Path, sweep: Path) -> dict[str, Any]:
    """An archive's settings with a further run of the same protocol (e.g. the remaining seeds on another machine) added:
    the seeds and resolved trial settings joined, the first run's record kept. A ValueError in one line when the two differ in
    anything but what a run records of itself (:data:`RUN_KEYS`), or resolve one trial's settings differently."""
    keys = (earlier.keys() | now.keys()) - set(RUN_KEYS)
    differ = sorted(k for k in keys if earlier.get(k) != now.get(k))
    both = earlier.get(RESOLVED, {}).keys() & now.get(RESOLVED, {}).keys()
    differ += sorted(f"{RESOLVED}[{t}]" for t in both if earlier[RESOLVED][t] != now[RESOLVED][t])
    if differ:
        raise ValueError(
            f"{dest} archives another sweep than {sweep} ({', '.join(differ[:4])} differ); allowed: runs of the same sweep "
            "settings and code, or another --out"
        )
    resolved = {**earlier.get(RESOLVED, {}), **now.get(RESOLVED, {})}
    seeds = sorted({*earlier.get("seeds", []), *now.get("seeds", [])})
    return earlier | {"seeds": seeds, RESOLVED: resolved, "trials": len(resolved)}


def archive_sweep(
    sweep: Path, out: Path, validation_episodes: int, modules: tuple[str, ...] = (), log: Callable[[str], None] = print
) -> dict[str, Any]:
    """Archive a sweep's finished trials under ``out/<sweep name>/``; returns the archive's record (:data:`ARCHIVE_FILE`).

    ``validation_episodes``: validation seeds per kept checkpoint for the selection; ``modules``: the methods whose
    checkpoints are archived with their critics. Refused in one line
    before any write: a bad ``validation_episodes``, a path that is not a sweep, an ``out`` inside the sweep,
    and an existing archive of another protocol under the same name (:func:`merged_settings`; a run of the same one,
    e.g. the remaining seeds on another machine, joins it). Unfinished
    trials, and trials without a checkpoint, are named and left out; they are added by a later run.
    """
    sweep, out = Path(sweep), Path(out)
    if isinstance(validation_episodes, bool) or not isinstance(validation_episodes, int) or validation_episodes < 1:
        raise ValueError(f"bad --validation-episodes {validation_episodes!r}; allowed: an integer >= 1")
    unknown = sorted(set(modules) - set(ALGORITHM_NAMES))
    if unknown:
        raise ValueError(f"bad --modules {' '.join(unknown)}; allowed: methods among {', '.join(ALGORITHM_NAMES)}")
    settings = read_settings(sweep)
    if out.resolve().is_relative_to(sweep.resolve()):
        raise ValueError(f"bad --out {out}: inside the sweep {sweep} it archives; allowed: a directory outside it")
    dest = out / sweep.resolve().name
    settings = _scrubbed(settings, sweep.resolve().parent)
    record: dict[str, Any] = {"trials": {}, "sources": []}
    source = {k: settings.get(k) for k in ("started", "command", "code_version")}
    if (dest / SETTINGS_FILE).is_file():
        record = json.loads((dest / ARCHIVE_FILE).read_text())
        settings = merged_settings(json.loads((dest / SETTINGS_FILE).read_text()), settings, dest, sweep)
    if source not in record["sources"]:
        record["sources"].append(source)
    trials = load_trials(sweep, live=True)  # the sweep may be running: a trial being created is left for the next run
    added, left_out = [], []
    dest.mkdir(parents=True, exist_ok=True)
    write_text_atomic(dest / SETTINGS_FILE, json.dumps(settings, indent=2))
    for trial in trials:
        if trial.name in record["trials"] and (dest / trial.name).is_dir():
            continue
        why = not_ready(trial)
        if why:
            left_out.append(f"{trial.name} ({why})")
            continue
        shutil.rmtree(dest / trial.name, ignore_errors=True)  # a trial dir without its record: an interrupted archive
        entry = archive_trial(trial, dest / trial.name, validation_episodes, log, module=trial.config["algo"] in modules)
        record["trials"][trial.name] = entry
        added.append(trial.name)
        write_text_atomic(dest / ARCHIVE_FILE, json.dumps(record, indent=2, sort_keys=True))
        log(f"  {trial.name}: final {entry['final']}, validation-selected {entry['selected']} -> {dest / trial.name}")
    write_text_atomic(dest / ARCHIVE_FILE, json.dumps(record, indent=2, sort_keys=True))
    size = sum(p.stat().st_size for p in dest.rglob("*") if p.is_file())
    log(f"archive {dest}: {len(added)} trial(s) added, {len(record['trials'])} in all, {size / 1e6:.1f} MB")
    if left_out:
        log(f"  not archived (unfinished or without a checkpoint): {', '.join(left_out)}")
    return record | {"path": str(dest), "added": added, "left_out": left_out, "bytes": size}


def archive_table(out: Path) -> str:
    """Markdown of every trial archived under ``out`` (sweeps in name order, trials in seed order): env steps, CPU hours,
    the final and the validation-selected checkpoints' validation success (``selection.csv``), and per method the mean
    and range of the selected ones. Validation seeds only: the test seeds are the report's."""
    rows, by_method = [], {}
    for record_file in sorted(Path(out).glob(f"*/{ARCHIVE_FILE}")):
        trials = json.loads(record_file.read_text())["trials"]
        for name, entry in sorted(trials.items(), key=lambda kv: (kv[0].rsplit("-s", 1)[0], int(kv[0].rsplit("-s", 1)[1]))):
            with open(record_file.parent / name / SELECTION_FILE, newline="") as f:
                table = list(csv.DictReader(f))
            score = {row["checkpoint"]: (int(row["trained_env_steps"]), float(row["validation_success"])) for row in table}
            steps, selected = score[entry["selected"]]
            cpu = "" if entry.get("cpu_s") is None else f"{entry['cpu_s'] / 3600:.3f}"
            rows.append(f"| {name} | {entry['env_steps']:,} | {cpu} | {score[entry['final']][1]:.3f} | {steps:,}: {selected:.3f} |")
            by_method.setdefault(name.rsplit("-s", 1)[0], []).append(selected)
    head = [
        "| trial | env steps | CPU hours | final checkpoint's validation success | selected checkpoint (env steps): validation success |",
        "|---|---:|---:|---:|---:|",
    ]
    means = ["| method | trials | selected checkpoints' validation success: mean (range) |", "|---|---:|---:|"]
    means += [f"| {m} | {len(v)} | {sum(v) / len(v):.3f} ({min(v):.3f}–{max(v):.3f}) |" for m, v in by_method.items()]
    return "\n".join(["# Archived trials", "", *head, *rows, "", *means, ""]) + "\n"
