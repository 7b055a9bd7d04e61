"""The bounds and waits that commands check their inputs against, in one Ray-free module (the parser shows them).

A count or size above its bound is refused in one line that names the bound, before any work;
a wait has a stated default and refuses a value that is not a positive number of seconds.
"""

from __future__ import annotations

import math
from typing import Any

CONNECT_TIMEOUT_S = 5.0  # seconds train and sweep wait for a cluster at --address before refusing it
MAX_EPISODES = 1000  # evaluate: seeds in one call (the paper: 20); all of them run at once in one batched simulator
MAX_CASE_VEHICLES = 64  # evaluate-arena: vehicles in one case (the paper's largest: 20); scenes are drawn point by point
MAX_CASE_OBSTACLES = 64  # evaluate-arena: obstacles in one case (the paper's largest: 12)
VALIDATION_EPISODES = 10  # report --select validation and archive: validation seeds per checkpoint
MAX_SCENARIOS_PER_CASE = 10_000  # evaluate-arena: test scenarios per case (the paper: 4062)


def check_timeout(value: Any, flag: str) -> float:
    """``value`` as seconds if it is a finite number > 0; otherwise a ValueError naming ``flag``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
        raise ValueError(f"bad {flag} {value!r}; allowed: a finite number of seconds > 0")
    return float(value)


def check_count(value: Any, flag: str, limit: int, low: int = 1) -> int:
    """``value`` if it is an integer in [low, limit]; otherwise a ValueError naming ``flag`` and the bound."""
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= limit:
        raise ValueError(f"bad {flag} {value!r}; allowed: an integer from {low} to {limit}")
    return value


def check_train_budget(steps: Any, max_minutes: Any, checkpoint_every: Any, threads: Any, max_cpu_hours: Any = None) -> None:
    """A ValueError naming the first bad one of ``train``'s budget: steps and checkpoint_every integers >= 1, max_minutes and
    max_cpu_hours numbers > 0 or None, threads an integer >= 1."""
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"bad steps {steps}; allowed: an integer >= 1")
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"bad max_minutes {max_minutes}; allowed: a number > 0 or None")
    if max_cpu_hours is not None and not max_cpu_hours > 0:
        raise ValueError(f"bad max_cpu_hours {max_cpu_hours}; allowed: a number > 0 or None")
    if isinstance(checkpoint_every, bool) or not isinstance(checkpoint_every, int) or checkpoint_every < 1:
        raise ValueError(f"bad checkpoint_every {checkpoint_every}; allowed: an integer >= 1")
    if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
        raise ValueError(f"bad threads {threads!r}; allowed: an integer >= 1")
