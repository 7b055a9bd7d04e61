"""The RLModule of the PPO family: RLlib's default PPO module with the ``ActorModule`` contract of ``spec.py``.

The policy is a Gaussian whose ``pi`` head outputs (mean, log std) per action dimension. The
deterministic policy is its mean, clipped to the action bounds [-1, 1] as the env clips
actions; ``deterministic_actor`` gives it as a plain torch network (actor encoder, then the
``pi`` head cut to the mean outputs, then ``Hardtanh``) for evaluation and export, and
``inference_actions`` gives the same actions from RLlib's own ``forward_inference``, the
reference the export's parity check compares against.

Initialization (``model_config["weight_init"]``): ``"normc"`` is Ray 1.x's, the one the CoPO
paper's PPO baselines started from (``docs/decisions.md`` §7.2): every linear layer's bias is 0
and each output unit's incoming weights are a Gaussian vector scaled to norm 1 in hidden layers
and to norm 0.01 in output layers (the policy's (mean, log std) head and every value head), so
the initial Gaussian means are within ``0.01 ||h||`` of 0 and the log stds near 0. A missing key
or ``"torch"`` keeps PyTorch's default (nav_ppo, modules saved before the key). ``model_config["log_std_init"]``
(nav_ppo) is then added to the bias of the head's log-std outputs, so the initial action std is about
``e^log_std_init`` (0 or missing: unchanged). ``model_config["log_std_min"]`` (nav_ppo) floors the
log-std outputs of every forward pass (train, exploration, inference) at that value, so the action
std never falls below ``e^log_std_min`` (None or missing: no floor); below the floor the log std
gets no gradient, as in SAC's clamp (Haarnoja et al. 2018).

Outputs are fp32 whatever the autocast (``precision.py``): under a bf16 learner update the
layers compute in bf16, and ``forward_train``'s Gaussian inputs and ``compute_values``' values
leave the module as fp32 (subclasses' value heads too), so every loss is computed in fp32.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from ray.rllib.algorithms.ppo.torch.default_ppo_torch_rl_module import DefaultPPOTorchRLModule
from ray.rllib.core.columns import Columns
from torch import nn

from coin_app.algorithms.ppo_family.precision import full_precision

NORMC_OUTPUT_STD = 0.01  # norm of an output unit's weights under normc (Ray 1.x's fcnet: logits and value_out)


def normc_(layer: nn.Linear, std: float) -> None:
    """Ray 1.x's normc initialization in place: each output unit's weights N(0, 1) scaled to norm ``std``; bias 0."""
    with torch.no_grad():
        weight = torch.randn_like(layer.weight)
        layer.weight.copy_(weight * (std / weight.norm(dim=1, keepdim=True)))
        layer.bias.zero_()


def normc_init(module: nn.Module) -> None:
    """normc on every linear layer of ``module``'s MLPs: norm 1 if an activation follows it in its ``nn.Sequential``, else 0.01."""
    for seq in module.modules():
        if not isinstance(seq, nn.Sequential):
            continue
        layers = list(seq)
        for i, layer in enumerate(layers):
            if isinstance(layer, nn.Linear):
                hidden = i + 1 < len(layers) and not isinstance(layers[i + 1], nn.Linear)
                normc_(layer, 1.0 if hidden else NORMC_OUTPUT_STD)


def gaussian_mean(head: nn.Linear) -> nn.Linear:
    """A copy of the first half of ``head``'s outputs (the Gaussian mean of (mean, log std) inputs)."""
    act_dim = head.out_features // 2
    mean = nn.Linear(head.in_features, act_dim)
    with torch.no_grad():
        mean.weight.copy_(head.weight[:act_dim])
        mean.bias.copy_(head.bias[:act_dim])
    return mean


class PPOActorModule(DefaultPPOTorchRLModule):
    """RLlib's default PPO module whose deterministic policy is the Gaussian mean clipped to [-1, 1]."""

    def setup(self) -> None:
        """Build RLlib's networks and the subclass's extra heads, then initialize them all by ``weight_init``."""
        super().setup()
        self.setup_heads()
        if self.model_config.get("weight_init", "torch") == "normc":
            normc_init(self)
        shift = float(self.model_config.get("log_std_init", 0.0))
        if shift:  # the policy head's log-std outputs start near ``shift`` (nav_ppo's option): an initial std of about e^shift
            head = self.pi.net.mlp[-1]
            with torch.no_grad():
                head.bias[head.out_features // 2 :] += shift

    def setup_heads(self) -> None:
        """Build a subclass's extra networks (before the initialization); none here."""

    def floored(self, inputs: torch.Tensor) -> torch.Tensor:
        """Gaussian inputs (mean, log std) with the log std clamped from below at ``log_std_min`` (unchanged without one)."""
        floor = self.model_config.get("log_std_min")
        if floor is None:
            return inputs
        mean, log_std = inputs.chunk(2, dim=-1)
        return torch.cat([mean, log_std.clamp(min=float(floor))], dim=-1)

    def _forward(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """RLlib's inference and exploration forward pass, with the log-std floor."""
        out = super()._forward(batch, **kwargs)
        out[Columns.ACTION_DIST_INPUTS] = self.floored(out[Columns.ACTION_DIST_INPUTS])
        return out

    def _forward_train(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        """RLlib's train forward pass, with the Gaussian inputs in fp32 and the log-std floor."""
        out = super()._forward_train(batch, **kwargs)
        out[Columns.ACTION_DIST_INPUTS] = self.floored(full_precision(out[Columns.ACTION_DIST_INPUTS]))
        return out

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        """RLlib's V(o) of shape (B,), in fp32."""
        return full_precision(super().compute_values(batch, embeddings))

    def deterministic_actor(self) -> nn.Sequential:
        """The actor encoder and the ``pi`` head's mean outputs, then ``Hardtanh(-1, 1)``, as an ``nn.Sequential`` on the CPU.

        On the CPU its layers are the module's own; a module on another device (a GPU learner's) gives a CPU copy.
        """
        encoder = getattr(self.encoder, "actor_encoder", self.encoder)
        layers = [*encoder.net.mlp, *self.pi.net.mlp]
        head = layers[-1]
        if not isinstance(head, nn.Linear):
            raise ValueError(f"cannot extract a deterministic actor: the policy head ends in {head!r}")
        if head.weight.device.type != "cpu":
            layers = [copy.deepcopy(layer).cpu() for layer in layers]
            head = layers[-1]
        return nn.Sequential(*layers[:-1], gaussian_mean(head), nn.Hardtanh(-1.0, 1.0)).eval()

    def inference_actions(self, obs: torch.Tensor) -> torch.Tensor:
        """The mean of ``forward_inference``'s Gaussian inputs on ``obs``, clamped to [-1, 1], on ``obs``'s device."""
        device = next(self.pi.parameters()).device
        with torch.no_grad():
            inputs = self.forward_inference({Columns.OBS: obs.to(device)})[Columns.ACTION_DIST_INPUTS]
        return inputs[:, : inputs.shape[1] // 2].clamp(-1.0, 1.0).to(obs.device)
