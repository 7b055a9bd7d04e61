"""CIG-TD3 RLModule: the actor (all that env runners build) plus, on the learner, the critics.

* inference-only build (env runners, export): ``actor`` only;
* full build (learner): ``actor``, twin local critics ``local_q`` and, unless ITD3, the
  centralized critic ``central`` (twin global Q, counterfactual baseline V, CVAE);
  ``make_target_networks`` adds ``actor_target``, ``local_q_target``, ``central_target``.

``_forward_inference`` is deterministic; ``_forward_exploration`` adds N(0, sigma) noise (sigma
0.05, or decaying linearly from ``exploration_noise_initial`` from ``exploration_noise_decay_start``, by
default the end of the warm-up), and during the first ``warmup_steps`` env
steps returns uniform random actions instead, drawn from the torch generator RLlib seeds, so the
warm-up is reproducible. ``t`` is the global env-step count: ``CigTd3`` hands the env runner the
exact count before every sample, so the warm-up ends exactly at ``warmup_steps`` env steps
whatever the iteration length.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.learner.utils import make_target_network
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, TargetNetworkAPI
from ray.rllib.core.rl_module.torch.torch_rl_module import TorchRLModule

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig
from coin_app.algorithms.cig_td3.individual import Actor, TwinQ
from coin_app.sim import schema


class CigTd3TorchRLModule(TorchRLModule, InferenceOnlyAPI, TargetNetworkAPI):
    """Actor, twin local critics and centralized critic of CIG-TD3 in one module."""

    def setup(self) -> None:
        """Build the networks from the spaces and ``model_config``."""
        obs_dim, act_dim, hidden = self.setup_actor()
        self.central = None
        if self.inference_only:
            return
        mc = self.model_config
        norm = bool(mc.get("critic_feature_norm", False))
        self.local_q = TwinQ(obs_dim, act_dim, (hidden, hidden), norm)
        if mc.get("global_critic", True):
            self.central = CentralCritic(
                CentralCriticConfig(
                    obs_dim=obs_dim,
                    state_dim=schema.STATE_DIM,
                    act_dim=act_dim,
                    latent_dim=int(mc.get("latent_dim", 20)),
                    hidden=hidden,
                    node_width=int(mc.get("node_width", 128)),
                    local_module=mc.get("local_module", "cvae"),
                    global_module=mc.get("global_module", "gat"),
                    graph_radius=mc.get("graph_radius"),
                    gat_heads=int(mc.get("gat_heads", 2)),
                    gat_init=str(mc.get("gat_init", "xavier")),
                    position_scale=float(mc.get("position_scale", 1.0)),
                    feature_norm=norm,
                )
            )

    def setup_actor(self) -> tuple[int, int, int]:
        """Build the actor and the exploration settings (all an env runner needs); returns (obs_dim, act_dim, hidden)."""
        mc = self.model_config
        obs_dim = int(self.observation_space.shape[0])
        act_dim = int(self.action_space.shape[0])
        hidden = int(mc.get("hidden", 256))
        self.actor = Actor(obs_dim, act_dim, (hidden,) * int(mc.get("actor_layers", 3)))
        self.exploration_noise = float(mc.get("exploration_noise", 0.05))
        noise0 = mc.get("exploration_noise_initial")
        self.exploration_noise_initial = self.exploration_noise if noise0 is None else float(noise0)
        self.exploration_noise_decay_steps = int(mc.get("exploration_noise_decay_steps", 0))
        self.warmup_steps = int(mc.get("warmup_steps", 0))
        start = mc.get("exploration_noise_decay_start")
        self.exploration_noise_decay_start = self.warmup_steps if start is None else int(start)
        return obs_dim, act_dim, hidden

    # ------------------------------------------------------------------ forward passes
    def _forward_inference(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """Deterministic actions mu(o)."""
        with torch.no_grad():
            obs = batch[Columns.OBS]
            order = canonical_order(obs)
            return {Columns.ACTIONS: unsort(self.actor(obs[order]), order)}

    def _forward_exploration(self, batch: dict[str, Any], t: int | None = None, **kwargs: Any) -> dict[str, Any]:
        """mu(o) + N(0, sigma), clipped; uniform random actions during the warm-up."""
        with torch.no_grad():
            obs = batch[Columns.OBS]
            order = canonical_order(obs)
            mu = self.actor(obs[order])
            if t is not None and t < self.warmup_steps:
                actions = torch.rand(mu.shape, device=mu.device) * 2.0 - 1.0  # on the CPU: the seeded default generator
            else:
                actions = (mu + torch.randn(mu.shape, device=mu.device) * self.noise_std(t)).clamp(-1.0, 1.0)
            return {Columns.ACTIONS: unsort(actions, order)}

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """Nothing: the learner calls the networks itself, loss by loss."""
        return {}

    def noise_std(self, t: int | None) -> float:
        """Exploration std at env step ``t``: ``exploration_noise_initial`` until the decay starts, then linear to ``exploration_noise``."""
        if t is None or self.exploration_noise_decay_steps <= 0:
            return self.exploration_noise
        frac = min(1.0, max(0.0, (t - self.exploration_noise_decay_start) / self.exploration_noise_decay_steps))
        return self.exploration_noise_initial + frac * (self.exploration_noise - self.exploration_noise_initial)

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
        return ["local_q", "central", "actor_target", "local_q_target", "central_target"]

    def make_target_networks(self) -> None:
        """Frozen copies of actor, local critics and centralized critic."""
        self.actor_target = make_target_network(self.actor)
        self.local_q_target = make_target_network(self.local_q)
        self.central_target = make_target_network(self.central) if self.central is not None else None

    def get_target_network_pairs(self) -> list[tuple[torch.nn.Module, torch.nn.Module]]:
        """(main, target) pairs that the learner soft-updates on policy steps."""
        pairs = [(self.actor, self.actor_target), (self.local_q, self.local_q_target)]
        if self.central is not None:
            pairs.append((self.central, self.central_target))
        return pairs

    def target_networks(self) -> dict[str, torch.nn.Module | None]:
        """Every target network by attribute name (None where the module has no such network): the learner checkpoints these."""
        return {"actor_target": self.actor_target, "local_q_target": self.local_q_target, "central_target": self.central_target}

    def forward_target(self, batch: dict[str, Any]) -> dict[str, Any]:
        """Target-actor actions for ``batch[OBS]`` (the losses call the target nets directly)."""
        with torch.no_grad():
            return {Columns.ACTIONS: self.actor_target(batch[Columns.OBS])}


def canonical_order(obs: torch.Tensor) -> torch.Tensor:
    """A canonical order of a batch of observations (ranks of a fixed projection of each row).

    RLlib batches the acting agents in the iteration order of a set of agent ids, which
    changes with Python's hash seed. Running the actor and drawing the noise in this order
    instead makes every agent's action independent of that order (bit for bit: BLAS results
    can depend on a row's position), so a seeded run gives the same result in every process.
    """
    n, dim = obs.shape[0], obs.shape[-1]
    weights = torch.cos(torch.arange(dim, dtype=torch.float64, device=obs.device) * 0.731) + 1.618
    return torch.argsort(obs.reshape(n, dim).to(torch.float64) @ weights, stable=True)


def unsort(rows: torch.Tensor, order: torch.Tensor) -> torch.Tensor:
    """Put rows computed in ``order`` back in the batch's original order."""
    out = torch.empty_like(rows)
    out[order] = rows
    return out
