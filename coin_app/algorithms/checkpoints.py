"""Checkpoint metadata and Ray-light policy loading for evaluation.

``train`` writes ``coin_app.json`` into every checkpoint directory it saves: the algorithm,
scenario, scenario overrides and seed, so a checkpoint is self-describing. ``load_policy``
returns the deterministic actor of a checkpoint as a numpy function ``(N, obs) -> (N, 2)``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.sim.config import ScenarioConfig, config_from_dict

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


def scenario_of(checkpoint: Path, **overrides: Any) -> ScenarioConfig:
    """The scenario config a checkpoint was trained on, with ``overrides`` (e.g. num_agents) applied."""
    meta = read_metadata(checkpoint)
    return config_from_dict(meta["scenario"], {**meta.get("env_config", {}), **overrides})


def deterministic_actor(module: Any) -> Any:
    """The observation -> action network of a trained module as a plain torch ``nn.Sequential``.

    CIG-TD3 / ITD3: the tanh actor. PPO family: the Gaussian policy's mean (actor encoder and
    ``pi`` head, the head cut to the mean outputs), clipped to the action bounds [-1, 1] as the
    env clips actions. CoPO: its policy reads the agent's LCF as a last observation feature; the
    actor returned takes the plain observation and acts with the learned mean LCF (a constant
    folded into the first layer's bias), so it runs in any evaluation env.
    """
    import torch
    from torch import nn

    if hasattr(module, "actor"):
        return module.actor.net
    if hasattr(module, "encoder") and hasattr(module, "pi"):
        enc = getattr(module.encoder, "actor_encoder", module.encoder)
        layers = [*enc.net.mlp, *module.pi.net.mlp]
        last = layers[-1]
        if not isinstance(last, nn.Linear):
            raise ValueError(f"cannot extract a deterministic actor: the policy head ends in {last!r}")
        act_dim = last.out_features // 2
        mean = nn.Linear(last.in_features, act_dim)
        with torch.no_grad():
            mean.weight.copy_(last.weight[:act_dim])
            mean.bias.copy_(last.bias[:act_dim])
        layers = [*layers[:-1], mean, nn.Hardtanh(-1.0, 1.0)]
        if hasattr(module, "lcf_params"):
            layers[0] = _fold_lcf(layers[0], module.lcf_distribution()[0])
        return nn.Sequential(*layers).eval()
    raise ValueError(f"cannot extract a deterministic actor from {type(module).__name__}")


def _fold_lcf(first: Any, lcf: float) -> Any:
    """A copy of ``first`` (Linear on [obs, LCF feature]) acting on obs alone with the LCF feature fixed."""
    import torch
    from torch import nn

    from coin_app.adapters.lcf import encode

    if not isinstance(first, nn.Linear):
        raise ValueError(f"cannot fold the LCF into {first!r}; expected a Linear first layer")
    folded = nn.Linear(first.in_features - 1, first.out_features)
    with torch.no_grad():
        folded.weight.copy_(first.weight[:, :-1])
        folded.bias.copy_(first.bias + first.weight[:, -1] * float(encode(lcf)))
    return folded


def inference_actions(module: Any, obs: np.ndarray) -> np.ndarray:
    """The actions (N, act_dim) of the module's own ``forward_inference`` on ``obs``, as the env applies them.

    CIG-TD3 / ITD3 return actions; the PPO family returns Gaussian inputs, whose deterministic
    action is the mean, clipped to [-1, 1] as the env clips; CoPO's module reads the learned
    mean LCF feature appended to each observation.
    """
    import torch
    from ray.rllib.core.columns import Columns

    x = torch.as_tensor(np.asarray(obs, dtype=np.float32))
    if hasattr(module, "lcf_params"):
        from coin_app.adapters.lcf import encode

        x = torch.cat([x, torch.full((len(x), 1), float(encode(module.lcf_distribution()[0])))], dim=1)
    with torch.no_grad():
        out = module.forward_inference({Columns.OBS: x})
    if Columns.ACTIONS in out:
        return out[Columns.ACTIONS].numpy()
    inputs = out[Columns.ACTION_DIST_INPUTS]
    return inputs[:, : inputs.shape[1] // 2].clamp(-1.0, 1.0).numpy()


def load_module(checkpoint: Path) -> Any:
    """The shared RLModule stored in a coin_app checkpoint."""
    from ray.rllib.core.rl_module.rl_module import RLModule

    read_metadata(checkpoint)
    return RLModule.from_checkpoint(str(Path(checkpoint).resolve().joinpath(*MODULE_PATH)))


def actor_policy(module: Any) -> Callable[[np.ndarray], np.ndarray]:
    """A module's deterministic actor as a numpy function (N, obs_dim) -> (N, 2)."""
    import torch

    actor = deterministic_actor(module).eval()

    def policy(obs: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return actor(torch.as_tensor(np.asarray(obs, dtype=np.float32))).numpy()

    return policy


def load_policy(checkpoint: Path) -> Callable[[np.ndarray], np.ndarray]:
    """The checkpoint's deterministic actor as a numpy function (N, obs_dim) -> (N, 2)."""
    return actor_policy(load_module(checkpoint))
