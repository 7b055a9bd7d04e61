"""CIG-TD3 RLModule: the TD3 module (actor, individual twin critic) plus, on the learner, the centralized critic.

The full build (learner) adds ``central`` (twin global Q, counterfactual baseline V, CVAE; ``critic.py``)
unless ``global_critic=False``, and ``make_target_networks`` its ``central_target``. Env runners build
the actor only, exactly the TD3 module's (``td3/rl_module.py``: exploration, the ActorModule contract).
"""

from __future__ import annotations

import torch
from ray.rllib.core.learner.utils import make_target_network

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig
from coin_app.algorithms.td3.rl_module import Td3TorchRLModule
from coin_app.sim import schema


class CigTd3TorchRLModule(Td3TorchRLModule):
    """Actor, twin local critics and centralized critic of CIG-TD3 in one module."""

    def setup(self) -> None:
        """The TD3 module's networks; ``central`` stays None on env runners (and with ``global_critic=False``)."""
        self.central: CentralCritic | None = None
        super().setup()

    def setup_critics(self) -> None:
        """The TD3 twin critic Q^l, then (with ``global_critic``) the centralized critic from ``model_config``."""
        super().setup_critics()
        mc = self.model_config
        if mc.get("global_critic", True):
            self.central = CentralCritic(
                CentralCriticConfig(
                    obs_dim=self.obs_dim,
                    state_dim=schema.STATE_DIM,
                    act_dim=self.act_dim,
                    latent_dim=int(mc.get("latent_dim", 20)),
                    hidden=self.hidden,
                    node_width=int(mc.get("node_width", 128)),
                    local_module=mc.get("local_module", "cvae"),
                    global_module=mc.get("global_module", "gat"),
                    graph_radius=mc.get("graph_radius"),
                    gat_heads=int(mc.get("gat_heads", 2)),
                    gat_init=str(mc.get("gat_init", "xavier")),
                    position_scale=float(mc.get("position_scale", 1.0)),
                    feature_norm=bool(mc.get("critic_feature_norm", False)),
                )
            )

    def get_non_inference_attributes(self) -> list[str]:
        """Everything but the actor stays on the learner."""
        return [*super().get_non_inference_attributes(), "central", "central_target"]

    def make_target_networks(self) -> None:
        """Frozen copies of the actor, the local critics and the centralized critic."""
        super().make_target_networks()
        self.central_target = make_target_network(self.central) if self.central is not None else None

    def get_target_network_pairs(self) -> list[tuple[torch.nn.Module, torch.nn.Module]]:
        """(main, target) pairs that the learner soft-updates on policy steps."""
        pairs = super().get_target_network_pairs()
        if self.central is not None:
            pairs.append((self.central, self.central_target))
        return pairs

    def target_networks(self) -> dict[str, torch.nn.Module | None]:
        """Every target network by attribute name (None where the module has no such network): the learner checkpoints these."""
        return super().target_networks() | {"central_target": self.central_target}
