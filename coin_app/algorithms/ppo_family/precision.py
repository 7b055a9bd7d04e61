"""The ``precision`` learner option of the PPO family and nav_ppo: fp32, or the update's forward passes in bfloat16.

``"bf16"`` runs each SGD minibatch's ``forward_train`` and loss computation (with every value
forward inside the loss) under ``torch.autocast(<module device type>, bfloat16)``: the linear
layers compute in bf16, everything else keeps its dtype. The family's modules return their
outputs (Gaussian inputs, values) in fp32 (``full_precision``), so log-probs, the ratio, the KL,
the entropy and the value losses are computed in fp32; backward and the optimizer step run
outside autocast on the fp32 parameters. What runs outside ``_uncompiled_update`` stays fp32:
the learner connector's value predictions (GAE, old values, CoPO's advantages) and CoPO's LCF
meta-gradient step. ``"fp32"`` (the default, and a config without the key) is RLlib's update
unchanged.
"""

from __future__ import annotations

import contextlib
from typing import Any

import torch
from ray.rllib.core.learner.torch.torch_learner import TorchLearner

from coin_app.algorithms.choices import PRECISIONS  # noqa: F401 (re-exported)


def full_precision(x: torch.Tensor) -> torch.Tensor:
    """``x`` as fp32 when it is a narrower float (bf16 under autocast); an fp32 tensor is returned as it is."""
    return x.float() if x.dtype in (torch.bfloat16, torch.float16) else x


def learner_precision(learner_config_dict: dict[str, Any]) -> str:
    """The ``precision`` of a learner's ``learner_config_dict`` ("fp32" if unset); a ValueError naming a bad one."""
    precision = learner_config_dict.get("precision", "fp32")
    if precision not in PRECISIONS:
        raise ValueError(f"bad value for 'precision': {precision!r}; allowed: {', '.join(map(repr, PRECISIONS))}")
    return precision


class MixedPrecisionLearner(TorchLearner):
    """Mixin for a ``TorchLearner`` (list it first): with ``precision`` "bf16" each minibatch's forward pass and losses run in bf16."""

    precision: str = "fp32"

    def build(self) -> None:
        """Build, then read ``learner_config_dict["precision"]``."""
        super().build()
        self.precision = learner_precision(self.config.learner_config_dict)

    def autocast(self) -> contextlib.AbstractContextManager:
        """The context of the update's forward pass and losses: bfloat16 autocast on the module's device for "bf16", else none."""
        if self.precision == "fp32":
            return contextlib.nullcontext()
        return torch.autocast(device_type=torch.device(self._device).type, dtype=torch.bfloat16)

    def _uncompiled_update(self, batch: dict[str, Any], **kwargs: Any) -> tuple[Any, Any, dict[str, Any]]:
        """One minibatch step: RLlib's own for "fp32"; for "bf16" the same steps with forward + losses under autocast."""
        if self.precision == "fp32":
            return super()._uncompiled_update(batch, **kwargs)
        # TorchLearner._uncompiled_update of RLlib 2.60, with the autocast around the forward pass and the losses only
        self._compute_off_policyness(batch)
        with self.autocast():
            fwd_out = self.module.forward_train(batch)
            loss_per_module = self.compute_losses(fwd_out=fwd_out, batch=batch)
        gradients = self.compute_gradients(loss_per_module)
        with contextlib.ExitStack() as stack:
            if self.config.num_learners > 1:
                for mod in self.module.values():
                    if isinstance(mod, torch.nn.Module):  # non-torch modules have no ``no_sync``
                        stack.enter_context(mod.no_sync())
            postprocessed_gradients = self.postprocess_gradients(gradients)
            self.apply_gradients(postprocessed_gradients)
        return fwd_out, loss_per_module, {}
