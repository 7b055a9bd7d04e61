"""masked_softmax: the masked softmax of the definition, at every row width, in fp32 and bf16, with its gradient."""

import math

import pytest
import torch

from coin_app.algorithms.masked_softmax import masked_softmax


def reference(logits: torch.Tensor, keep: torch.Tensor) -> torch.Tensor:
    """exp(x_j) / sum_{k kept} exp(x_k) on kept entries, 0 elsewhere, in float64, one row at a time."""
    x = logits.double()
    out = torch.zeros_like(x)
    for idx in torch.cartesian_prod(*[torch.arange(s) for s in x.shape[:-1]]).reshape(-1, x.dim() - 1):
        row, k = x[tuple(idx)], keep[tuple(idx)]
        m = max(v for v, kk in zip(row.tolist(), k.tolist(), strict=True) if kk)
        e = [math.exp(v - m) if kk else 0.0 for v, kk in zip(row.tolist(), k.tolist(), strict=True)]
        out[tuple(idx)] = torch.tensor(e, dtype=torch.float64) / sum(e)
    return out


@pytest.mark.parametrize("width", [1, 2, 13, 15, 16, 17, 31, 33, 40])
def test_matches_the_definition_and_zeroes_the_masked_entries(width: int) -> None:
    g = torch.Generator().manual_seed(width)
    logits = torch.randn(3, 2, width, generator=g) * 4
    keep = torch.rand(3, 2, width, generator=g) < 0.6
    keep[..., 0] = True
    out = masked_softmax(logits, keep)
    assert out.shape == logits.shape and out.dtype == torch.float32
    assert torch.equal(out[~keep], torch.zeros(int((~keep).sum())))
    torch.testing.assert_close(out.double(), reference(logits, keep), atol=1e-6, rtol=1e-5)
    torch.testing.assert_close(out.sum(-1), torch.ones(3, 2))


@pytest.mark.parametrize("width", [13, 20, 32])
def test_bf16_rows_match_the_definition(width: int) -> None:
    g = torch.Generator().manual_seed(width)
    logits = (torch.randn(4, width, generator=g) * 2).bfloat16()
    keep = torch.rand(4, width, generator=g) < 0.5
    keep[:, -1] = True
    out = masked_softmax(logits, keep)
    assert out.dtype == torch.bfloat16 and out.shape == logits.shape
    assert torch.equal(out[~keep].float(), torch.zeros(int((~keep).sum())))
    torch.testing.assert_close(out.double(), reference(logits.float(), keep), atol=1e-2, rtol=2e-2)


def test_gradient_is_the_softmax_jacobian_on_kept_entries() -> None:
    """d(sum_j c_j p_j)/dx_i = p_i (c_i - sum_j c_j p_j) on kept entries and 0 on masked ones."""
    g = torch.Generator().manual_seed(0)
    logits = torch.randn(5, 13, generator=g, requires_grad=True)
    keep = torch.rand(5, 13, generator=g) < 0.5
    keep[:, 3] = True
    c = torch.randn(5, 13, generator=g)
    p = masked_softmax(logits, keep)
    (p * c).sum().backward()
    pd = p.detach().double()
    expected = pd * (c.double() - (c.double() * pd).sum(-1, keepdim=True))
    torch.testing.assert_close(logits.grad.double(), expected, atol=1e-6, rtol=1e-5)
    assert torch.equal(logits.grad[~keep], torch.zeros(int((~keep).sum())))
