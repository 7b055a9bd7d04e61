"""The one scenario dispatch: a scenario name and flat overrides to its typed config (driving scenarios or the arena)."""

from __future__ import annotations

from typing import Any

from coin_app.sim.arena.config import ArenaConfig, make_arena_config
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.scenes import ARENA

AnyScenarioConfig = ScenarioConfig | ArenaConfig


def config_from_dict(scenario: str, env_config: dict[str, Any]) -> AnyScenarioConfig:
    """The config of ``scenario`` from a flat dict of overrides (env_config, checkpoint metadata, ``--set``).

    Driving scenarios: ``make_config`` (the dict may hold ``preset``); ``"arena"``: an
    :class:`~coin_app.sim.arena.config.ArenaConfig` (no presets).
    """
    values = dict(env_config)
    if scenario == ARENA:
        if "preset" in values:
            raise ValueError(f"the arena has no presets (got preset={values['preset']!r})")
        return make_arena_config(**values)
    return make_config(scenario, values.pop("preset", "paper"), **values)


def scenario_name(config: AnyScenarioConfig) -> str:
    """The scenario name of a parsed config (``"arena"`` for an :class:`ArenaConfig`)."""
    return ARENA if isinstance(config, ArenaConfig) else config.scenario
