"""CIG-TD3 (COIN): what it adds to the TD3 family's base (``td3/``): config, algorithm and spec in one file (as RLlib's ``tqc.py``).

``CigTd3Config`` is ``Td3Config`` plus CIG-TD3's keys, documented once in ``HYPERPARAMETERS`` with
the paper's defaults (COIN §5.1; where the official code differs, its value is noted, and
``docs/decisions.md`` §2.1 says which side coin_app follows): the centralized critic (twin global Q,
counterfactual baseline V, CVAE pair latents, GAT; ``critic.py``, ``pairwise.py``, ``graph.py``),
its learning rate and loss weights, and the ablation switches of COIN's Tables 5.2 and B.1-B.3.
``global_critic=False`` leaves TD3 (ITD3 is its own algorithm, ``td3/``: ``--algo itd3``).
The algorithm is ``Td3``'s (sample -> joint-step replay -> updates -> sync); the module and the
learner add the centralized critic (``rl_module.py``, ``learner.py``, ``losses.py``).

``CIG_TD3`` is its :class:`~coin_app.algorithms.spec.AlgorithmSpec` entry.
"""

from __future__ import annotations

from typing import Any, ClassVar

from ray.rllib.core.rl_module.rl_module import RLModuleSpec

from coin_app.algorithms.cig_td3.learner import CigTd3TorchLearner
from coin_app.algorithms.cig_td3.rl_module import CigTd3TorchRLModule
from coin_app.algorithms.spec import AlgorithmSpec, Capabilities
from coin_app.algorithms.td3 import td3
from coin_app.algorithms.td3.td3 import Td3, Td3Config, config_builder

# name -> (default, meaning): TD3's keys and CIG-TD3's; the single source of the documentation and of training() kwargs
HYPERPARAMETERS: dict[str, tuple[Any, str]] = {
    **td3.HYPERPARAMETERS,
    "critic_lr": (3e-4, "Adam learning rate of the twin local critics"),
    "central_critic_lr": (3e-4, "Adam learning rate of the centralized critic: twin global Q, baseline V and CVAE (official 2e-4)"),
    "tau": (0.005, "soft target update rate of actor, local and global critics"),
    "hidden": (256, "width of actor, local-critic and CVAE layers"),
    "precision": (
        "bf16",
        "learner update precision: bf16 | fp32 (bf16: every loss forward pass under torch.autocast bfloat16; parameters, "
        "optimizer state, TD targets, loss reductions and soft updates stay fp32; 0.37x the fp32 update time at the paper's "
        "sizes on this CPU, no loss of success at equal env steps: docs/studies/learning_curves_precision)",
    ),
    "global_critic": (True, "use the centralized critic (False: TD3's losses only; ITD3 is --algo itd3)"),
    "counterfactual_baseline": (True, "subtract the counterfactual baseline V in the actor loss (Eq. 12)"),
    "local_module": ("cvae", "pairwise interaction module: cvae | attention (Table B.1) | none (w/o VAE)"),
    "global_module": ("gat", "global interaction module: gat | gcn | graphsage | none (w/o GAT: mean-pool)"),
    "graph": ("full", "'full' graph, or a radius in metres for a sparse graph (Tables B.2/B.3: 40)"),
    "global_weight": (1.0, "weight of the global term in the actor loss (paper 1.0; official 0.8)"),
    "vae_weight": (1.0, "weight of the CVAE loss in the centralized-critic loss (official 0.01)"),
    "kl_beta": (1.0, "weight of the KL term inside the CVAE loss"),
    "latent_dim": (20, "CVAE latent size"),
    "node_width": (128, "GAT node feature width"),
    "gat_heads": (2, "heads of the first GAT layer, concatenated (official code 2; the paper is silent; 1 before coin_app 0.2)"),
    "gat_init": ("xavier", "GAT weight initialization: xavier (gain 1.414, official code) | default (torch Linear, before 0.2)"),
}


class CigTd3Config(Td3Config):
    """Configuration of CIG-TD3 on RLlib's new API stack: TD3's with the centralized critic's keys."""

    HYPERPARAMETERS: ClassVar[dict[str, tuple[Any, str]]] = HYPERPARAMETERS
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


# ---------------------------------------------------------------------- the spec (algorithm contract)
# the quick scenario: TD3's small settings, and the centralized critic's widths and rate
QUICK_CIG_TD3: dict[str, Any] = {**td3.QUICK_TD3, "latent_dim": 8, "node_width": 16, "central_critic_lr": 1e-3}
# the smallest scale: TD3's, and the centralized critic's widths
TINY_CIG_TD3: dict[str, Any] = {**td3.TINY_TD3, "latent_dim": 4, "node_width": 8}

CIG_TD3 = AlgorithmSpec(
    name="cig_td3",
    description="COIN: CIG-TD3 with the interaction-aware centralized critic",
    hyperparameters={**HYPERPARAMETERS, **td3.RLLIB_KEYS},
    build=config_builder(CigTd3Config),
    capabilities=Capabilities(on_policy=False, centralized_critic=True, joint_replay=True, periodic_evaluation=True),
    quick=QUICK_CIG_TD3,
    tiny=TINY_CIG_TD3,
)
