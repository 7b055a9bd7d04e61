"""The table of trainable algorithms, and the routing of ``--set key=value`` overrides.

Each algorithm package exports its :class:`~coin_app.algorithms.spec.AlgorithmSpec`; this
module only lists them. An override key goes to the scenario config (``ScenarioConfig`` /
``ArenaConfig`` fields) or to the algorithm's documented hyper-parameters; anything else is
refused with the allowed keys listed.
"""

from __future__ import annotations

import ast
from dataclasses import fields
from typing import Any

from coin_app.algorithms.cig_td3.cig_td3 import CIG_TD3, ITD3
from coin_app.algorithms.copo.copo import COPO
from coin_app.algorithms.nav_ppo.config import NAV_PPO
from coin_app.algorithms.ppo_family.config import CPPO, IPPO, MFPO
from coin_app.algorithms.spec import AlgorithmSpec
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig

ALGORITHMS: dict[str, AlgorithmSpec] = {spec.name: spec for spec in (CIG_TD3, ITD3, IPPO, CPPO, MFPO, COPO, NAV_PPO)}

# A small bottleneck setting that learns within minutes on a laptop CPU (CI learning test,
# benchmarks/learning_curves.py); each spec's ``quick`` adds its small-network settings.
QUICK_SCENARIO: dict[str, Any] = {"num_agents": 4, "horizon": 300, "max_agent_steps": 300}
QUICK_SETTINGS: dict[str, Any] = {**QUICK_SCENARIO, **CIG_TD3.quick}  # CIG-TD3 / ITD3 on the quick scenario


def get(name: str) -> AlgorithmSpec:
    """The spec of algorithm ``name``; unknown names raise a ValueError listing the choices."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; allowed: {', '.join(sorted(ALGORITHMS))}")
    return ALGORITHMS[name]


def quick_settings(name: str) -> dict[str, Any]:
    """Settings of algorithm ``name`` on the small quick scenario (learning test, learning curves)."""
    return {**QUICK_SCENARIO, **get(name).quick}


def scenario_keys(scenario: str) -> set[str]:
    """The ``--set`` keys of a scenario's config."""
    if scenario == "arena":
        return {f.name for f in fields(ArenaConfig)}
    return {f.name for f in fields(ScenarioConfig)} - {"scenario"} | {"preset"}


def split_overrides(name: str, overrides: dict[str, Any], scenario: str = "intersection") -> tuple[dict[str, Any], dict[str, Any]]:
    """Route ``--set`` keys to (scenario config, algorithm config); unknown keys are refused."""
    env_keys = scenario_keys(scenario)
    algo_keys = set(get(name).keys())
    env_cfg = {k: v for k, v in overrides.items() if k in env_keys}
    algo_cfg = {k: v for k, v in overrides.items() if k in algo_keys}
    unknown = sorted(set(overrides) - set(env_cfg) - set(algo_cfg))
    if unknown:
        raise ValueError(
            f"unknown --set key(s) {unknown}; scenario keys: {', '.join(sorted(env_keys))}; {name} keys: {', '.join(sorted(algo_keys))}"
        )
    return env_cfg, algo_cfg


def parse_overrides(items: list[str]) -> dict[str, Any]:
    """``key=value`` strings to a dict; values are Python literals when they parse as one."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        if not sep or not key:
            raise ValueError(f"bad --set {item!r}; expected key=value, e.g. --set crash_penalty=10")
        try:
            out[key] = ast.literal_eval(raw)
        except (ValueError, SyntaxError):
            out[key] = raw
    return out
