"""Every learner's gradient step (``gradient_step.py``): RLlib's step bit for bit, fused Adam, one finiteness check."""

import copy

import pytest
import torch
from fixtures import tiny
from ray.rllib.core.learner.torch.torch_learner import TorchLearner

from coin_app.adapters.rllib_env import register_envs
from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.algorithms.gradient_step import FastGradientStep
from coin_app.training import build_config

torch.set_num_threads(1)
register_envs()
ALGOS = ("cig_td3", "ippo", "copo", "nav_ppo")  # the TD3 family's base and child, the PPO family's, nav_ppo's learner


def build_learner(algo):
    """``algo``'s learner at the tiny scale, from the same seed (the same initial weights every call)."""
    scenario, settings = tiny(algo)
    cfg = build_config(algo, scenario, settings, 0)
    runner = cfg.env_runner_cls(config=cfg)
    try:
        spaces = {SHARED_MODULE_ID: runner.get_spaces()[SHARED_MODULE_ID]}
    finally:
        runner.stop()
    torch.manual_seed(0)
    return cfg.build_learner(spaces=spaces)


def weights(learner):
    """Every parameter of the learner's modules, flattened in order."""
    return [p.detach().clone() for p in learner._params.values()]


def random_grads(learner, seed, poison=None):
    """A gradient for every parameter (seeded); with ``poison`` one entry of the first one set to it ("overflow": two
    finite entries whose sum is inf)."""
    gen = torch.Generator().manual_seed(seed)
    grads = [torch.randn(p.shape, generator=gen) for p in learner._params.values()]
    if poison == "overflow":
        grads[0].view(-1)[:2] = 3e38
    elif poison is not None:
        grads[0].view(-1)[0] = poison
    return dict(zip(learner._params, grads, strict=True))


def saved_groups(state):
    """Every optimizer param group saved in a learner state (nested dicts)."""
    if isinstance(state, dict):
        if "param_groups" in state:
            yield from state["param_groups"]
        for v in state.values():
            yield from saved_groups(v)


@pytest.fixture(scope="module", params=ALGOS)
def algo(request):
    return request.param


@pytest.mark.parametrize("poison", [None, float("nan"), float("inf"), "overflow"])
def test_the_step_is_rllibs_bit_for_bit_with_finite_and_non_finite_gradients(algo, poison):
    ours, theirs = build_learner(algo), build_learner(algo)
    assert isinstance(ours, FastGradientStep)
    for step in range(3):  # Adam's state carries over: later steps depend on the earlier ones
        # RLlib zeroes a non-finite entry, warns and steps; a finite gradient whose sum overflows takes its path too
        grads = random_grads(ours, step, poison if step == 1 else None)
        ours.apply_gradients({ref: g.clone() for ref, g in grads.items()})
        TorchLearner.apply_gradients(theirs, {ref: g.clone() for ref, g in zip(theirs._params, grads.values(), strict=True)})
    for p, q in zip(weights(ours), weights(theirs), strict=True):
        assert torch.equal(p, q) and torch.isfinite(p).all()


def test_every_optimizer_is_fused_and_steps_as_the_per_tensor_loop_up_to_rounding(algo):
    fused, loop = build_learner(algo), build_learner(algo)
    groups = [g for opt in fused._named_optimizers.values() for g in opt.param_groups]
    assert groups and all(g["fused"] is True for g in groups)
    for opt in loop._named_optimizers.values():  # PyTorch's CPU default, RLlib's own optimizer
        for group in opt.param_groups:
            group["fused"], group["foreach"] = None, False
    start = weights(fused)
    for step in range(20):
        grads = random_grads(fused, step)
        fused.apply_gradients({ref: g.clone() for ref, g in grads.items()})
        loop.apply_gradients({ref: g.clone() for ref, g in zip(loop._params, grads.values(), strict=True)})
    moved = max((p - s).abs().max().item() for p, s in zip(weights(fused), start, strict=True))
    gap = max((p - q).abs().max().item() for p, q in zip(weights(fused), weights(loop), strict=True))
    assert moved > 1e-3 and gap < 1e-4 * moved  # float rounding, far below the steps


def test_a_state_saved_before_the_fused_step_restores_fused_and_continues_bit_for_bit(algo):
    ours = build_learner(algo)
    ours.apply_gradients(random_grads(ours, 0))
    state = copy.deepcopy(ours.get_state())
    groups = list(saved_groups(state))
    assert groups and all(g["fused"] is True for g in groups)
    for group in groups:  # as torch.optim.Adam's default (the per-tensor loop) saved it
        group["fused"], group["foreach"] = None, None
    restored = build_learner(algo)
    restored.set_state(state)
    assert all(g["fused"] is True and g["foreach"] is None for opt in restored._named_optimizers.values() for g in opt.param_groups)
    for step in (1, 2):  # the per-tensor loop rounds differently, so only the fused step continues bit for bit
        grads = random_grads(ours, step)
        ours.apply_gradients({ref: g.clone() for ref, g in grads.items()})
        restored.apply_gradients({ref: g.clone() for ref, g in zip(restored._params, grads.values(), strict=True)})
    for p, q in zip(weights(ours), weights(restored), strict=True):
        assert torch.equal(p, q)
