"""The gradient step every learner of this project takes: fused Adam, and one finiteness check over all gradients.

RLlib 2.60's ``TorchLearner`` builds PyTorch's default Adam, which on the CPU steps one tensor at a
time, and its ``apply_gradients`` checks every gradient tensor for NaN/inf twice, each check a host
sync. For the small networks of these algorithms both are per-tensor overhead, a large share of an
update (docs/reference/speed.md). :class:`FastGradientStep` keeps RLlib's step and replaces only
these two: the fused Adam kernel (CPU and CUDA: the same update up to float rounding) and one
check over all gradients, after which the step is exactly RLlib's; a non-finite gradient still
takes RLlib's own path (its warning, the entry zeroed).
"""

from __future__ import annotations

from typing import Any

import torch
from ray.rllib.core.learner.torch.torch_learner import TorchLearner


def fused_adam(params: Any, **kwargs: Any) -> torch.optim.Adam:
    """``torch.optim.Adam`` over ``params`` with the fused kernel (every tensor in one call)."""
    return torch.optim.Adam(params, fused=True, **kwargs)


class FastGradientStep(TorchLearner):
    """Mixin for a ``TorchLearner``: fused Adam for the default optimizer, one finiteness check per gradient step."""

    def configure_optimizers_for_module(self, module_id: str, config: Any = None) -> None:
        """RLlib's default optimizer (one Adam over the module, the rate or schedule of ``config.lr``), fused."""
        params = self.get_parameters(self._module[module_id])
        self.register_optimizer(module_id=module_id, optimizer=fused_adam(params), params=params, lr_or_lr_schedule=config.lr)

    def apply_gradients(self, gradients_dict: dict[Any, torch.Tensor]) -> None:
        """RLlib's optimizer steps, after one finiteness check over all gradients instead of two per tensor.

        The check reads each gradient's sum: a NaN or an inf entry makes it NaN or inf, so a finite
        sum for every gradient means every entry is finite, and then the gradients are set and
        every optimizer steps, as RLlib would. Otherwise (a sum that overflowed included), or with
        grad scalers or lr scheduler classes, RLlib's own method runs.
        """
        if not gradients_dict or self._grad_scalers is not None or self._lr_scheduler_classes is not None:
            return super().apply_gradients(gradients_dict)
        if not bool(torch.isfinite(torch.stack([g.sum() for g in gradients_dict.values()])).all()):
            return super().apply_gradients(gradients_dict)
        for pid, grad in gradients_dict.items():
            self._params[pid].grad = grad
        for optimizer in self._named_optimizers.values():
            optimizer.step()
        return None

    def set_state(self, state: dict[str, Any]) -> None:
        """RLlib's restore; optimizers saved before the fused step (``fused`` None in their groups) step fused again."""
        super().set_state(state)
        for optimizer in self._named_optimizers.values():
            for group in optimizer.param_groups:
                group["fused"], group["foreach"] = True, None
