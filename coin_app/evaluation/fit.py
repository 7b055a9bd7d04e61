"""Whether a trained policy fits the env it is asked to drive: its observation layout must match, its scene should.

A policy's metadata (a checkpoint's ``coin_app.json``, an exported file's ``meta``) names the
scenario and the env config it was trained on. :func:`policy_fit` refuses, in one line, an env
whose observation has another layout (another size: the MetaDrive backend's 96 numbers against
the native 91, another ``lidar_beams``), and returns a warning for a scene or a vehicle count it
was not trained on: those run, and the warning goes with the results.
"""

from __future__ import annotations

from typing import Any

from coin_app.sim.config import ScenarioConfig
from coin_app.sim.scenarios import config_from_dict


def policy_fit(meta: dict[str, Any], config: ScenarioConfig, source: Any, obs_dim: int | None = None) -> list[str]:
    """The warnings of running a policy (metadata ``meta``, from ``source``) on ``config``; a ValueError if it cannot run there.

    ``obs_dim``: the observation size the policy's weights take (an exported file's), checked against its metadata too.
    Metadata without an ``env_config`` (a hand-made file) is checked by its weights' size and scenario only.
    """
    scenario, env_config = meta.get("scenario"), meta.get("env_config")
    extra = 1 if "lcf" in meta else 0  # an exported CoPO actor also reads its vehicle's LCF
    trained = config_from_dict(scenario, dict(env_config)) if scenario and isinstance(env_config, dict) else None
    if trained is not None and obs_dim is not None and obs_dim != trained.obs_dim + extra:
        raise ValueError(
            f"{source}: its weights take {obs_dim} observation numbers, its metadata's training config gives {trained.obs_dim + extra}; "
            "allowed: a policy file whose metadata and weights belong together"
        )
    reads = trained.obs_dim if trained is not None else None if obs_dim is None else obs_dim - extra
    if reads is not None and reads != config.obs_dim:
        how = f" ({trained.scenario}, {trained.backend} backend, {trained.lidar_beams} lidar beams)" if trained is not None else ""
        raise ValueError(
            f"{source} reads {reads} observation numbers{how}; this env gives {config.obs_dim} ({config.scenario}, {config.backend} "
            f"backend, {config.lidar_beams} lidar beams); allowed: the backend and observation settings it was trained with"
        )
    warnings = []
    if scenario and scenario != config.scenario:
        warnings.append(f"warning: {source} was trained on {scenario}, not {config.scenario}: a scene it was not trained for")
    if trained is not None and trained.num_agents != config.num_agents:
        warnings.append(
            f"warning: {source} was trained with {trained.num_agents} vehicles, here {config.num_agents}: a count it was not trained for"
        )
    return warnings
