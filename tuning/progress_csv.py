"""``progress.csv`` with one column order across restores: Tune's CSV logger, aligned to the file's own header.

Tune's ``CSVLoggerCallback`` takes its columns from the first result it logs in a process. After
a sweep ``--resume`` the first result of a resumed trial lists its keys in another order (the
learner's metrics arrive in another order after a restore), so the new rows landed under the
old header's wrong columns. :class:`AlignedCSVLogger` reads the header of an existing file and
writes every row in that order. A result with keys the header lacks (CIG-TD3's learner metrics
after the warm-up, a periodic evaluation) rewrites the file once with those columns added at the
end, so no metric is dropped and no row is shifted. Passing it to ``RunConfig(callbacks=...)``
replaces Tune's own CSV logger (Tune adds its default only when none is given).
"""

from __future__ import annotations

import csv
import os
from pathlib import Path
from typing import Any

from ray.tune.logger import CSVLoggerCallback
from ray.tune.utils import flatten_dict

PROGRESS_FILE = "progress.csv"


def read_table(path: Path) -> tuple[list[str], list[dict[str, str]]]:
    """(header, rows) of a CSV file; ([], []) when it is missing or empty."""
    if not path.is_file() or path.stat().st_size == 0:
        return [], []
    with open(path, newline="") as f:
        reader = csv.DictReader(f)
        return list(reader.fieldnames or []), list(reader)


def write_table(path: Path, columns: list[str], rows: list[dict[str, Any]]) -> None:
    """Write a CSV file atomically (a temporary sibling renamed into place)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "w", newline="") as f:
        writer = csv.DictWriter(f, fieldnames=columns, extrasaction="ignore")
        writer.writeheader()
        writer.writerows(rows)
        f.flush()
        os.fsync(f.fileno())
    os.replace(tmp, path)


def aligned_row(columns: list[str], result: dict[str, Any]) -> tuple[list[str], dict[str, Any]]:
    """(columns, row): the existing ``columns`` with the result's new keys appended in their order, and the row to write."""
    new = [k for k in result if k not in columns]
    return columns + new, {k: result.get(k, "") for k in columns + new}


class AlignedCSVLogger(CSVLoggerCallback):
    """Tune's CSV logger whose rows follow the existing header of ``progress.csv`` (see module doc)."""

    def log_trial_result(self, iteration: int, trial: Any, result: dict) -> None:
        """Append one result in the file's column order, adding columns (one rewrite) for keys it has not seen."""
        if trial not in self._trial_files:
            self._setup_trial(trial)
        flat = flatten_dict({k: v for k, v in result.items() if k != "config"}, delimiter="/")
        path = Path(trial.local_path, PROGRESS_FILE)
        writer = self._trial_csv[trial]
        columns = list(writer.fieldnames) if writer else read_table(path)[0]
        columns, row = aligned_row(columns, flat)
        if writer is None or len(columns) != len(writer.fieldnames):
            self._trial_files[trial].close()
            header, rows = read_table(path)
            if header != columns:  # a new file, or new columns: rewrite it with the full header
                write_table(path, columns, rows)
            self._trial_files[trial] = path.open("a", newline="")
            self._trial_csv[trial] = csv.DictWriter(self._trial_files[trial], fieldnames=columns, extrasaction="ignore")
        self._trial_csv[trial].writerow(row)
        self._trial_files[trial].flush()
