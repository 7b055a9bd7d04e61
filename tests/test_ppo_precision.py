"""The PPO family's and nav_ppo's ``precision`` option: bf16 SGD steps really run in bf16, agree with fp32, and are refused when unknown."""

import copy
import random

import numpy as np
import pytest
import torch
from fixtures import NO_BRAKES
from ray.rllib.core.columns import Columns
from ray.rllib.utils.metrics import NUM_ENV_STEPS_SAMPLED_LIFETIME

from coin_app.algorithms.common import SHARED_MODULE_ID
from coin_app.algorithms.copo.learner import POLICY_PREFIXES
from coin_app.algorithms.ppo_family.precision import MixedPrecisionLearner, full_precision, learner_precision
from coin_app.training import build_config

torch.set_num_threads(1)
DRIVING = {"num_agents": 5, "horizon": 60, "max_agent_steps": 60, "delay_done": 0, "dynamics": NO_BRAKES}
DRIVING |= {"train_batch_size_per_learner": 100, "rollout_fragment_length": 50, "minibatch_size": 100, "num_epochs": 2, "hidden": 64}
ARENA = {"train_batch_size_per_learner": 100, "minibatch_size": 100, "num_epochs": 2, "hidden": 64, "max_steps": 40}
ALGOS = ("ippo", "cppo", "copo", "nav_ppo")
# measured on the first minibatch step of each algorithm's batch below (relative total-loss error; gradient cosine of the
# policy and of the value networks), over runs: ippo 7e-7, cppo 1.5e-6, copo 4e-6, nav_ppo 5e-5 to 7.5e-5 (the value loss
# dominates the total); every cosine > 0.99997. The bounds leave a margin of 10x and more.
LOSS_RTOL = 1e-3
GRAD_COSINE = 0.999


def config(name, precision):
    """The small config of ``name`` with ``precision``."""
    scenario, settings = ("arena", ARENA) if name == "nav_ppo" else ("intersection", DRIVING)
    return build_config(name, scenario, {**settings, "precision": precision}, 0)


@pytest.fixture(scope="module", params=ALGOS)
def sampled(request):
    """(name, episodes, spaces): one train batch of episodes of ``name``, sampled once for both precisions."""
    cfg = config(request.param, "fp32")
    runner = cfg.env_runner_cls(config=cfg)
    try:
        episodes = runner.sample(num_timesteps=cfg.train_batch_size_per_learner)
        spaces = {SHARED_MODULE_ID: runner.get_spaces()[SHARED_MODULE_ID]}
    finally:
        runner.stop()
    return request.param, episodes, spaces


def seeded_learner(name, precision, spaces):
    """A learner of ``name`` at ``precision`` with the same initial weights for either precision."""
    cfg = config(name, precision)
    torch.manual_seed(0)
    return cfg, cfg.build_learner(spaces=spaces)


def update(cfg, learner, episodes):
    """One PPO update of ``learner`` on a copy of ``episodes`` (the learner connector edits them), minibatches shuffled by seed."""
    episodes = copy.deepcopy(episodes)
    random.seed(0)
    np.random.seed(0)
    torch.manual_seed(0)
    steps = sum(len(e) for e in episodes)
    return learner.update(
        episodes=episodes, timesteps={NUM_ENV_STEPS_SAMPLED_LIFETIME: steps}, num_epochs=cfg.num_epochs, minibatch_size=cfg.minibatch_size
    )


def first_step(name, precision, episodes, spaces):
    """(total loss, {"policy" | "value": flat gradient}) of the first minibatch step of an update from the seeded initial weights."""
    cfg, learner = seeded_learner(name, precision, spaces)
    assert isinstance(learner, MixedPrecisionLearner) and learner.precision == precision
    names = {id(p): n for n, p in learner.module[SHARED_MODULE_ID].unwrapped().named_parameters()}
    steps = []
    compute_gradients = learner.compute_gradients

    def recording(loss_per_module, **kwargs):
        grads = compute_gradients(loss_per_module, **kwargs)
        loss = sum(loss_per_module.values())
        assert loss.dtype == torch.float32  # the losses reach backward in fp32
        groups: dict[str, list] = {"policy": [], "value": []}
        for pid, grad in grads.items():
            if grad is None:  # CPPO's own-observation critic encoder: its value head reads the central input instead
                continue
            assert grad.dtype == torch.float32
            policy = names[id(learner._params[pid])].startswith(POLICY_PREFIXES)
            groups["policy" if policy else "value"].append(grad.detach().flatten().clone())
        steps.append((float(loss.detach()), {k: torch.cat(v) for k, v in groups.items()}))
        return grads

    learner.compute_gradients = recording
    update(cfg, learner, episodes)
    return steps[0]


