"""TraCo (Liu et al., CoRL 2023) as COIN ran it (COIN §5.2): TD3 with a cross-attention domain critic and a counterfactual advantage.

Neither TraCo's code nor its full text is public. COIN describes it as "a cross-attention
mechanism to capture crucial information from nearby vehicles" and "a counterfactual advantage
function for credit assignment within a neighborhood range of 40 meters", re-implemented in COIN's
TD3 framework with COIN's TD3 settings (exploration std 0.05, batch 256, gamma 0.99, tau 0.005,
actor lr 2e-4, critic lr 3e-4, target noise 0.1 clipped at 0.5, policy delay 5, hidden 256).
This is that re-implementation on the TD3 family's base (``td3/``): the same joint-step replay and
centralized-critic connector (which also gives the others' rewards), sampling, actor, exploration,
update order, checkpoints and export; only the critics and losses differ (``networks.py``,
``losses.py``). Every choice nobody has published is a documented key below, marked
"inference"; docs/guides/traco.md lists them.

``TracoConfig`` / ``Traco`` subclass ``Td3Config`` / ``Td3``; ``TRACO`` is the
:class:`~coin_app.algorithms.spec.AlgorithmSpec` entry.
"""

from __future__ import annotations

from typing import Any, ClassVar

from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.algorithms.td3.td3 import Td3, Td3Config, config_builder
from coin_app.algorithms.traco.learner import TracoTorchLearner
from coin_app.algorithms.traco.rl_module import TracoTorchRLModule
from coin_app.algorithms.traco.settings import TracoSettings


class TracoConfig(Td3Config):
    """Configuration of TraCo-TD3 on RLlib's new API stack: TD3's with TraCo's keys."""

    SETTINGS: ClassVar[type[TracoSettings]] = TracoSettings
    LABEL: ClassVar[str] = "TraCo"

    def __init__(self, algo_class: type | None = None):
        super().__init__(algo_class=algo_class or Traco)

    def combination_errors(self) -> list[str]:
        """One line per invalid combination of well-typed keys."""
        errors = []
        if self.hidden % self.attention_heads:
            errors.append(f"hidden={self.hidden} is not a multiple of attention_heads={self.attention_heads}")
        if self.domain_weight == 0 and not self.individual_critic:
            errors.append("domain_weight=0 without individual_critic leaves the actor no objective")
        return errors

    def get_default_rl_module_spec(self) -> RLModuleSpec:
        """The TraCo torch RLModule."""
        return RLModuleSpec(module_class=TracoTorchRLModule)

    def get_default_learner_class(self) -> type:
        """The TraCo torch Learner."""
        return TracoTorchLearner

    @property
    def _model_config_auto_includes(self) -> dict[str, Any]:
        """TD3's model-config entries and the domain critic's."""
        return super()._model_config_auto_includes | {
            "attention_heads": self.attention_heads,
            "token_layers": self.token_layers,
            "neighbour_features": self.neighbour_features,
            "null_token": self.null_token,
            "counterfactual_baseline": self.counterfactual_baseline,
            "individual_critic": self.individual_critic,
        }


class Traco(Td3):
    """TraCo-TD3: TD3's sampling, joint-step replay and update loop with TraCo's module and learner."""

    @classmethod
    def get_default_config(cls) -> TracoConfig:
        """A default ``TracoConfig``."""
        return TracoConfig()


build_traco_config = config_builder(TracoConfig)  # TraCo's spec (settings.py) names it
