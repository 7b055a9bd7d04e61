"""What a ``--set`` value may be: :class:`Rule` (a type, a range, the few literal values also taken) and ``--set`` parsing.

Every setting declares its rule with its default (``coin_app.algorithms.settings``); a bad value is
refused before a Ray session, an env or a network exists, with one line that names the key, the
value and what is allowed, e.g.::

    bad value for 'tau': inf; allowed: a finite number in (0, 1]

The algorithm configs keep their own checks of combinations (e.g. a counterfactual baseline
without the global critic). Scenario keys are checked by ``coin_app.sim.config`` in the same form.
``tests/test_checks.py`` loops over the registry: every key has a rule, and inf, NaN, a wrong type
and an out-of-range value are refused for each.
"""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass
from typing import Any

INF = math.inf


@dataclass(frozen=True)
class Rule:
    """What one key takes: ``kind`` int | float | bool | choice, a range (open or closed ends) and extra literal values."""

    kind: str
    lo: float = -INF
    hi: float = INF
    lo_open: bool = False
    hi_open: bool = False
    also: tuple[Any, ...] = ()  # literal values also allowed (None, "auto", "full", the choices of a "choice" key)

    def accepts(self, value: Any) -> bool:
        """Whether ``value`` is allowed."""
        if any(value is a or (type(value) is type(a) and value == a) for a in self.also):
            return True
        if self.kind == "bool":
            return isinstance(value, bool)
        if self.kind == "choice" or isinstance(value, bool):
            return False
        kinds = (int,) if self.kind == "int" else (int, float)
        if not isinstance(value, kinds) or not math.isfinite(value):
            return False
        above = value > self.lo if self.lo_open else value >= self.lo
        below = value < self.hi if self.hi_open else value <= self.hi
        return above and below

    def allowed(self) -> str:
        """What is allowed, in words: ``a finite number in (0, 1]``, ``an integer >= 1``, ``True or False``."""
        extra = " or ".join(repr(a) for a in self.also)
        if self.kind == "bool":
            return "True or False"
        if self.kind == "choice":
            return ", ".join(repr(a) for a in self.also)
        what = "an integer" if self.kind == "int" else "a finite number"
        if self.lo > -INF and self.hi < INF:
            what += f" in {'(' if self.lo_open else '['}{_num(self.lo)}, {_num(self.hi)}{')' if self.hi_open else ']'}"
        elif self.lo > -INF:
            what += f" {'>' if self.lo_open else '>='} {_num(self.lo)}"
        elif self.hi < INF:
            what += f" {'<' if self.hi_open else '<='} {_num(self.hi)}"
        return f"{extra} or {what}" if extra else what


def _num(x: float) -> str:
    """A bound as written in a message: 1 not 1.0."""
    return str(int(x)) if float(x).is_integer() else str(x)


def positive(kind: str = "float", hi: float = INF, *also: Any) -> Rule:
    """A number (or integer) > 0 (up to ``hi``)."""
    return Rule(kind, 0.0, hi, lo_open=kind == "float", also=also) if kind == "float" else Rule(kind, 1, hi, also=also)


def non_negative(kind: str = "float", *also: Any) -> Rule:
    """A number (or integer) >= 0."""
    return Rule(kind, 0, INF, also=also)


def unit(lo_open: bool = False) -> Rule:
    """A number in [0, 1] (or (0, 1])."""
    return Rule("float", 0.0, 1.0, lo_open=lo_open)


def choice(*values: Any) -> Rule:
    """One of ``values``."""
    return Rule("choice", also=values)


BOOL = Rule("bool")


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``key=value`` strings to a dict; values are Python literals when they parse as one (``inf``/``nan``: floats)."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"bad --set {item!r}; expected key=value, e.g. --set crash_penalty=10")
        if raw.strip().lower() in NON_FINITE:  # refused by name later, rather than read as the string 'inf'
            out[key] = float(raw)
            continue
        try:
            out[key] = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            out[key] = raw
    return out


NON_FINITE = ("inf", "+inf", "-inf", "nan", "infinity", "-infinity")
