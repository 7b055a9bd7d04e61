"""TraCo-TD3 RLModule: CIG-TD3's actor and exploration (all that env runners build) plus, on the learner, the domain critics.

* inference-only build (env runners, export): ``actor`` only, exactly CIG-TD3's (decentralized execution);
* full build (learner): ``domain_q`` (twin cross-attention domain critic), ``baseline`` (the
  counterfactual baseline, unless ``counterfactual_baseline=False``) and ``local_q`` (CIG-TD3's twin
  individual critic, only with ``individual_critic=True``); ``make_target_networks`` adds
  ``actor_target``, ``domain_q_target`` and ``local_q_target``. The baseline regresses on the domain
  target y^D, which the domain critic's target network gives, so it has no target network of its own.
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.learner.utils import make_target_network

from coin_app.algorithms.cig_td3.individual import TwinQ
from coin_app.algorithms.cig_td3.rl_module import CigTd3TorchRLModule
from coin_app.algorithms.traco.networks import CounterfactualBaseline, DomainCritic
from coin_app.sim import schema


class TracoTorchRLModule(CigTd3TorchRLModule):
    """Actor, twin domain critic, counterfactual baseline and optional individual critic of TraCo-TD3."""

    def setup(self) -> None:
        """Build the networks from the spaces and ``model_config``."""
        obs_dim, act_dim, hidden = self.setup_actor()
        self.central = None  # CIG-TD3's centralized critic: not part of TraCo
        self.domain_q = self.baseline = self.local_q = None
        if self.inference_only:
            return
        mc = self.model_config
        attention: dict[str, Any] = {
            "heads": int(mc.get("attention_heads", 4)),
            "token_layers": int(mc.get("token_layers", 2)),
            "neighbour_features": str(mc.get("neighbour_features", "relative+absolute")),
            "null_token": bool(mc.get("null_token", True)),
        }
        self.domain_q = DomainCritic(obs_dim, schema.STATE_DIM, act_dim, hidden, **attention)
        if mc.get("counterfactual_baseline", True):
            self.baseline = CounterfactualBaseline(obs_dim, schema.STATE_DIM, act_dim, hidden, **attention)
        if mc.get("individual_critic", False):
            self.local_q = TwinQ(obs_dim, act_dim, (hidden, hidden), bool(mc.get("critic_feature_norm", False)))

    def get_non_inference_attributes(self) -> list[str]:
        """Everything but the actor stays on the learner."""
        return ["domain_q", "baseline", "local_q", "actor_target", "domain_q_target", "local_q_target"]

    def make_target_networks(self) -> None:
        """Frozen copies of the actor, the domain critic and (if any) the individual critic."""
        self.actor_target = make_target_network(self.actor)
        self.domain_q_target = make_target_network(self.domain_q)
        self.local_q_target = make_target_network(self.local_q) if self.local_q is not None else None

    def get_target_network_pairs(self) -> list[tuple[torch.nn.Module, torch.nn.Module]]:
        """(main, target) pairs that the learner soft-updates on policy steps."""
        pairs = [(self.actor, self.actor_target), (self.domain_q, self.domain_q_target)]
        if self.local_q is not None:
            pairs.append((self.local_q, self.local_q_target))
        return pairs

    def target_networks(self) -> dict[str, torch.nn.Module | None]:
        """Every target network by attribute name (None where absent): the learner checkpoints these."""
        return {"actor_target": self.actor_target, "domain_q_target": self.domain_q_target, "local_q_target": self.local_q_target}
