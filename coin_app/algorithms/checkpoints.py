"""Loading a coin_app checkpoint's policy for evaluation and export.

The checkpoint on disk (metadata, manifest, verification, the atomic save) is
:mod:`coin_app.algorithms.checkpoint_files`, importable without Ray; every loader here checks
a checkpoint with its :func:`~coin_app.algorithms.checkpoint_files.verify` first. The policy of a checkpoint is
its shared RLModule's deterministic actor (the :class:`~coin_app.algorithms.spec.ActorModule`
contract every algorithm's module implements). A CoPO module
(:class:`~coin_app.algorithms.spec.CoordinatedActorModule`) is evaluated as its ``eval_lcf``
says: by default every vehicle draws its own LCF from the learned distribution
(:class:`~coin_app.adapters.lcf.SampledLCFPolicy`, as CoPO's evaluation did), or every vehicle
gets the learned mean (the deterministic actor, the mean folded in).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.adapters.lcf import SampledLCFPolicy
from coin_app.algorithms.checkpoint_files import ACTOR_ONLY, MODULE_PATH, contents_of, read_metadata
from coin_app.algorithms.ppo_family.rl_module import PPOActorModule
from coin_app.algorithms.spec import LCF_MODES, ActorModule, CoordinatedActorModule
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.rollout import AgentPolicy, Policy
from coin_app.sim.scenarios import config_from_dict


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
    """The shared RLModule stored in a coin_app checkpoint; a ValueError for an actor-only copy, which has none."""
    read_metadata(checkpoint)
    if contents_of(checkpoint) == ACTOR_ONLY:
        raise ValueError(
            f"checkpoint {checkpoint} holds only its exported actor (an archived copy), not the RLModule with its critics; "
            "allowed: a whole checkpoint written by train or a sweep"
        )
    return actor_module(RLModule.from_checkpoint(str(Path(checkpoint).resolve().joinpath(*MODULE_PATH))))


def lcf_mode(module: Any, lcf: str | None = None) -> str | None:
    """How a module's evaluation gives vehicles their LCF: ``lcf`` or the module's ``evaluation_lcf``; None without LCFs."""
    if not isinstance(module, CoordinatedActorModule):
        return None
    mode = module.evaluation_lcf() if lcf is None else lcf
    if mode not in LCF_MODES:
        raise ValueError(f"bad LCF mode {mode!r}; allowed: {', '.join(LCF_MODES)}")
    return mode


def actor_policy(module: Any, lcf: str | None = None, lcf_seed: int = 0) -> Policy | AgentPolicy:
    """A module's evaluation policy: its deterministic actor as a numpy function (N, obs_dim) -> (N, 2).

    CoPO: ``lcf`` (default: the module's ``evaluation_lcf``) ``"sampled"`` gives a
    :class:`~coin_app.adapters.lcf.SampledLCFPolicy` (one LCF per vehicle, drawn with ``lcf_seed``),
    ``"mean"`` the mean-LCF actor. Other modules ignore ``lcf``.
    """
    module = actor_module(module)
    if lcf_mode(module, lcf) == "sampled":
        mean, std = module.lcf_distribution()
        return SampledLCFPolicy(network_policy(module.lcf_actor()), mean, std, lcf_seed)
    return network_policy(module.deterministic_actor())


def export_actor(module: Any) -> tuple[torch.nn.Module, Callable[[np.ndarray], np.ndarray], dict[str, Any]]:
    """What ``export`` writes of a module: the network, the module's own actions on that network's inputs, and extra metadata.

    The actions are the export's parity reference. A CoPO module evaluated with sampled LCFs
    exports its actor on ``[obs | LCF feature]`` with ``{"lcf": {"mean", "std", "seed"}}``, from
    which evaluation draws each vehicle's LCF again (the same draws as the checkpoint's); any other
    module exports its deterministic actor on the plain observation and no extra metadata.
    """
    module = actor_module(module)
    if lcf_mode(module) == "sampled":
        mean, std = module.lcf_distribution()

        def reference(obs: np.ndarray) -> np.ndarray:
            with torch.no_grad():
                return module.lcf_inference_actions(torch.as_tensor(np.asarray(obs, dtype=np.float32))).numpy()

        return module.lcf_actor(), reference, {"lcf": {"mean": mean, "std": std, "seed": 0}}
    return module.deterministic_actor(), lambda obs: inference_actions(module, obs), {}


def export_metadata(meta: dict[str, Any], extra: dict[str, Any], checkpoint: str) -> dict[str, Any]:
    """What an exported actor file records: the checkpoint's algorithm, scenario, seed and env config, ``export_actor``'s
    extra metadata, and the checkpoint's name as given (no machine path unless given one)."""
    return {k: meta[k] for k in ("algo", "scenario", "seed", "env_config") if k in meta} | extra | {"checkpoint": checkpoint}


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


def load_checkpoint_policy(checkpoint: Path, lcf: str | None = None) -> Policy | AgentPolicy:
    """The checkpoint's evaluation policy (``actor_policy``): its deterministic actor, CoPO's with each vehicle's LCF."""
    return actor_policy(load_module(checkpoint), lcf)
