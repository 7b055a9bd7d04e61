"""The allowed values of every algorithm's ``--set`` keys, in one table, checked before any work.

Every hyper-parameter of every registered algorithm (``AlgorithmSpec.hyperparameters``) has a
:class:`Rule` here: its type (an integer, a number, a boolean or one of named choices), whether
it must be finite (always, for numbers), its range and the few non-numeric values it also takes
(``None``, ``"auto"``, ``"full"``). :func:`check_value` refuses anything else with one line that
names the key, the value and what is allowed, e.g.::

    bad value for 'tau': inf; allowed: a finite number in (0, 1]

``registry.split_overrides`` applies it to every ``--set`` value of an algorithm, so a bad value
is refused before a Ray session, an env or a network exists; the algorithm configs keep their
own checks of combinations (e.g. a counterfactual baseline without the global critic).
Scenario keys are checked by ``coin_app.sim.config`` (types, finiteness, ranges) in the same
one-line form. ``tests/test_checks.py`` loops over the registry: every key has a rule, and
inf, NaN, a wrong type and an out-of-range value are refused for each.
"""

from __future__ import annotations

import ast
import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from coin_app.algorithms.choices import (
    DOMAIN_REWARDS,
    GAT_INITS,
    GLOBAL_MODULES,
    LOCAL_MODULES,
    NEIGHBOUR_FEATURES,
    PRECISIONS,
    UPDATE_ORDERS,
)

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

# The TD3 family's hyper-parameters (their meaning is documented once in the algorithm's HYPERPARAMETERS); the PPO family
# declares each setting with its rule in its settings class (coin_app.algorithms.settings).
RULES: dict[str, Rule] = {
    # learning rates and TD3
    "actor_lr": positive("float", 1.0),
    "critic_lr": positive("float", 1.0),
    "central_critic_lr": positive("float", 1.0),
    "gamma": unit(),
    "tau": unit(lo_open=True),
    "policy_delay": positive("int"),
    "exploration_noise": non_negative(),
    "exploration_noise_initial": non_negative("float", None),
    "exploration_noise_decay_steps": non_negative("int"),
    "exploration_noise_decay_start": non_negative("int", None),
    "lr_decay_start": non_negative("int"),
    "lr_decay_steps": non_negative("int"),
    "lr_final_fraction": unit(lo_open=True),
    "target_noise": non_negative(),
    "target_noise_clip": non_negative(),
    "warmup_steps": non_negative("int"),
    "actor_start_steps": non_negative("int"),
    "replay_capacity": positive("int"),
    "updates_per_env_step": positive("float", 1000.0),
    "train_batch_size_per_learner": positive("int"),
    "rollout_fragment_length": positive("int", INF, "auto"),
    "num_env_runners": non_negative("int"),
    "learner_threads": positive("int"),
    "precision": choice(*PRECISIONS),
    "eval_every": non_negative("int"),
    "checkpoint_replay": BOOL,
    "eval_episodes": positive("int"),
    # CIG-TD3's critic and its ablations
    "global_critic": BOOL,
    "counterfactual_baseline": BOOL,
    "local_module": choice(*LOCAL_MODULES),
    "global_module": choice(*GLOBAL_MODULES),
    "graph": positive("float", INF, "full"),
    "global_weight": non_negative(),
    "vae_weight": non_negative(),
    "kl_beta": non_negative(),
    "hidden": positive("int"),
    "actor_layers": positive("int"),
    "latent_dim": positive("int"),
    "node_width": positive("int"),
    "gat_heads": positive("int"),
    "gat_init": choice(*GAT_INITS),
    "update_order": choice(*UPDATE_ORDERS),
    "actor_preact_penalty": non_negative(),
    "actor_preact_threshold": non_negative(),
    "critic_feature_norm": BOOL,
    # TraCo's domain critic
    "baseline_lr": positive("float", 1.0),
    "domain_radius": positive(),
    "domain_reward": choice(*DOMAIN_REWARDS),
    "attention_heads": positive("int"),
    "token_layers": positive("int"),
    "neighbour_features": choice(*NEIGHBOUR_FEATURES),
    "null_token": BOOL,
    "individual_critic": BOOL,
    "domain_weight": non_negative(),
    "timeout_bootstrap": BOOL,
}


def check_value(key: str, value: Any) -> Any:
    """``value`` if ``key`` allows it (keys without a rule pass); else a ValueError naming the key, the value and what is allowed."""
    rule = RULES.get(key)
    if rule is not None and not rule.accepts(value):
        raise ValueError(f"bad value for {key!r}: {value!r}; allowed: {rule.allowed()}")
    return value


def check_values(values: Mapping[str, Any]) -> None:
    """Check every key of ``values``; a ValueError with the first bad one's message (:func:`check_value`)."""
    errors = value_errors(values)
    if errors:
        raise ValueError(errors[0])


def value_errors(values: Mapping[str, Any]) -> list[str]:
    """The one-line message of every bad value in ``values`` (empty when all are allowed)."""
    errors = []
    for key, value in values.items():
        try:
            check_value(key, value)
        except ValueError as exc:
            errors.append(str(exc))
    return errors


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
