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

SETTINGS_FILE = "coin_sweep.json"


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
        from tuning.experiment import trial_name

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


def read_settings(experiment_dir: Path) -> dict[str, Any]:
    """The sweep's ``coin_sweep.json``; a ValueError naming the directory if it is not a coin_app sweep."""
    path = Path(experiment_dir) / SETTINGS_FILE
    if not path.is_file():
        raise ValueError(f"{experiment_dir} is not a coin_app sweep directory (no {SETTINGS_FILE})")
    return json.loads(path.read_text())


def load_trials(experiment_dir: Path) -> list[TrialRecord]:
    """Every trial directory of a sweep, sorted by trial name."""
    read_settings(experiment_dir)
    trials = []
    for params in sorted(Path(experiment_dir).glob("*/params.json")):
        d = params.parent
        results_file = d / "result.json"
        lines = results_file.read_text().splitlines() if results_file.is_file() else []
        results = [json.loads(line) for line in lines if line.strip()]
        checkpoints = sorted(
            (c for c in d.glob("checkpoint_*") if (c / "coin_app.json").is_file()), key=lambda c: int(c.name.split("_")[-1])
        )
        trials.append(TrialRecord(d, json.loads(params.read_text()), results, checkpoints))
    return sorted(trials, key=lambda t: t.name)
