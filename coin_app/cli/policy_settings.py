"""The scenario config a trained policy runs on: its training config, a preset in its place, then ``--set`` (Ray-free)."""

from __future__ import annotations

from typing import Any

from coin_app.sim.config import PRESETS
from coin_app.sim.scenarios import AnyScenarioConfig, config_from_dict

PRESET_KEYS = tuple(dict.fromkeys(k for values in PRESETS.values() for k in values))  # the config keys some preset sets


def check_preset(preset: str | None) -> None:
    """Refuse a preset name that is not one of :data:`PRESETS` (None: no preset asked for)."""
    if preset is not None and preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; allowed: {', '.join(PRESETS)}")


def with_preset(env_config: dict[str, Any], preset: str | None) -> dict[str, Any]:
    """A stored env_config under an explicit ``preset``: its own preset and every key a preset sets dropped (None: as stored)."""
    check_preset(preset)
    if preset is None:
        return dict(env_config)
    return {**{k: v for k, v in env_config.items() if k != "preset" and k not in PRESET_KEYS}, "preset": preset}


def driving_config(
    meta: dict[str, Any], source: Any, scenario: str | None, overrides: dict[str, Any], preset: str | None = None
) -> AnyScenarioConfig:
    """The config to run a policy with metadata ``meta`` (from ``source``) on: ``scenario`` (default: its own), its training
    env_config under ``preset``, then ``overrides``; a ValueError for an arena policy or an unknown scenario."""
    scenario = scenario or meta.get("scenario")
    if scenario == "arena" or meta.get("scenario") == "arena":
        raise ValueError(f"{source} is an arena policy; evaluate it with: python -m coin_app evaluate-arena {source}")
    if scenario is None:
        raise ValueError(f"{source} does not say which scenario it was trained on; pass --scenario")
    return config_from_dict(scenario, {**with_preset(meta.get("env_config", {}), preset), **overrides})
