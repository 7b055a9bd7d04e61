"""Trained policies that ship inside the package, loaded by name without Ray or torch.

``shipped/catalog.json`` is their one record: per name, the file (relative to ``shipped/``), the
algorithm, scenario and vehicle count it was trained on, the protocol, the commit and command that
made it, and its test figures. ``coin_app.inference.load_policy(name)`` loads one;
``python -m coin_app policies`` lists them.
"""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

SHIPPED_DIR = Path(__file__).resolve().parent / "shipped"
CATALOG = SHIPPED_DIR / "catalog.json"
REQUIRED = ("file", "algo", "scenario", "num_agents", "protocol", "commit", "command", "test", "description")


@cache
def shipped_policies() -> dict[str, dict[str, Any]]:
    """Name -> record of every shipped policy, in the catalog's order; a ValueError names a record that lacks a field."""
    records = json.loads(CATALOG.read_text())
    for name, record in records.items():
        missing = [k for k in REQUIRED if k not in record]
        if missing:
            raise ValueError(f"shipped policy {name!r} lacks {', '.join(missing)} in {CATALOG.name}")
    return records


def shipped_path(name: str) -> Path:
    """The file of shipped policy ``name``; a ValueError lists the shipped names for an unknown one."""
    records = shipped_policies()
    if name not in records:
        raise ValueError(f"no shipped policy {name!r}; allowed: {', '.join(records)} (or a policy file path)")
    return SHIPPED_DIR / records[name]["file"]


def is_shipped_name(source: Any) -> bool:
    """Whether ``source`` (a string or path) is a shipped policy's name and no file or directory of that name exists here."""
    return isinstance(source, (str, Path)) and str(source) in shipped_policies() and not Path(source).exists()


def resolve(source: Any) -> Any:
    """``source`` with a shipped policy's name replaced by its file's path; anything else as given."""
    return shipped_path(str(source)) if is_shipped_name(source) else source
