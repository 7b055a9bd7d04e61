"""TraCo-TD3 RLModule: the TD3 module's actor and exploration (all that env runners build) plus, on the learner, the domain critics.

* inference-only build (env runners, export): ``actor`` only, exactly the TD3 module's (decentralized execution);
* full build (learner): ``domain_q`` (twin cross-attention domain critic), ``baseline`` (the
  counterfactual baseline, unless ``counterfactual_baseline=False``) and ``local_q`` (the TD3 twin
  individual critic, only with ``individual_critic=True``); ``make_target_networks`` adds
  ``actor_target``, ``domain_q_target`` and ``local_q_target``. The baseline regresses on the domain
  target y^D, which the domain critic's target network gives, so it has no target network of its own.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.learner.utils import make_target_network

from coin_app.algorithms.td3.rl_module import Td3TorchRLModule
from coin_app.algorithms.traco.networks import CounterfactualBaseline, DomainCritic
from coin_app.sim import schema


class TracoTorchRLModule(Td3TorchRLModule):
    """Actor, twin domain critic, counterfactual baseline and optional individual critic of TraCo-TD3."""

    def setup(self) -> None:
        """The TD3 module's actor; ``domain_q`` and ``baseline`` stay None on env runners."""
        self.domain_q: DomainCritic | None = None
        self.baseline: CounterfactualBaseline | None = None
        super().setup()

    def setup_critics(self) -> None:
        """The domain critic, the baseline (if any) and the individual critic (if any), from ``model_config``."""
        mc = self.model_config
        attention: dict[str, Any] = {
            "heads": int(mc.get("attention_heads", 4)),
            "token_layers": int(mc.get("token_layers", 2)),
            "neighbour_features": str(mc.get("neighbour_features", "relative+absolute")),
            "null_token": bool(mc.get("null_token", True)),
        }
        self.domain_q = DomainCritic(self.obs_dim, schema.STATE_DIM, self.act_dim, self.hidden, **attention)
        if mc.get("counterfactual_baseline", True):
            self.baseline = CounterfactualBaseline(self.obs_dim, schema.STATE_DIM, self.act_dim, self.hidden, **attention)
        if mc.get("individual_critic", False):
            super().setup_critics()

    def get_non_inference_attributes(self) -> list[str]:
        """Everything but the actor stays on the learner."""
        return [*super().get_non_inference_attributes(), "domain_q", "baseline", "domain_q_target"]

    def make_target_networks(self) -> None:
        """Frozen copies of the actor, the domain critic and (if any) the individual critic."""
        super().make_target_networks()
        self.domain_q_target = make_target_network(self.domain_q)

    def get_target_network_pairs(self) -> list[tuple[torch.nn.Module, torch.nn.Module]]:
        """(main, target) pairs that the learner soft-updates on policy steps."""
        return [*super().get_target_network_pairs(), (self.domain_q, self.domain_q_target)]

    def target_networks(self) -> dict[str, torch.nn.Module | None]:
        """Every target network by attribute name (None where absent): the learner checkpoints these."""
        return super().target_networks() | {"domain_q_target": self.domain_q_target}
