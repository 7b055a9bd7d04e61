"""One value per setting: ``--set`` pairs merged with the flags that set the same keys, a conflict refused in one line."""

from __future__ import annotations

from typing import Any

from coin_app.algorithms.checks import parse_overrides


def overrides_of(items: list[str], flags: dict[str, tuple[str, Any]] | None = None) -> dict[str, Any]:
    """``--set`` pairs as a dict, plus each flag's value (``key -> (flag, value)``, None: not given).

    Refused: one key twice in ``--set`` with two values, and a flag and ``--set`` giving one key two values.
    """
    seen: dict[str, Any] = {}
    for item in items:
        pair = parse_overrides([item])
        for key, value in pair.items():
            if key in seen and seen[key] != value:
                raise ValueError(f"--set gives {key} twice ({seen[key]!r} and {value!r}); allowed: one value per key")
            seen[key] = value
    for key, (flag, value) in (flags or {}).items():
        if value is None:
            continue
        if key in seen and seen[key] != value:
            raise ValueError(f"{flag} {value} and --set {key}={seen[key]!r} set one key to two values; allowed: one of them")
        seen[key] = value
    return seen
