"""TraCo networks (coin_app.algorithms.traco.networks): the 40 m domain, the cross-attention critic and the counterfactual baseline.

Expectations are hand-computed (the domain, the advantage) or invariants of the design: attention
rows sum to 1 over the null token and the domain and are exactly 0 elsewhere, slots outside the
domain change nothing (bit-identical), the neighbour slots' order does not matter, the baseline
ignores the ego action, the twin critics share no tensor and the ego action reaches the query.
"""

from __future__ import annotations

import pytest
import torch

from coin_app.algorithms.traco.networks import (
    CounterfactualBaseline,
    DomainAttention,
    DomainCritic,
    counterfactual_advantage,
    neighbourhood_mask,
)

torch.set_num_threads(1)

B, N, O, S, A = 6, 5, 91, 10, 2
HIDDEN, HEADS = 16, 2
RADIUS, SCALE = 40.0, 100.0  # metres; metres per state unit of the position


def _batch(seed: int = 0) -> dict[str, torch.Tensor]:
    """A batch with near (< 40 m), far (> 40 m) and padded slots; row 4 has only far / padded slots, row 5 only padded ones."""
    g = torch.Generator().manual_seed(seed)
    state = torch.randn(B, S, generator=g)
    state[:, :2] = torch.rand(B, 2, generator=g) - 0.5
    dist = torch.tensor(  # metres from the ego per slot
        [
            [5.0, 20.0, 60.0, 35.0, 80.0],
            [12.0, 45.0, 30.0, 70.0, 8.0],
            [39.0, 41.0, 15.0, 25.0, 90.0],
            [1.0, 2.0, 3.0, 50.0, 55.0],
            [45.0, 50.0, 60.0, 70.0, 10.0],
            [5.0, 10.0, 15.0, 20.0, 25.0],
        ]
    )
    mask = torch.tensor(
        [
            [True, True, True, True, False],
            [True, True, True, True, True],
            [True, True, True, False, True],
            [True, False, True, True, True],
            [True, True, True, True, False],
            [False, False, False, False, False],
        ]
    )
    angle = torch.rand(B, N, generator=g) * 2 * torch.pi
    others_state = torch.randn(B, N, S, generator=g)
    others_state[..., :2] = state[:, None, :2] + torch.stack([angle.cos(), angle.sin()], -1) * (dist / SCALE).unsqueeze(-1)
    others_state = torch.where(mask.unsqueeze(-1), others_state, 0.0)
    others_actions = torch.where(mask.unsqueeze(-1), torch.rand(B, N, A, generator=g) * 2 - 1, 0.0)
    return {
        "obs": torch.randn(B, O, generator=g),
        "actions": torch.rand(B, A, generator=g) * 2 - 1,
        "state": state,
        "others_state": others_state,
        "others_actions": others_actions,
        "others_mask": mask,
        "dist": dist,
    }


def _nets(seed: int = 0) -> tuple[DomainCritic, CounterfactualBaseline]:
    torch.manual_seed(seed)
    return DomainCritic(O, S, A, hidden=HIDDEN, heads=HEADS), CounterfactualBaseline(O, S, A, hidden=HIDDEN, heads=HEADS)


def _domain(b: dict[str, torch.Tensor]) -> torch.Tensor:
    return neighbourhood_mask(b["state"], b["others_state"], b["others_mask"], RADIUS, SCALE)


def _outputs(critic: DomainCritic, baseline: CounterfactualBaseline, b: dict[str, torch.Tensor], nbr: torch.Tensor) -> list[torch.Tensor]:
    """q1, q2, b and the attention weights of both critics and the baseline."""
    args = (b["state"], b["others_state"], b["others_actions"], nbr)
    q1, w1 = critic.q1(b["obs"], b["actions"], *args)
    q2, w2 = critic.q2(b["obs"], b["actions"], *args)
    assert torch.equal(torch.stack(critic(b["obs"], b["actions"], *args)), torch.stack([q1, q2]))
    return [q1, q2, baseline(b["obs"], *args), w1, w2]


