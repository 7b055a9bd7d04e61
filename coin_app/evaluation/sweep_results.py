"""Reading a sweep's directory without Ray: its settings, and per trial the config, last result and checkpoints.

Layout (Tune's, under ``<storage>/<name>/``): ``coin_sweep.json`` (what was asked: experiment,
scenario, scale, methods, ...), Tune's ``experiment_state-*.json``, and one directory per trial
with ``params.json``, ``result.json`` (one JSON line per iteration), ``progress.csv`` and
``checkpoint_<k>/`` directories (coin_app checkpoints).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from coin_app.algorithms.checkpoint_files import META_FILE

SETTINGS_FILE = "coin_sweep.json"


def trial_name(config: dict[str, Any]) -> str:
    """``<algo>-<variant>-s<seed>`` (``<algo>-s<seed>`` for the default variant)."""
    variant = "" if config["variant"] == "default" else f"-{config['variant']}"
    return f"{config['algo']}{variant}-s{config['seed']}"


@dataclass
class TrialRecord:
    """One trial directory of a sweep."""

    path: Path
    config: dict[str, Any]
    results: list[dict[str, Any]]
    checkpoints: list[Path]

    @property
    def name(self) -> str:
        """``<algo>[-<variant>]-s<seed>``."""
        return trial_name(self.config)

    @property
    def last(self) -> dict[str, Any]:
        """The last reported result ({} before the first)."""
        return self.results[-1] if self.results else {}

    @property
    def finished(self) -> bool:
        """Whether the trial reached its env-step budget."""
        return bool(self.last.get("done")) or self.last.get("env_steps", 0) >= self.config.get("steps", float("inf"))

    @property
    def final_checkpoint(self) -> Path | None:
        """The newest checkpoint, or None."""
        return self.checkpoints[-1] if self.checkpoints else None

    def checkpoint_env_steps(self, checkpoint: Path) -> int | None:
        """The env steps ``checkpoint`` was saved at: its metadata's, else the last result's for the final one, else None."""
        try:
            steps = json.loads((Path(checkpoint) / META_FILE).read_text()).get("env_steps")
        except (OSError, ValueError):  # unreadable metadata: the evaluation names the checkpoint
            steps = None
        if steps is None and Path(checkpoint) == self.final_checkpoint and "env_steps" in self.last:
            steps = self.last["env_steps"]
        return None if steps is None else int(steps)


def read_settings(experiment_dir: Path) -> dict[str, Any]:
    """The sweep's ``coin_sweep.json``; a ValueError naming the directory if it is not a coin_app sweep."""
    path = Path(experiment_dir) / SETTINGS_FILE
    if not path.is_file():
        raise ValueError(f"{experiment_dir} is not a coin_app sweep directory (no {SETTINGS_FILE})")
    return json.loads(path.read_text())


def sweep_dirs(path: Path) -> list[Path]:
    """``path`` if it is a sweep directory, else the sweeps directly under it; a ValueError naming a path that holds none."""
    path = Path(path)
    found = [path] if (path / SETTINGS_FILE).is_file() else sorted(p.parent for p in path.glob(f"*/{SETTINGS_FILE}"))
    if not path.is_dir() or not found:
        raise ValueError(f"{path} is not a sweep directory (with {SETTINGS_FILE}) or a directory of sweeps")
    return found


def _read_json_lines(path: Path) -> list[dict[str, Any]]:
    """The complete JSON lines of ``result.json``; a trailing line still being written is left out."""
    if not path.is_file():
        return []
    lines = [line for line in path.read_text().splitlines() if line.strip()]
    results = []
    for i, line in enumerate(lines):
        try:
            results.append(json.loads(line))
        except json.JSONDecodeError as err:
            if i == len(lines) - 1:  # Tune appends one line per iteration; the last may be mid-write
                break
            raise ValueError(f"{path} line {i + 1} is not valid JSON ({err.msg}); the trial's results are corrupt") from err
    return results


def load_trials(experiment_dir: Path, live: bool = False, unreadable: list[dict[str, Any]] | None = None) -> list[TrialRecord]:
    """Every trial directory of a sweep, sorted by trial name.

    ``live=True`` is for a sweep that may be running: a trial whose ``params.json`` is still
    being written is left out instead of refused. ``unreadable``: a list that collects the trials
    whose files are corrupt (``{"trial", "path", "error"}``) instead of refusing the whole sweep.
    """
    read_settings(experiment_dir)
    trials = []
    for params in sorted(Path(experiment_dir).glob("*/params.json")):
        d = params.parent
        try:
            config = json.loads(params.read_text())
        except (json.JSONDecodeError, UnicodeDecodeError) as err:
            if live:
                continue
            error = f"{params} is not valid JSON ({getattr(err, 'msg', err)}); the trial's config is missing or corrupt"
            if unreadable is None:
                raise ValueError(error) from err
            unreadable.append({"trial": d.name, "path": str(d), "error": error})
            continue
        checkpoints = sorted((c for c in d.glob("checkpoint_*") if (c / META_FILE).is_file()), key=lambda c: int(c.name.split("_")[-1]))
        try:
            results = _read_json_lines(d / "result.json")
        except (ValueError, UnicodeDecodeError) as err:
            if unreadable is None:
                raise
            unreadable.append({"trial": d.name, "path": str(d), "error": str(err)})
            continue
        trials.append(TrialRecord(d, config, results, checkpoints))
    return sorted(trials, key=lambda t: t.name)
