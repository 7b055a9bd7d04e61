"""The one place that picks a simulator backend for a scenario config."""

from __future__ import annotations

from coin_app.backends.metadrive import MetaDriveDrivingEnv
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.driving_env import DrivingEnv


def make_driving_env(config: ScenarioConfig | ArenaConfig) -> DrivingEnv | MetaDriveDrivingEnv | ArenaEnv:
    """The dict-API env of ``config``: a native :class:`DrivingEnv`, a ``MetaDriveDrivingEnv`` or (an arena config) an ``ArenaEnv``."""
    if isinstance(config, ArenaConfig):
        return ArenaEnv(config)
    if config.backend == "metadrive":
        return MetaDriveDrivingEnv(config)
    return DrivingEnv(config)
