"""A masked softmax over the last dimension that stays on torch's vectorized CPU path for short rows.

torch 2.13's CPU softmax over a last dimension shorter than one 64-byte vector (16 fp32 or 32 bf16
values) falls back to a per-row path that is about ten times slower than a row of 16
(``python benchmarks/masked_softmax.py``). The attention rows of the reduced-scale intersection
are 13 wide (the ego and 12 other slots), so the CIG-TD3 GAT and the TraCo domain attention pad
such rows with -inf to one vector; the padded columns get exactly 0 and are sliced off.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

__all__ = ["VECTOR_BYTES", "masked_softmax"]

VECTOR_BYTES = 64  # one AVX-512 register; wider than needed on AVX2, where 32 bytes suffice


def masked_softmax(logits: Tensor, keep: Tensor) -> Tensor:
    """Softmax of ``logits`` over the last dim with the entries where ``keep`` is False exactly 0 (each row keeps one or more)."""
    x = logits.masked_fill(~keep, float("-inf"))
    n = x.shape[-1]
    width = VECTOR_BYTES // x.element_size()
    if x.device.type != "cpu" or n >= width:
        return torch.softmax(x, dim=-1)
    return torch.softmax(F.pad(x, (0, width - n), value=float("-inf")), dim=-1)[..., :n]
