"""TraCo (Liu et al., CoRL 2023) as COIN ran it (COIN §5.2): TD3 with a cross-attention domain critic and a counterfactual advantage.

Neither TraCo's code nor its full text is public. COIN describes it as "a cross-attention
mechanism to capture crucial information from nearby vehicles" and "a counterfactual advantage
function for credit assignment within a neighborhood range of 40 meters", re-implemented in COIN's
TD3 framework with COIN's TD3 settings (exploration std 0.05, batch 256, gamma 0.99, tau 0.005,
actor lr 2e-4, critic lr 3e-4, target noise 0.1 clipped at 0.5, policy delay 5, hidden 256).
This is that re-implementation on the TD3 family's base (``td3/``): the same joint-step replay (the
centralized-critic connector, which also gives the others' rewards), sampling, actor, exploration,
update order, checkpoints and export; only the critics and losses differ (``networks.py``,
``losses.py``). Every choice nobody has published is a documented key below, marked
"inference"; docs/guides/traco.md lists them.

``TracoConfig`` / ``Traco`` subclass ``Td3Config`` / ``Td3``; ``TRACO`` is the
:class:`~coin_app.algorithms.spec.AlgorithmSpec` entry.
"""

from __future__ import annotations

from typing import Any, ClassVar

from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.algorithms.spec import AlgorithmSpec, Capabilities
from coin_app.algorithms.td3 import td3
from coin_app.algorithms.td3.td3 import Td3, Td3Config, config_builder
from coin_app.algorithms.traco.learner import TracoTorchLearner
from coin_app.algorithms.traco.networks import DOMAIN_RADIUS
from coin_app.algorithms.traco.rl_module import TracoTorchRLModule

TRACO_PRECISION = "fp32"  # as ITD3: fp32 until a learning-curve comparison backs bf16 for this critic

# name -> (default, meaning): TD3's keys (COIN §5.1: "consistent with TD3" for ITD3, TraCo and COIN) and TraCo's;
# the single source of the documentation and of training() kwargs
HYPERPARAMETERS: dict[str, tuple[Any, str]] = {
    **td3.HYPERPARAMETERS,
    "critic_lr": (3e-4, "Adam learning rate of the twin domain critic (and of the individual critic, if any)"),
    "tau": (0.005, "soft target update rate of the actor and the domain critic (and of the individual critic, if any)"),
    "hidden": (256, "width of the actor's layers, of the attention tokens and of the critic heads (COIN's TD3 hidden size)"),
    "baseline_lr": (3e-4, "Adam learning rate of the counterfactual baseline (inference: COIN's critic rate)"),
    "precision": (TRACO_PRECISION, "learner update precision: fp32 | bf16 (fp32 until a learning-curve comparison backs bf16)"),
    # TraCo's own choices; all but the radius are inferences (no TraCo code or full text is public)
    "domain_radius": (DOMAIN_RADIUS, "metres: the ego's domain, the others strictly within it (COIN §5.2: 40 m)"),
    "domain_reward": (
        "mean",
        "inference: the domain critic's reward, mean over the ego and its domain | neighbours (mean over the domain, "
        "0 if empty: CoPO's nei_rewards) | own (the ego's reward)",
    ),
    "attention_heads": (4, "inference: heads of the cross-attention (the width is hidden, split over the heads)"),
    "token_layers": (2, "inference: layers of the ego-token MLP([o_i, a_i]) and of the neighbour-token MLP"),
    "neighbour_features": (
        "relative+absolute",
        "inference: neighbour token inputs [s_j - s_i, s_j, a_j] | absolute ([s_j, a_j], COIN style) | relative ([s_j - s_i, a_j])",
    ),
    "null_token": (True, "inference: a learned, always attendable null token (False: a fixed zero token) so an empty domain is defined"),
    "counterfactual_baseline": (
        True,
        "inference: train the baseline b (the domain critic with the ego action set to (-1, -1), COIN's released-code "
        "convention) and subtract it in the actor loss; it carries no actor gradient (logged as the advantage)",
    ),
    "individual_critic": (False, "inference: also a twin individual critic on the ego's reward, its Q^l_1 added to the actor objective"),
    "domain_weight": (1.0, "weight w of the domain term Q^D_1 - b in the actor objective"),
}


class TracoConfig(Td3Config):
    """Configuration of TraCo-TD3 on RLlib's new API stack: TD3's with TraCo's keys."""

    HYPERPARAMETERS: ClassVar[dict[str, tuple[Any, str]]] = HYPERPARAMETERS
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


# ---------------------------------------------------------------------- the spec (algorithm contract)
# the quick scenario: TD3's small settings (the freeze guard included), the baseline at the critics' rate
QUICK_TRACO: dict[str, Any] = {**td3.QUICK_TD3, "baseline_lr": td3.QUICK_TD3["critic_lr"]}
# the smallest scale: TD3's
TINY_TRACO: dict[str, Any] = dict(td3.TINY_TD3)

TRACO = AlgorithmSpec(
    name="traco",
    description="TraCo (re-implemented, TD3, per COIN §5.2): cross-attention domain critic, counterfactual advantage within 40 m",
    hyperparameters={**HYPERPARAMETERS, **td3.RLLIB_KEYS},
    build=config_builder(TracoConfig),
    capabilities=Capabilities(on_policy=False, centralized_critic=True, joint_replay=True, periodic_evaluation=True),
    quick=QUICK_TRACO,
    tiny=TINY_TRACO,
)
