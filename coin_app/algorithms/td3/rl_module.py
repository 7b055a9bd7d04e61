"""The TD3 family's RLModule (ITD3's as it is): the actor (all that env runners build) plus, on the learner, the twin critic.

* inference-only build (env runners, export): ``actor`` only;
* full build (learner): ``actor`` and the individual twin critic ``local_q``; ``make_target_networks``
  adds ``actor_target`` and ``local_q_target``. CIG-TD3 and TraCo add their critics in subclasses,
  extending the lists of learner-only attributes and target networks.

``_forward_inference`` is deterministic; ``_forward_exploration`` follows ``exploration.py`` (uniform
random actions for the first ``warmup_steps`` env steps, then Gaussian noise on its schedule). ``t`` is
the global env-step count: the algorithm hands the env runner the exact count before every sample,
so the warm-up ends exactly at ``warmup_steps`` env steps whatever the iteration length.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.torch.torch_rl_module import TorchRLModule

from coin_app.algorithms.td3.exploration import Exploration, canonical_order, unsort
from coin_app.algorithms.td3.networks import Actor, TwinQ


class Td3TorchRLModule(TorchRLModule, InferenceOnlyAPI, TargetNetworkAPI):
    """The shared actor and the individual twin critic of TD3 (ITD3) in one module; the base of the family's modules."""

    def setup(self) -> None:
        """Build the actor and its exploration, then (unless inference-only) the twin critic, from the spaces and ``model_config``."""
        mc = self.model_config
        self.obs_dim = int(self.observation_space.shape[0])
        self.act_dim = int(self.action_space.shape[0])
        self.hidden = int(mc.get("hidden", 256))
        self.actor = Actor(self.obs_dim, self.act_dim, (self.hidden,) * int(mc.get("actor_layers", 3)))
        self.exploration = Exploration.from_model_config(mc)
        self.local_q = None
        if not self.inference_only:
            self.setup_critics()

    def setup_critics(self) -> None:
        """The learner-only networks: the individual twin critic Q^l (children add or replace theirs)."""
        self.local_q = TwinQ(
            self.obs_dim, self.act_dim, (self.hidden, self.hidden), bool(self.model_config.get("critic_feature_norm", False))
        )

    # ------------------------------------------------------------------ forward passes
    def _forward_inference(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """Deterministic actions mu(o)."""
        with torch.no_grad():
            obs = batch[Columns.OBS]
            order = canonical_order(obs)
            return {Columns.ACTIONS: unsort(self.actor(obs[order]), order)}

    def _forward_exploration(self, batch: dict[str, Any], t: int | None = None, **kwargs: Any) -> dict[str, Any]:
        """mu(o) + N(0, sigma(t)), clipped; uniform random actions during the warm-up (``exploration.py``)."""
        with torch.no_grad():
            obs = batch[Columns.OBS]
            order = canonical_order(obs)
            return {Columns.ACTIONS: unsort(self.exploration.actions(self.actor(obs[order]), t), order)}

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """Nothing: the learner calls the networks itself, loss by loss."""
        return {}

    def noise_std(self, t: int | None) -> float:
        """The exploration std at env step ``t`` (``Exploration.noise_std``)."""
        return self.exploration.noise_std(t)

    # ------------------------------------------------------------------ the algorithm contract (ActorModule)
    def deterministic_actor(self) -> torch.nn.Module:
        """The tanh actor mu(o) as a plain ``nn.Sequential`` on the CPU (evaluation and export; a copy if the module is on a GPU)."""
        net = self.actor.net
        return net if next(net.parameters()).device.type == "cpu" else copy.deepcopy(net).cpu()

    def inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The env actions of ``forward_inference`` on ``obs`` (already in [-1, 1]), on ``obs``'s device."""
        device = next(self.actor.parameters()).device
        with torch.no_grad():
            return self.forward_inference({Columns.OBS: obs.to(device)})[Columns.ACTIONS].to(obs.device)

    # ------------------------------------------------------------------ APIs
    def get_non_inference_attributes(self) -> list[str]:
        """Everything but the actor stays on the learner."""
        return ["local_q", "actor_target", "local_q_target"]

    def make_target_networks(self) -> None:
        """Frozen copies of the actor and the twin critic."""
        self.actor_target = make_target_network(self.actor)
        self.local_q_target = make_target_network(self.local_q) if self.local_q is not None else None

    def get_target_network_pairs(self) -> list[tuple[torch.nn.Module, torch.nn.Module]]:
        """(main, target) pairs that the learner soft-updates on policy steps."""
        pairs = [(self.actor, self.actor_target)]
        if self.local_q is not None:
            pairs.append((self.local_q, self.local_q_target))
        return pairs

    def target_networks(self) -> dict[str, torch.nn.Module | None]:
        """Every target network by attribute name (None where the module has no such network): the learner checkpoints these."""
        return {"actor_target": self.actor_target, "local_q_target": self.local_q_target}

    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Target-actor actions for ``batch[OBS]`` (the losses call the target nets directly)."""
        with torch.no_grad():
            return {Columns.ACTIONS: self.actor_target(batch[Columns.OBS])}
