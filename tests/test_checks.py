"""One table of allowed values: every algorithm key has a rule, and inf, NaN, wrong types and out-of-range values are refused by name."""

import math

import pytest

from coin_app.algorithms import registry
from coin_app.algorithms.checks import INF, Rule

ALL_KEYS = sorted({(name, key) for name, spec in registry.ALGORITHMS.items() for key in spec.hyperparameters})


def bad_values(rule: Rule) -> list:
    """Values the rule must refuse: non-finite numbers, a wrong type, and just outside each finite bound."""
    if rule.kind == "bool":
        return [1, "yes", None]
    if rule.kind == "choice":
        return ["surely-not-a-choice", 1.5, True]
    out = [math.inf, -math.inf, math.nan, "abc", True, [1]]
    if rule.kind == "int":
        out.append(2.5)
    if rule.lo > -INF:
        out.append(rule.lo if rule.lo_open else rule.lo - 1)
    if rule.hi < INF:
        out.append(rule.hi if rule.hi_open else rule.hi + 1)
    return [v for v in out if not any(v is a for a in rule.also)]


@pytest.mark.parametrize(("name", "key"), ALL_KEYS)
def test_every_key_has_a_rule_that_accepts_its_default(name, key):
    rule = registry.get(name).rule(key)
    assert rule is not None, f"{name}'s key {key!r} has no rule (its settings declaration)"
    default = registry.get(name).hyperparameters[key][0]
    assert rule.accepts(default), f"{name}'s default {key}={default!r} is refused by its own rule"


@pytest.mark.parametrize(("name", "key"), ALL_KEYS)
def test_bad_values_are_refused_in_one_line_before_any_work(name, key):
    rule = registry.get(name).rule(key)
    for value in bad_values(rule):
        with pytest.raises(ValueError) as err:
            registry.split_overrides(name, {key: value}, registry.get(name).scenarios[0])
        text = str(err.value)
        assert "\n" not in text and f"bad value for {key!r}: {value!r}; allowed: {rule.allowed()}" == text


def test_allowed_text_names_the_range():
    cig = registry.get("cig_td3")
    assert cig.rule("tau").allowed() == "a finite number in (0, 1]"
    assert cig.rule("policy_delay").allowed() == "an integer >= 1"
    assert cig.rule("exploration_noise_initial").allowed() == "None or a finite number >= 0"
    assert cig.rule("graph").allowed() == "'full' or a finite number > 0"
    assert cig.rule("global_critic").allowed() == "True or False"
    assert cig.rule("precision").allowed() == "'auto', 'fp32', 'bf16'"


def test_edges_of_ranges():
    itd3 = registry.get("itd3")
    assert itd3.value_errors({"tau": 1, "gamma": 0.0, "warmup_steps": 0}) == []
    for key, value in (("tau", 0.0), ("gamma", 1.0000001), ("hidden", 64.0)):
        assert itd3.value_errors({key: value}) == [f"bad value for {key!r}: {value!r}; allowed: {itd3.rule(key).allowed()}"]
    copo = registry.get("copo")
    assert copo.value_errors({"num_epochs": 0, "initial_lcf_mean": 1.0, "neighbour_radius": None, "lr": 1e-3}) == [
        "bad value for 'num_epochs': 0; allowed: an integer >= 1",
        "bad value for 'initial_lcf_mean': 1.0; allowed: a finite number in (-1, 1)",
        "bad value for 'neighbour_radius': None; allowed: a finite number > 0",
    ]
    assert itd3.value_errors({"unknown_key_without_rule": object}) == []  # keys without a rule are the router's business
