"""The one scenario dispatch: a scenario name and flat overrides to its typed config (driving scenarios or the arena)."""

from __future__ import annotations

from typing import Any

import numpy as np

from coin_app.sim.arena.config import ArenaConfig, make_arena_config
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.scenes import ARENA

AnyScenarioConfig = ScenarioConfig | ArenaConfig


def config_from_dict(scenario: str, env_config: dict[str, Any]) -> AnyScenarioConfig:
    """The config of ``scenario`` from a flat dict of overrides (env_config, checkpoint metadata, ``--set``).

    Driving scenarios: ``make_config`` (the dict may hold ``preset``); ``"arena"``: an
    :class:`~coin_app.sim.arena.config.ArenaConfig` (no presets).
    """
    values = {k: v.item() if isinstance(v, np.generic) else v for k, v in dict(env_config).items()}  # np.int64(4): the 4 it is
    if scenario == ARENA:
        if "preset" in values:
            raise ValueError(f"the arena has no presets (got preset={values['preset']!r})")
        return make_arena_config(**values)
    return make_config(scenario, values.pop("preset", "paper"), **values)


def scenario_name(config: AnyScenarioConfig) -> str:
    """The scenario name of a parsed config (``"arena"`` for an :class:`ArenaConfig`)."""
    return ARENA if isinstance(config, ArenaConfig) else config.scenario


def env_config(
    config: Any, scenario: str | None, preset: str | None, overrides: dict[str, Any], who: str, arena: bool = True
) -> AnyScenarioConfig:
    """The env's config: ``config`` as given, or ``scenario`` (default intersection) with ``preset`` and ``overrides``.

    Refused in one line: a config together with a scenario, preset or override (one of them would be
    dropped), a string in the config's place, an ``ArenaConfig`` where ``arena`` is False, and any bad key or value.
    """
    kinds = (ScenarioConfig, ArenaConfig) if arena else (ScenarioConfig,)
    if isinstance(config, str):
        raise ValueError(f"{who}: got the string {config!r} as its config; allowed: {who}(scenario={config!r}) or a ScenarioConfig")
    if config is not None:
        if not isinstance(config, kinds):
            allowed = " or ".join(k.__name__ for k in kinds)
            raise ValueError(f"{who}: bad config of type {type(config).__name__}; allowed: a {allowed}, or None with scenario=...")
        given = [k for k, v in (("scenario", scenario), ("preset", preset)) if v is not None] + sorted(overrides)
        if given:
            raise ValueError(
                f"{who}: pass either a config or scenario/preset/overrides, not both (got a config and {', '.join(given)}); "
                "allowed: dataclasses.replace(config, ...) for a changed config"
            )
        return config
    values = dict(overrides)  # numpy scalars: config_from_dict reads them as the numbers they are
    if preset is not None:
        values["preset"] = preset
    return config_from_dict(scenario or "intersection", values)