def test_neighbourhood_mask_hand_built():
    # Map half-extent 64 m: every position below is exact in float32. Ego at (-8, 4) m.
    scale = 64.0
    ego = torch.zeros(1, S)
    ego[0, :2] = torch.tensor([-8.0, 4.0]) / scale
    others_m = torch.tensor(
        [
            [2.0, 4.0],  # offset (10, 0): 10 m
            [-8.0, -35.9],  # offset (0, -39.9): 39.9 m
            [16.0, 36.0],  # offset (24, 32): sqrt(576 + 1024) = 40 m exactly, not strictly within
            [-41.0, -40.0],  # offset (-33, -44): sqrt(1089 + 1936) = 55 m
            [-8.0, 4.0],  # padded slot at the ego's own position (0 m)
        ]
    )
    others = torch.zeros(1, 5, S)
    others[0, :, :2] = others_m / scale
    valid = torch.tensor([[True, True, True, True, False]])
    got = neighbourhood_mask(ego, others, valid, 40.0, scale)
    assert got.dtype == torch.bool
    assert got.tolist() == [[True, True, False, False, False]]
    # A larger radius admits the 40 m and 55 m vehicles, never the padded slot.
    assert neighbourhood_mask(ego, others, valid, 60.0, scale).tolist() == [[True, True, True, True, False]]


def test_batch_domain_matches_the_planted_distances():
    b = _batch()
    assert torch.equal(_domain(b), b["others_mask"] & (b["dist"] < RADIUS))


def test_attention_rows_sum_to_one_and_are_zero_outside_the_domain():
    b = _batch()
    nbr = _domain(b)
    critic, baseline = _nets()
    for w in _outputs(critic, baseline, b, nbr)[3:]:
        assert w.shape == (B, HEADS, 1 + N)
        keep = torch.cat([torch.ones(B, 1, dtype=torch.bool), nbr], 1).unsqueeze(1).expand_as(w)
        torch.testing.assert_close(w.sum(-1), torch.ones(B, HEADS), atol=1e-6, rtol=0)
        assert torch.all(w[~keep] == 0.0)  # padded, far: exactly 0
        assert torch.all(w[keep] > 0.0)  # the null token and every neighbour get some weight


def test_padded_and_far_vehicles_change_nothing():
    b = _batch()
    nbr = _domain(b)
    critic, baseline = _nets()
    with torch.no_grad():
        before = _outputs(critic, baseline, b, nbr)
    g = torch.Generator().manual_seed(1)
    padded = ~b["others_mask"]
    far = b["others_mask"] & ~nbr
    assert padded.any() and far.any()
    p = dict(b)
    noise_s = torch.randn(B, N, S, generator=g) * 1e4
    noise_a = torch.randn(B, N, A, generator=g) * 1e4
    # Far vehicles: any other state and action, positions pushed further out (still outside 40 m).
    offset = b["others_state"][..., :2] - b["state"][:, None, :2]
    far_state = torch.cat([b["state"][:, None, :2] + offset * (1 + torch.rand(B, N, 1, generator=g) * 50), noise_s[..., 2:]], -1)
    p["others_state"] = torch.where(padded.unsqueeze(-1), noise_s, torch.where(far.unsqueeze(-1), far_state, b["others_state"]))
    p["others_actions"] = torch.where((padded | far).unsqueeze(-1), noise_a, b["others_actions"])
    assert not torch.equal(p["others_state"], b["others_state"])
    nbr_p = _domain(p)
    assert torch.equal(nbr_p, nbr)
    with torch.no_grad():
        after = _outputs(critic, baseline, p, nbr_p)
        # Even non-finite contents of padded slots cannot leak.
        p["others_state"] = torch.where(padded.unsqueeze(-1), float("nan"), p["others_state"])
        with_nan = _outputs(critic, baseline, p, nbr_p)
    for x, y, z in zip(before, after, with_nan, strict=True):
        assert torch.equal(x, y)
        assert torch.equal(x, z)


def test_neighbour_order_does_not_matter():
    b = _batch()
    nbr = _domain(b)
    critic, baseline = _nets()
    torch.manual_seed(3)
    perm = torch.randperm(N)
    assert not torch.equal(perm, torch.arange(N))
    p = dict(b)
    for key in ("others_state", "others_actions", "others_mask"):
        p[key] = b[key][:, perm]
    nbr_p = _domain(p)
    assert torch.equal(nbr_p, nbr[:, perm])
    with torch.no_grad():
        before, after = _outputs(critic, baseline, b, nbr), _outputs(critic, baseline, p, nbr_p)
    for x, y in zip(before[:3], after[:3], strict=True):
        torch.testing.assert_close(y, x, atol=1e-6, rtol=0)
    for w, w_p in zip(before[3:], after[3:], strict=True):
        torch.testing.assert_close(w_p[..., 0], w[..., 0], atol=1e-6, rtol=0)
        torch.testing.assert_close(w_p[..., 1:], w[..., 1:][..., perm], atol=1e-6, rtol=0)