def test_bf16_losses_and_gradients_agree_with_fp32(sampled):
    name, episodes, spaces = sampled
    (l32, g32), (l16, g16) = first_step(name, "fp32", episodes, spaces), first_step(name, "bf16", episodes, spaces)
    # bf16 really changed the arithmetic: something differs. IPPO's total loss can round to the same float32 value
    # (relative error ~7e-7, one ulp at its size: it did once in CI), so the loss alone does not tell.
    assert l16 != l32 or any(not torch.equal(g16[k], g32[k]) for k in ("policy", "value"))
    cosines = {k: float(torch.nn.functional.cosine_similarity(g32[k], g16[k], dim=0)) for k in ("policy", "value")}
    print(f"{name}: loss fp32 {l32:.6g} bf16 {l16:.6g} rel {abs(l16 - l32) / abs(l32):.2e} cosines {cosines}")
    assert l16 == pytest.approx(l32, rel=LOSS_RTOL)
    assert all(c > GRAD_COSINE for c in cosines.values()), cosines


@pytest.mark.parametrize("precision,dtype", [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_the_sgd_steps_run_in_the_configured_precision_and_the_rest_in_fp32(sampled, precision, dtype):
    name, episodes, spaces = sampled
    cfg, learner = seeded_learner(name, precision, spaces)
    module = learner.module[SHARED_MODULE_ID].unwrapped()
    phase = ["outside"]  # "step" while a minibatch step runs (forward, losses, backward, optimizer step)
    seen: dict[str, set] = {"step": set(), "outside": set()}
    outputs: set = set()  # dtypes of the module outputs the losses read
    hooks = [
        layer.register_forward_hook(lambda mod, args, out: seen[phase[0]].add(out.dtype))
        for layer in module.modules()
        if isinstance(layer, torch.nn.Linear)
    ]
    step, compute_loss = learner._possibly_compiled_update, learner.compute_loss_for_module

    def in_step(batch, **kwargs):
        phase[0] = "step"
        try:
            return step(batch, **kwargs)
        finally:
            phase[0] = "outside"

    def loss_recording(*, module_id, config, batch, fwd_out):
        outputs.add(fwd_out[Columns.ACTION_DIST_INPUTS].dtype)
        return compute_loss(module_id=module_id, config=config, batch=batch, fwd_out=fwd_out)

    for method in ("compute_values", "compute_all_values"):
        if hasattr(module, method):
            original = getattr(module, method)

            def value_recording(*args, _original=original, **kwargs):
                out = _original(*args, **kwargs)
                outputs.update(v.dtype for v in (out if isinstance(out, tuple) else (out,)))
                return out

            setattr(module, method, value_recording)
    learner._possibly_compiled_update, learner.compute_loss_for_module = in_step, loss_recording
    try:
        update(cfg, learner, episodes)
    finally:
        for hook in hooks:
            hook.remove()
    assert seen["step"] == {dtype}  # every Linear of forward_train and of the value forwards inside the loss
    # the learner connector's value predictions (GAE, old values, CoPO's advantages) and CoPO's meta-gradient stay fp32
    assert seen["outside"] == {torch.float32}
    assert outputs == {torch.float32}  # Gaussian inputs and every value head leave the module in fp32
    assert all(p.dtype == torch.float32 for p in module.parameters())
    for optim in learner._optimizer_parameters:
        for state in optim.state.values():
            assert all(v.dtype == torch.float32 for v in state.values() if torch.is_tensor(v) and v.is_floating_point())


def test_full_precision_widens_bf16_and_keeps_fp32_as_it_is():
    x = torch.ones(3)
    assert full_precision(x) is x
    assert full_precision(x.bfloat16()).dtype == torch.float32


@pytest.mark.parametrize("name", ["ippo", "mfpo", "copo", "nav_ppo"])
@pytest.mark.parametrize("bad", ["fp16", "bfloat16", None])
def test_an_unknown_precision_is_refused_naming_it(name, bad):
    with pytest.raises(ValueError, match=rf"bad value for 'precision': {bad!r}; allowed: 'fp32', 'bf16'"):
        config(name, bad)


def test_a_learner_refuses_an_unknown_precision_and_defaults_to_fp32():
    assert learner_precision({}) == "fp32"
    with pytest.raises(ValueError, match=r"bad value for 'precision': 'half'; allowed: 'fp32', 'bf16'"):
        learner_precision({"precision": "half"})
