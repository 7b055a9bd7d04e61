"""The driving scenarios, one record each: every list of scenario names, default vehicle counts, map files, MetaDrive
classes and generalization grids in the project derives from :data:`SCENES`.

The counts are COIN's (Table 5.1: intersection 30, roundabout 40, bottleneck 20 initial vehicles) and its
generalization grids (Fig. 4/6); the maps are MetaDrive 0.4.3's multi-agent scenes extracted into ``maps/``.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Scene:
    """One driving scenario: its name and the facts the simulator, backends, sweeps and tests read from it."""

    name: str
    default_vehicles: int  # initial vehicles (COIN Table 5.1); the cap on active + dying while respawning
    metadrive_class: str  # the MetaDrive 0.4.3 multi-agent env it rebuilds (coin_app.backends.metadrive)
    generalization_counts: tuple[int, ...]  # initial vehicle counts of the paper's generalization grid (Fig. 4/6)
    metadrive_obs_layout: str = "standard"  # the observation MetaDrive's env gives (config.OBS_LAYOUTS)
    progress_sign_flip: bool = True  # MetaDrive's reward negates progress off the reference lanes of a negative road

    @property
    def map_file(self) -> str:
        """The map's file name in ``coin_app/sim/maps/``."""
        return f"{self.name}.json"

    @property
    def env_id(self) -> str:
        """The Gymnasium / RLlib id the env is registered under."""
        return env_id(self.name)


def env_id(name: str) -> str:
    """The Gymnasium / RLlib id of scenario ``name`` (a driving scene or the arena)."""
    return f"coin-{name}-v0"


SCENES: dict[str, Scene] = {
    s.name: s
    for s in (
        Scene("intersection", 30, "MultiAgentIntersectionEnv", (6, 12, 18, 24, 30, 36)),
        Scene("roundabout", 40, "MultiAgentRoundaboutEnv", (8, 16, 24, 32, 40, 48)),
        # MetaDrive's bottleneck: side and lane-line detectors (96 numbers), and its own reward without the sign flip
        Scene("bottleneck", 20, "MultiAgentBottleneckEnv", (5, 10, 15, 20, 25, 30), "bottleneck96", progress_sign_flip=False),
    )
}
DRIVING_SCENARIOS: tuple[str, ...] = tuple(SCENES)
ARENA = "arena"  # the other scenario: the second paper's navigation-and-parking arena (coin_app/sim/arena/)
SCENARIOS: tuple[str, ...] = (*DRIVING_SCENARIOS, ARENA)


def scene(name: str) -> Scene:
    """The record of driving scenario ``name``; a ValueError lists the scenarios for an unknown one."""
    if name not in SCENES:
        raise ValueError(f"unknown scenario {name!r}; allowed: {', '.join(SCENES)}")
    return SCENES[name]
