"""The algorithm contract: what every algorithm package exports, as BenchMARL's ``Algorithm`` base declares it.

Each package under ``coin_app/algorithms/`` declares one :class:`AlgorithmSpec` per algorithm it
holds, in its Ray-free ``settings.py`` beside the settings class and presets. The spec says what
the algorithm is, its settings (the ``--set`` keys), the scenarios it trains on, its
capabilities, and names the function that builds its RLlib config from a typed scenario config
(``"module:function"``, imported only when a config is built, so the registry, the command
line's checks and ``config`` need neither Ray nor torch). Its RLModule implements
:class:`ActorModule`, so evaluation and export never guess by attribute.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

from coin_app.algorithms.checks import Rule
from coin_app.algorithms.choices import LCF_MODES  # noqa: F401 (re-exported)
from coin_app.algorithms.settings import Settings
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.scenes import DRIVING_SCENARIOS as SCENE_NAMES

if TYPE_CHECKING:  # annotations only: the contract itself imports neither Ray nor torch
    import torch
    from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
    from torch import nn

DRIVING_SCENARIOS = SCENE_NAMES  # re-exported for the algorithm packages

AnyScenarioConfig = ScenarioConfig | ArenaConfig
# (typed scenario config, the algorithm's --set values, seed) -> a validated RLlib config
ConfigBuilder = Callable[[AnyScenarioConfig, dict[str, Any], int], "AlgorithmConfig"]


@dataclass(frozen=True)
class Capabilities:
    """What an algorithm is, in the terms the rest of the system needs."""

    on_policy: bool  # learns from fresh rollouts (PPO family), not from a replay buffer
    centralized_critic: bool  # a critic reads other agents' data (global state or neighbours)
    joint_replay: bool  # replays whole joint env steps with the global state (the CIG-TD3 family)
    periodic_evaluation: bool = False  # has eval_every / eval_episodes: training evaluates it on validation seeds


def _no_scenario_defaults(algo_cfg: Mapping[str, Any]) -> dict[str, Any]:
    """No scenario values of the algorithm's own."""
    return {}


@dataclass(frozen=True)
class AlgorithmSpec:
    """One trainable algorithm: its name, what it is, its ``--set`` keys and how to build its RLlib config."""

    name: str
    description: str
    build: ConfigBuilder | str  # the builder, or "package.module:function" imported when a config is built
    capabilities: Capabilities
    settings: type[Settings]  # every --set key of the algorithm, declared once (coin_app.algorithms.settings)
    presets: Mapping[str, Settings] = field(default_factory=dict)  # values of ``settings``: paper, quick, smoke, reduced, dense, tiny
    scenarios: tuple[str, ...] = DRIVING_SCENARIOS
    # scenario values the algorithm sets beneath the user's --set (nav_ppo's stage mix), from its --set values
    scenario_defaults: Callable[[Mapping[str, Any]], dict[str, Any]] = _no_scenario_defaults

    @property
    def hyperparameters(self) -> dict[str, tuple[Any, str]]:
        """``--set`` key -> (default, meaning), from the settings class."""
        return self.settings.hyperparameters()

    @property
    def family(self) -> str:
        """``"ppo"`` (on-policy: the PPO family) or ``"td3"`` (the TD3 family): what a sweep scale's per-family budget names."""
        return "ppo" if self.capabilities.on_policy else "td3"

    @property
    def quick(self) -> dict[str, Any]:
        """The ``quick`` preset's changes from the defaults (the small networks of ``--quick`` and the learning curves)."""
        return self.presets["quick"].changes() if "quick" in self.presets else {}

    @property
    def tiny(self) -> dict[str, Any]:
        """The ``tiny`` preset's changes: the smallest settings that build, update and checkpoint in seconds (tests)."""
        return self.presets["tiny"].changes() if "tiny" in self.presets else {}

    def keys(self) -> tuple[str, ...]:
        """The algorithm's ``--set`` keys."""
        return tuple(self.hyperparameters)

    def rule(self, key: str) -> Rule | None:
        """The rule of ``key``'s values (its declaration's in the settings class); None for a key the class does not declare."""
        decl = self.settings.declarations().get(key)
        return decl.rule if decl is not None else None

    def value_errors(self, values: Mapping[str, Any]) -> list[str]:
        """The one-line message of every bad value in ``values`` (keys without a rule pass)."""
        errors = []
        for key, value in values.items():
            rule = self.rule(key)
            if rule is not None and not rule.accepts(value):
                errors.append(f"bad value for {key!r}: {value!r}; allowed: {rule.allowed()}")
        return errors

    def build_config(self, scenario: AnyScenarioConfig, algo_cfg: Mapping[str, Any], seed: int) -> AlgorithmConfig:
        """The RLlib config of this algorithm on ``scenario`` with ``algo_cfg`` (its own keys only) and ``seed``."""
        build = self.build
        if isinstance(build, str):
            module, _, name = build.partition(":")
            build = getattr(importlib.import_module(module), name)
        return build(scenario, dict(algo_cfg), seed)


@runtime_checkable
class ActorModule(Protocol):
    """What evaluation and export need of a trained RLModule: its deterministic policy."""

    def deterministic_actor(self) -> nn.Module:
        """A plain torch network mapping observations (N, obs_dim) to env actions (N, 2) in [-1, 1]."""
        ...

    def inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The env actions (N, 2) of the module's own ``forward_inference`` on ``obs`` (the export parity reference)."""
        ...


@runtime_checkable
class CoordinatedActorModule(ActorModule, Protocol):
    """An ``ActorModule`` whose policy also reads a per-vehicle local coordination factor (CoPO's LCF).

    Its ``deterministic_actor`` acts with the learned mean LCF; evaluation and export use the
    network on ``[obs | LCF feature]`` and give each vehicle its LCF as ``evaluation_lcf`` says.
    """

    def lcf_actor(self) -> nn.Module:
        """A plain torch network mapping ``[obs | (lcf + 1) / 2]`` (N, obs_dim + 1) to env actions (N, 2)."""
        ...

    def lcf_inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The module's own ``forward_inference`` actions on ``[obs | LCF feature]`` (the parity reference of ``lcf_actor``)."""
        ...

    def lcf_distribution(self) -> tuple[float, float]:
        """The learned LCF (mean, std)."""
        ...

    def evaluation_lcf(self) -> str:
        """``"sampled"`` (one draw per vehicle from the learned distribution) or ``"mean"`` (the learned mean for all)."""
        ...
