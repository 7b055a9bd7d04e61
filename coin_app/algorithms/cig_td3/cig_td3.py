"""CIG-TD3 (COIN): what it adds to the TD3 family's base (``td3/``): config and algorithm (as RLlib's ``tqc.py``).

``CigTd3Config`` is ``Td3Config`` plus CIG-TD3's keys, declared once in ``settings.py`` (``CigTd3Settings``) with
the paper's defaults (COIN §5.1; where the official code differs, its value is noted, and
``docs/decisions.md`` §2.1 says which side coin_app follows): the centralized critic (twin global Q,
counterfactual baseline V, CVAE pair latents, GAT; ``critic.py``, ``pairwise.py``, ``graph.py``),
its learning rate and loss weights, and the ablation switches of COIN's Tables 5.2 and B.1-B.3.
``global_critic=False`` leaves TD3 (ITD3 is its own algorithm, ``td3/``: ``--algo itd3``).
The algorithm is ``Td3``'s (sample -> joint-step replay -> updates -> sync); the module and the
learner add the centralized critic (``rl_module.py``, ``learner.py``, ``losses.py``).

``CIG_TD3``, its :class:`~coin_app.algorithms.spec.AlgorithmSpec` entry, is in ``settings.py``.
"""

from __future__ import annotations

from typing import Any, ClassVar

from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.algorithms.cig_td3.learner import CigTd3TorchLearner
from coin_app.algorithms.cig_td3.rl_module import CigTd3TorchRLModule
from coin_app.algorithms.cig_td3.settings import CigTd3Settings
from coin_app.algorithms.td3.td3 import Td3, Td3Config, config_builder


class CigTd3Config(Td3Config):
    """Configuration of CIG-TD3 on RLlib's new API stack: TD3's with the centralized critic's keys."""

    SETTINGS: ClassVar[type[CigTd3Settings]] = CigTd3Settings
    LABEL: ClassVar[str] = "CIG-TD3"

    def __init__(self, algo_class: type | None = None):
        super().__init__(algo_class=algo_class or CigTd3)

    def combination_errors(self) -> list[str]:
        """One line per invalid combination of well-typed keys (CIG-TD3's ablation switches)."""
        errors = []
        if not self.global_critic:
            if self.counterfactual_baseline:
                errors.append("counterfactual_baseline=True needs global_critic=True (without it this is ITD3: --algo itd3)")
            if self.local_module != "none" or self.global_module != "none":
                errors.append("local_module/global_module configure the global critic; with global_critic=False set both to 'none'")
            if self.vae_weight > 0:
                errors.append("vae_weight > 0 needs global_critic=True (the CVAE lives in the global critic)")
        elif self.local_module != "cvae" and self.vae_weight > 0:
            errors.append(f"vae_weight={self.vae_weight} but local_module={self.local_module!r} has no CVAE; set vae_weight=0")
        if self.graph != "full" and self.global_module == "none":
            errors.append("a sparse graph radius needs a graph module (gat | gcn | graphsage), not global_module='none'")
        return errors

    def get_default_rl_module_spec(self) -> RLModuleSpec:
        """The CIG-TD3 torch RLModule."""
        return RLModuleSpec(module_class=CigTd3TorchRLModule)

    def get_default_learner_class(self) -> type:
        """The CIG-TD3 torch Learner."""
        return CigTd3TorchLearner

    @property
    def _model_config_auto_includes(self) -> dict[str, Any]:
        """TD3's model-config entries and the centralized critic's."""
        return super()._model_config_auto_includes | {
            "latent_dim": self.latent_dim,
            "node_width": self.node_width,
            "gat_heads": self.gat_heads,
            "gat_init": self.gat_init,
            "global_critic": self.global_critic,
            "counterfactual_baseline": self.counterfactual_baseline,
            "local_module": self.local_module,
            "global_module": self.global_module,
            "graph_radius": None if self.graph == "full" else float(self.graph),
        }


class CigTd3(Td3):
    """Counterfactual individual-global TD3 (COIN) with a shared policy for all agents: TD3's loop with CIG-TD3's module and learner."""

    @classmethod
    def get_default_config(cls) -> CigTd3Config:
        """A default ``CigTd3Config``."""
        return CigTd3Config()


build_cig_td3_config = config_builder(CigTd3Config)  # CIG-TD3's spec (settings.py) names it
