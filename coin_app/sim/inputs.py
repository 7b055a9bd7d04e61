"""The checks every env API shares (``DrivingEnv``, the PettingZoo and the RLlib envs): one rule, one one-line message each.

* :func:`~coin_app.sim.scenarios.env_config`: a config, or a scenario name with a preset and overrides,
  never both (no override is dropped); a string where a config goes is named.
* numpy scalars (``np.int64(4)``) pass as the Python numbers they hold (``config_from_dict``).
* :func:`check_seed`: ``None`` or an integer >= 0 (numpy integers too).
* :func:`checked_actions`: exactly one action of two finite numbers per acting agent, keyed by its id.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from coin_app.sim import schema


def check_seed(seed: Any) -> int | None:
    """``seed`` as an int (``None`` stays None); a ValueError for anything but an integer >= 0."""
    if seed is None:
        return None
    if isinstance(seed, (bool, np.bool_)) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"bad seed {seed!r}; allowed: None or an integer >= 0")
    return int(seed)


def checked_actions(actions: Any, agents: list[str], act_dim: int = schema.ACT_DIM) -> dict[str, np.ndarray]:
    """``actions`` as float arrays of shape (act_dim,), after checking there is exactly one per agent in ``agents``."""
    if not isinstance(actions, dict):
        raise ValueError(f"actions must be a dict of agent id -> action, got {type(actions).__name__}; acting agents: {agents}")
    keys = list(actions)
    bad_keys = [k for k in keys if not isinstance(k, str)]
    if bad_keys:
        raise ValueError(f"action keys must be agent ids (str) such as {agents[:1]}; got {bad_keys[0]!r} ({type(bad_keys[0]).__name__})")
    unknown = sorted(set(keys) - set(agents))
    if unknown:
        raise ValueError(f"actions for agent(s) {unknown} that cannot act now; acting agents: {agents}")
    missing = [a for a in agents if a not in actions]
    if missing:
        raise ValueError(f"missing actions for agent(s) {missing}; every agent in env.agents must act")
    out = {}
    for aid, a in actions.items():
        try:
            arr = np.asarray(a, dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"action of {aid} must be {act_dim} numbers, got {type(a).__name__} {a!r:.60}") from None
        if arr.shape != (act_dim,):
            raise ValueError(f"action of {aid} must have {act_dim} numbers, got shape {arr.shape}")
        if not all(math.isfinite(x) for x in arr):
            raise ValueError(f"action of {aid} holds a non-finite number {arr.tolist()}; allowed: finite numbers")
        out[aid] = arr
    return out
