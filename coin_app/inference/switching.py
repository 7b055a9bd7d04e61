"""The run-time switching policy of the seed-2 paper (§III-C): short-range inside R_switch, long-range outside.

``pi_t = pi_short if d_t < R_switch else pi_long`` with ``d_t`` the vehicle's distance to its
target, read from the arena observation (its first two numbers are the target position in
the vehicle frame, in units of 25 m). Both policies act on one batch each per call, so all
vehicles' actions still cost two forward passes at most.

A pair file (``.json``, format ``coin_app.switching.v1``) names the two policy sources
(exported ``.npz`` files or checkpoint directories, paths relative to the file) and the radius.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.sim.arena.observation import POSITION_SCALE

FORMAT = "coin_app.switching.v1"


def target_distance(obs: np.ndarray) -> np.ndarray:
    """Distance (N,) of each vehicle to its target from arena observations (N, 6 + 7 k [+ 44])."""
    obs = np.asarray(obs, np.float32)
    return np.linalg.norm(obs[:, 0:2], axis=1) * POSITION_SCALE


PAPER_OBSERVATION = {"observed_entities": 1, "candidate_features": False}  # the arena keys of an observation's layout


def observation_options(policy: Any) -> dict[str, Any] | None:
    """The arena observation keys ``policy`` was trained with (its metadata's env config; ``PAPER_OBSERVATION`` where unset),
    None if unknown."""
    meta = getattr(policy, "meta", None)
    if not isinstance(meta, dict) or meta.get("scenario") != "arena":
        return None
    env = meta.get("env_config", {})
    return {key: type(default)(env.get(key, default)) for key, default in PAPER_OBSERVATION.items()}


def observed_entities(policy: Any) -> int | None:
    """The arena entities ``policy`` was trained to observe (its metadata's ``observed_entities``, 1 if unset), None if unknown."""
    options = observation_options(policy)
    return None if options is None else options["observed_entities"]


def _describe(options: dict[str, Any]) -> str:
    """``"6 entities"`` or ``"6 entities and the candidate features"``."""
    return f"{options['observed_entities']} entities" + (" and the candidate features" if options["candidate_features"] else "")


def check_arena_part(role: str, part: Any, scenario: str | None = None) -> None:
    """Refuse a part of a pair that was trained on a driving scenario (``scenario``, else its metadata's; unknown: accepted)."""
    meta = getattr(part, "meta", None)
    scenario = scenario or (meta.get("scenario") if isinstance(meta, dict) else None)
    if scenario is not None and scenario != "arena":
        raise ValueError(f"the {role}-range policy was trained on {scenario!r}, not the arena; allowed: two arena policies (nav_ppo)")


class SwitchingPolicy:
    """Short-range policy inside ``switch_radius`` of the target, long-range outside."""

    def __init__(self, long: Callable[[np.ndarray], np.ndarray], short: Callable[[np.ndarray], np.ndarray], switch_radius: float):
        if not switch_radius > 0:
            raise ValueError(f"bad switch_radius {switch_radius!r}; allowed: a number of metres > 0")
        for role, part in (("long", long), ("short", short)):
            check_arena_part(role, part)
        self.long, self.short, self.switch_radius = long, short, float(switch_radius)
        self.meta: dict[str, Any] = {"scenario": "arena", "switch_radius": self.switch_radius}
        seen = {name: observation_options(part) for name, part in (("long", long), ("short", short))}
        if None not in seen.values() and seen["long"] != seen["short"]:
            long_sees, short_sees = (_describe(seen[name]) for name in ("long", "short"))
            raise ValueError(f"the long-range policy observes {long_sees}, the short-range one {short_sees}; allowed: the same")
        options = seen["long"] if seen["long"] is not None else seen["short"]
        if options is not None and options != PAPER_OBSERVATION:
            self.meta["env_config"] = {k: v for k, v in options.items() if v != PAPER_OBSERVATION[k]}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, 2) for arena observations (N, 6 + 7 k [+ 44])."""
        obs = np.asarray(obs, np.float32)
        near = target_distance(obs) < self.switch_radius
        out = np.zeros((len(obs), 2), np.float32)
        if near.any():
            out[near] = self.short(obs[near])
        if (~near).any():
            out[~near] = self.long(obs[~near])
        return out


def write_pair(path: str | Path, long: str | Path, short: str | Path, switch_radius: float) -> Path:
    """Write a pair file naming the long- and short-range policy sources; returns its path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if not switch_radius > 0:
        raise ValueError(f"bad switch_radius {switch_radius!r}; allowed: a number of metres > 0")
    for name, source in (("long", long), ("short", short)):
        if not Path(source).exists():
            raise ValueError(f"{name}-range policy {source} does not exist")

    def rel(p: str | Path) -> str:
        return os.path.relpath(Path(p).resolve(), path.parent.resolve())

    spec = {"format": FORMAT, "long": rel(long), "short": rel(short), "switch_radius": float(switch_radius)}
    partial = path.with_name(f".{path.name}.partial")  # whole or not at all: written beside, renamed over
    try:
        partial.write_text(json.dumps(spec, indent=2))
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def read_pair(path: str | Path) -> dict[str, Any]:
    """The spec of a pair file with absolute policy paths; a clear error if it is not one."""
    path = Path(path)
    try:
        spec = json.loads(path.read_text())
    except (OSError, ValueError) as exc:
        raise ValueError(f"{path} is not a coin_app switching-policy file: {exc}") from exc
    if not isinstance(spec, dict) or spec.get("format") != FORMAT:
        raise ValueError(f"{path} is not a coin_app switching-policy file (format {FORMAT!r} expected)")
    return {**spec, "long": path.parent / spec["long"], "short": path.parent / spec["short"]}


def load_pair(path: str | Path, loader: Callable[[Path], Callable[[np.ndarray], np.ndarray]]) -> SwitchingPolicy:
    """The switching policy of a pair file, each part loaded with ``loader``."""
    spec = read_pair(path)
    return SwitchingPolicy(loader(spec["long"]), loader(spec["short"]), spec["switch_radius"])
