"""The coin_app checkpoint format, and loading a checkpoint's policy for evaluation and export.

A checkpoint is RLlib's directory layout plus ``coin_app.json``: the algorithm, scenario,
scenario overrides and seed, so a checkpoint is self-describing. The policy of a checkpoint is
its shared RLModule's deterministic actor (the :class:`~coin_app.algorithms.spec.ActorModule`
contract every algorithm's module implements).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule
from coin_app.algorithms.spec import ActorModule
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.scenarios import config_from_dict

META_FILE = "coin_app.json"
MODULE_PATH = ("learner_group", "learner", "rl_module", SHARED_MODULE_ID)


def write_metadata(checkpoint: Path, meta: dict[str, Any]) -> None:
    """Store what a checkpoint was trained on next to it."""
    (checkpoint / META_FILE).write_text(json.dumps(meta, indent=2, default=str))


def read_metadata(checkpoint: Path) -> dict[str, Any]:
    """The metadata of a checkpoint written by ``train``; a clear error if it is not one."""
    checkpoint = Path(checkpoint)
    if not checkpoint.is_dir():
        raise ValueError(f"checkpoint {checkpoint} does not exist or is not a directory")
    meta = checkpoint / META_FILE
    if not meta.exists() or not (checkpoint.joinpath(*MODULE_PATH)).is_dir():
        raise ValueError(f"{checkpoint} is not a coin_app checkpoint (missing {META_FILE} or {'/'.join(MODULE_PATH)})")
    return json.loads(meta.read_text())


def scenario_of(checkpoint: Path, **overrides: Any) -> ScenarioConfig | ArenaConfig:
    """The scenario config a checkpoint was trained on, with ``overrides`` (e.g. num_agents) applied."""
    meta = read_metadata(checkpoint)
    return config_from_dict(meta["scenario"], {**meta.get("env_config", {}), **overrides})


def actor_module(module: Any) -> ActorModule:
    """``module`` as the algorithm contract's :class:`ActorModule`; a clear error for a module that is not one."""
    if type(module) is DefaultPPOTorchRLModule:  # an IPPO / nav_ppo checkpoint saved before the contract: same networks
        module.__class__ = PPOActorModule  # the subclass only adds the contract's two methods
    if not isinstance(module, ActorModule):
        raise ValueError(f"{type(module).__name__} does not implement the ActorModule contract (deterministic_actor, inference_actions)")
    return module


def load_module(checkpoint: Path) -> ActorModule:
    """The shared RLModule stored in a coin_app checkpoint."""
    read_metadata(checkpoint)
    return actor_module(RLModule.from_checkpoint(str(Path(checkpoint).resolve().joinpath(*MODULE_PATH))))


def actor_policy(module: Any) -> Callable[[np.ndarray], np.ndarray]:
    """A module's deterministic actor as a numpy function (N, obs_dim) -> (N, 2)."""
    return network_policy(actor_module(module).deterministic_actor())


def network_policy(network: torch.nn.Module) -> Callable[[np.ndarray], np.ndarray]:
    """An observation -> action torch network as a numpy function (N, obs_dim) -> (N, 2), in eval mode."""
    actor = network.eval()

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor(torch.as_tensor(np.asarray(obs, dtype=np.float32))).numpy()

    return policy


def inference_actions(module: Any, obs: np.ndarray) -> np.ndarray:
    """The env actions (N, 2) of the module's own ``forward_inference`` on ``obs`` (the export parity reference)."""
    with torch.no_grad():
        return actor_module(module).inference_actions(torch.as_tensor(np.asarray(obs, dtype=np.float32))).numpy()


def load_checkpoint_policy(checkpoint: Path) -> Callable[[np.ndarray], np.ndarray]:
    """The checkpoint's deterministic actor as a numpy function (N, obs_dim) -> (N, 2)."""
    return actor_policy(load_module(checkpoint))
