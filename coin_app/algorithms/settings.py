"""One declaration per setting: an algorithm family's hyper-parameters as a frozen dataclass.

Each field is declared once with :func:`setting`: its default, the rule its values obey
(:class:`~coin_app.algorithms.checks.Rule`), its meaning in one line, the component that reads
it, and the official code's value where that differs. The rest derives from the class: the
``--set`` keys and their one-line refusals (:meth:`Settings.of`), the spec's
``hyperparameters`` table, ``python -m coin_app scenarios``, ``python -m coin_app config`` and
``docs/reference/config-keys.md``. A child algorithm's class subclasses its family's and holds
only its difference (:func:`redeclare` changes an inherited default). Presets (paper, quick,
smoke, reduced, dense, tiny) are values of the class, written in one ``settings.py`` per family.

Ray-free and torch-free: the command line checks ``--set`` values from here before any work.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field, fields
from typing import Any, TypeVar

from coin_app.algorithms.checks import Rule

S = TypeVar("S", bound="Settings")


class _Same:
    """The official code's value equals the default (the marker of :func:`setting`'s ``official``)."""

    def __repr__(self) -> str:
        return "SAME"


SAME: Any = _Same()


@dataclass(frozen=True)
class Declaration:
    """One setting as declared: key, default, rule, meaning, the component that reads it, the official code's value."""

    key: str
    default: Any
    rule: Rule
    meaning: str
    reads: str
    official: Any = SAME

    def differs_from_official(self) -> bool:
        """Whether the official code uses another value than the default."""
        return self.official is not SAME


def setting(default: Any, rule: Rule, meaning: str, *, reads: str, official: Any = SAME) -> Any:
    """A dataclass field declaring one setting (see :class:`Declaration`); ``default`` must obey ``rule``."""
    if not rule.accepts(default):
        raise ValueError(f"default {default!r} refused by its own rule ({rule.allowed()})")
    return field(default=default, metadata={"setting": (rule, meaning, reads, official)})


def redeclare(parent: type[Settings], key: str, default: Any, meaning: str | None = None, *, official: Any = SAME) -> Any:
    """The field of ``parent``'s setting ``key`` with another default (and optionally meaning); rule and reader kept."""
    base = parent.declarations()[key]
    return setting(default, base.rule, meaning or base.meaning, reads=base.reads, official=official)


class Settings:
    """Base of every family's frozen settings dataclass: the declarations, checks and presets' arithmetic."""

    @classmethod
    def declarations(cls) -> dict[str, Declaration]:
        """Every setting of the class, in field order."""
        out = {}
        for f in fields(cls):  # type: ignore[arg-type]
            rule, meaning, reads, official = f.metadata["setting"]
            out[f.name] = Declaration(f.name, f.default, rule, meaning, reads, official)
        return out

    @classmethod
    def keys(cls) -> tuple[str, ...]:
        """The ``--set`` keys of the class."""
        return tuple(f.name for f in fields(cls))  # type: ignore[arg-type]

    @classmethod
    def hyperparameters(cls) -> dict[str, tuple[Any, str]]:
        """``key -> (default, meaning)`` (the spec's table)."""
        return {k: (d.default, d.meaning) for k, d in cls.declarations().items()}

    @classmethod
    def value_errors(cls, values: Mapping[str, Any]) -> list[str]:
        """The one-line message of every bad value of a known key in ``values`` (other keys are the router's business)."""
        decl = cls.declarations()
        return [
            f"bad value for {k!r}: {v!r}; allowed: {decl[k].rule.allowed()}"
            for k, v in values.items()
            if k in decl and not decl[k].rule.accepts(v)
        ]

    @classmethod
    def of(cls: type[S], values: Mapping[str, Any], base: S | None = None) -> S:
        """``base`` (default: the class defaults) with ``values``; a ValueError in one line for an unknown key or a bad value."""
        unknown = sorted(set(values) - set(cls.keys()))
        if unknown:
            raise ValueError(f"unknown {cls.__name__} key(s) {unknown}; allowed: {', '.join(cls.keys())}")
        errors = cls.value_errors(values)
        if errors:
            raise ValueError(errors[0])
        return dataclasses.replace(base if base is not None else cls(), **values)  # type: ignore[type-var]

    @classmethod
    def lift(cls: type[S], other: Settings) -> S:
        """A preset of a parent class as a value of this class: what it changed from the parent's defaults, over this class's
        defaults (a default the child redeclared stays the child's unless the preset changed it)."""
        return cls(**{k: v for k, v in other.changes().items() if k in cls.keys()})

    def values(self) -> dict[str, Any]:
        """Every setting's value, in field order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}  # type: ignore[arg-type]

    def changes(self, base: Settings | None = None) -> dict[str, Any]:
        """The settings whose value differs from ``base`` (default: the class defaults), in field order."""
        ref = (base if base is not None else type(self)()).values()
        return {k: v for k, v in self.values().items() if k not in ref or type(ref[k]) is not type(v) or ref[k] != v}
