"""Evaluated episodes kept on disk, so that an interrupted or repeated evaluation does again only what it has not done.

One entry is one task of :func:`~coin_app.evaluation.protocol.run_evaluation`: one run (method, variant, trained seed,
trained env steps, checkpoint) over one grid (test seeds, agent counts, scenarios, backend), stored as one JSON file
as soon as the task ends. An entry is found again by the model's *content* (the SHA-256 of every file in its checkpoint's
manifest, or of the file of a one-file model), not its path, so a report moved to another machine or directory keeps its
episodes; and it is used only if the code that decides an episode (:func:`episode_code`) is byte for byte the code that
wrote it: after any change there the task runs again, and its new entry replaces the old one. A checkpoint directory
without a manifest is never cached.
"""

from __future__ import annotations

import fnmatch
import hashlib
import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from coin_app.algorithms.checkpoint_files import MANIFEST_FILE
from coin_app.evaluation.outputs import write_text_atomic

FORMAT, VERSION = "coin_app.episodes", 1
DEFAULT_DIR = "episodes"  # the report's cache: this folder of its output directory
PACKAGE = Path(__file__).resolve().parents[1]  # coin_app/
# what decides an episode's outcome: the simulators with their map data, the env adapters, the policies' code and
# loading, the episode loop and its metrics (not the report's tables and figures, the training loop or the CLI)
CODE_PARTS = (
    "sim",
    "backends",
    "adapters",
    "algorithms",
    "inference",
    "evaluation/evaluate.py",
    "evaluation/metrics.py",
    "evaluation/policies.py",
    "evaluation/protocol.py",
    "evaluation/reference.py",
)
DATA_SUFFIXES = (".json", ".npz")  # data files covered beside the code (map geometry, dynamics fits)
# never run by an evaluation (tests/test_algorithm_conformance.py traces one per algorithm): how models learn and are
# configured for training, and the models themselves (an entry is keyed by its model's own content)
NOT_EPISODE_CODE = (
    "algorithms/gradient_step.py",
    "algorithms/*/learner.py",
    "algorithms/*/losses.py",
    "algorithms/td3/buffer.py",
    "algorithms/td3/connector.py",
    "algorithms/td3/transitions.py",
    "algorithms/copo/advantages.py",
    "algorithms/nav_ppo/warm_start.py",
    "inference/shipped/*",
    "inference/weights/*",
)


def episode_code(package: Path = PACKAGE) -> list[Path]:
    """The files :func:`code_fingerprint` covers, in :data:`CODE_PARTS`' order: the ``.py`` and data files of :data:`CODE_PARTS` under
    ``package`` except :data:`NOT_EPISODE_CODE` (``fnmatch`` patterns of paths relative to ``package``) and caches."""
    files = []
    for part in CODE_PARTS:
        path = package / part
        files += sorted(path.rglob("*")) if path.is_dir() else [path]
    return [
        f
        for f in files
        if f.is_file()
        and f.suffix in (".py", *DATA_SUFFIXES)
        and "__pycache__" not in f.parts
        and not any(fnmatch.fnmatchcase(f.relative_to(package).as_posix(), pattern) for pattern in NOT_EPISODE_CODE)
    ]


def code_fingerprint(package: Path = PACKAGE) -> str:
    """SHA-256 (first 16 hex digits) of the paths and bytes of every file of :func:`episode_code` under ``package``."""
    digest = hashlib.sha256()
    for f in episode_code(package):
        digest.update(f.relative_to(package).as_posix().encode() + b"\0" + f.read_bytes() + b"\0")
    return digest.hexdigest()[:16]


def checkpoint_identity(checkpoint: Path) -> str | None:
    """SHA-256 of the checkpoint's manifest's file list (every file's size and SHA-256), or of the file itself where the
    model is one file (the COIN authors' actors); None for a directory without a readable manifest."""
    if Path(checkpoint).is_file():
        return hashlib.sha256(Path(checkpoint).read_bytes()).hexdigest()
    try:
        files = json.loads((Path(checkpoint) / MANIFEST_FILE).read_text())["files"]
    except (OSError, ValueError, KeyError, TypeError):
        return None
    return hashlib.sha256(json.dumps(files, sort_keys=True).encode()).hexdigest()


class EpisodeCache:
    """The entries under ``root`` (created on the first store) written by the code of ``code`` (default: this code's)."""

    def __init__(self, root: Path, code: str | None = None) -> None:
        self.root = Path(root)
        self.code = code if code is not None else code_fingerprint()

    def _entry(self, run: Any, seeds: Sequence[int], counts: Sequence[int] | None, scenarios: Sequence[str] | None, backend: str | None):
        """(the entry's path, its grid record), or None for a checkpoint without a manifest."""
        identity = checkpoint_identity(Path(run.checkpoint))
        if identity is None:
            return None
        grid = {
            "method": run.method,
            "variant": run.variant,
            "trained_seed": int(run.trained_seed),
            "trained_env_steps": run.trained_env_steps,
            "checkpoint": identity,
            "seeds": [int(s) for s in seeds],
            "counts": None if counts is None else sorted(int(c) for c in counts),
            "scenarios": None if scenarios is None else list(scenarios),
            "backend": backend,
        }
        key = hashlib.sha256(json.dumps(grid, sort_keys=True).encode()).hexdigest()[:16]
        variant = "" if run.variant == "default" else f"-{run.variant}"
        name = f"{run.method}{variant}-s{int(run.trained_seed)}-{Path(run.checkpoint).name}-{backend or 'own'}-{key}.json"
        return self.root / name, grid

    def load(
        self, run: Any, seeds: Sequence[int], counts: Sequence[int] | None, scenarios: Sequence[str] | None, backend: str | None
    ) -> list[dict[str, Any]] | None:
        """The task's rows (their ``checkpoint`` the run's path), or None: not stored, stored by other code, or unreadable."""
        entry = self._entry(run, seeds, counts, scenarios, backend)
        if entry is None or not entry[0].is_file():
            return None
        try:
            record = json.loads(entry[0].read_text())
            if record.get("format") != FORMAT or record.get("version") != VERSION or record.get("grid") != entry[1]:
                return None
            if record.get("code") != self.code:
                return None
            columns = record["columns"]
            return [{**dict(zip(columns, values)), "checkpoint": str(run.checkpoint)} for values in record["rows"]]
        except (OSError, ValueError, KeyError, TypeError):
            return None

    def store(
        self,
        run: Any,
        seeds: Sequence[int],
        counts: Sequence[int] | None,
        scenarios: Sequence[str] | None,
        backend: str | None,
        rows: Sequence[dict[str, Any]],
    ) -> Path | None:
        """Write the task's rows (atomically; the path column left out) and return the entry's path (None: not cacheable)."""
        entry = self._entry(run, seeds, counts, scenarios, backend)
        if entry is None or not rows:
            return None
        path, grid = entry
        columns = [c for c in rows[0] if c != "checkpoint"]
        record = {
            "format": FORMAT,
            "version": VERSION,
            "code": self.code,
            "grid": grid,
            "columns": columns,
            "rows": [[r[c] for c in columns] for r in rows],
        }
        self.root.mkdir(parents=True, exist_ok=True)
        return write_text_atomic(path, json.dumps(record, separators=(",", ":")) + "\n")