def test_empty_neighbourhood_attends_only_to_the_null_token():
    b = _batch()
    critic, baseline = _nets()
    empty = torch.zeros(B, N, dtype=torch.bool)
    with torch.no_grad():
        out = _outputs(critic, baseline, b, empty)
        # The same as having no slots at all.
        none = {k: v for k, v in b.items()}
        none["others_state"], none["others_actions"] = b["others_state"][:, :0], b["others_actions"][:, :0]
        out_none = _outputs(critic, baseline, none, torch.zeros(B, 0, dtype=torch.bool))
    for x in out[:3]:
        assert x.shape == (B,) and torch.isfinite(x).all()
    for w in out[3:]:
        assert torch.equal(w[..., 0], torch.ones(B, HEADS))
        assert torch.equal(w[..., 1:], torch.zeros(B, HEADS, N))
    for x, y in zip(out[:3], out_none[:3], strict=True):
        torch.testing.assert_close(y, x, atol=1e-6, rtol=0)
    # Row 5 of the planted batch has no valid slot: its outputs equal those of the all-empty domain.
    with torch.no_grad():
        planted = _outputs(critic, baseline, b, _domain(b))
    for x, y in zip(out[:3], planted[:3], strict=True):
        torch.testing.assert_close(y[5], x[5], atol=1e-6, rtol=0)


def test_baseline_ignores_the_ego_action_and_the_critic_does_not():
    b = _batch()
    nbr = _domain(b)
    critic, baseline = _nets()
    args = (b["state"], b["others_state"], b["others_actions"], nbr)
    other = dict(b, actions=-b["actions"])
    with torch.no_grad():
        q = critic(b["obs"], b["actions"], *args)
        q_other = critic(other["obs"], other["actions"], *args)
        base = baseline(b["obs"], *args)
        # b is its network evaluated at the default action (-1, -1), whatever the ego did.
        at_default = baseline.net(b["obs"], torch.full((B, A), -1.0), *args)[0]
        at_ego = baseline.net(b["obs"], b["actions"], *args)[0]
    assert torch.equal(base, at_default)
    assert not torch.allclose(base, at_ego)
    for x, y in zip(q, q_other, strict=True):
        assert (x - y).abs().min() > 0  # every row's Q depends on the ego action


def test_counterfactual_advantage_hand_computed():
    q = torch.tensor([1.5, -0.5])
    base = torch.tensor([0.5, 0.25])
    assert torch.equal(counterfactual_advantage(q, base), torch.tensor([1.0, -0.75]))
    with pytest.raises(ValueError, match="same shape"):
        counterfactual_advantage(q, base.unsqueeze(-1))


def test_twin_critics_are_separate_and_the_ego_action_reaches_the_query():
    b = _batch()
    nbr = _domain(b)
    critic, _ = _nets()
    ptr1 = {p.data_ptr() for p in critic.q1.parameters()}
    ptr2 = {p.data_ptr() for p in critic.q2.parameters()}
    assert len(ptr1) == len(list(critic.q1.parameters())) and ptr1.isdisjoint(ptr2)
    assert len(list(critic.parameters())) == 2 * len(list(critic.q1.parameters()))
    args = (b["state"], b["others_state"], b["others_actions"], nbr)
    actions = b["actions"].clone().requires_grad_(True)
    q1, q2 = critic(b["obs"], actions, *args)
    assert not torch.allclose(q1, q2)
    (grad,) = torch.autograd.grad(critic.q1_only(b["obs"], actions, *args).sum(), actions)
    assert (grad.abs().sum(-1) > 0).all()
    # Through the attention query: the weights depend on the ego action only via the query, in every row with neighbours.
    _, w = critic.q1.attention(b["obs"], actions, *args)
    coef = torch.randn(w.shape, generator=torch.Generator().manual_seed(2))
    (grad_w,) = torch.autograd.grad((w * coef).sum(), actions)
    has_nbr = nbr.any(-1)
    assert has_nbr.any() and (~has_nbr).any()
    assert (grad_w[has_nbr].abs().sum(-1) > 0).all()
    assert torch.equal(grad_w[~has_nbr], torch.zeros_like(grad_w[~has_nbr]))


def test_invalid_arguments_are_rejected():
    with pytest.raises(ValueError, match="multiple of heads"):
        DomainAttention(O, S, A, hidden=10, heads=4)
    with pytest.raises(ValueError, match="neighbour_features"):
        DomainAttention(O, S, A, hidden=HIDDEN, heads=HEADS, neighbour_features="obs")
    with pytest.raises(ValueError, match="default_action"):
        CounterfactualBaseline(O, S, A, hidden=HIDDEN, heads=HEADS, default_action=(-1.0,))
