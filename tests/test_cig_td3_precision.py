"""CIG-TD3 bf16 learner updates: the losses' forward passes really run in bf16, and agree with fp32."""

import contextlib
import re

import numpy as np
import pytest
import torch
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms.cig_td3.cig_td3 import CigTd3Config
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.td3 import learner as td3_learner
from coin_app.algorithms.td3.learner import autocast, native_bf16, resolve_precision
from coin_app.sim import schema

torch.set_num_threads(1)
register_envs()
ENV_CFG = {"num_agents": 4, "horizon": 50, "max_agent_steps": 50}
B = 64
# measured on the batch below (relative loss error, gradient cosine): local critic 7e-5 / 0.99999, centralized critic
# 2e-6 / 0.9997, actor 3e-3 / 0.999995 (its loss is small, 0.025); at the benchmark's size (B=256, intersection, hidden 256)
# 4e-5 / 0.9994, 1e-5 / 0.9996, 2e-3 / 0.99999. The bounds leave a wide margin.
LOSS_RTOL = 0.02
GRAD_COSINE = 0.99


def make_config(**training):
    base = {"train_batch_size_per_learner": B, "hidden": 32, "latent_dim": 4, "node_width": 16, "policy_delay": 1, "warmup_steps": 0}
    return CigTd3Config().environment("coin-bottleneck-v0", env_config=ENV_CFG).debugging(seed=0).training(**{**base, **training})


def build_learner(**training):
    cfg = make_config(**training)
    cfg.validate()
    return cfg, cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))


def batch_np(cfg, present=3):
    """A fixed seeded batch (as ``benchmarks/learner_update.py``'s): ``present`` other agents at t, one more at t+1."""
    rng, n, o, s, a, f = (
        np.random.default_rng(0),
        cfg.max_others,
        cfg.scenario_config().obs_dim,
        schema.STATE_DIM,
        schema.ACT_DIM,
        np.float32,
    )
    mask, next_mask = np.zeros((B, n), bool), np.zeros((B, n), bool)
    mask[:, :present], next_mask[:, : present + 1] = True, True
    return {
        col.OBS: rng.random((B, o), dtype=f),
        col.STATE: rng.standard_normal((B, s)).astype(f),
        col.ACTIONS: rng.uniform(-1, 1, (B, a)).astype(f),
        col.REWARDS: rng.standard_normal(B).astype(f),
        col.GLOBAL_REWARDS: rng.standard_normal(B).astype(f),
        col.TERMINATEDS: rng.random(B) < 0.05,
        col.TRUNCATEDS: np.zeros(B, bool),
        col.NEXT_OBS: rng.random((B, o), dtype=f),
        col.NEXT_STATE: rng.standard_normal((B, s)).astype(f),
        col.OTHERS_STATE: rng.standard_normal((B, n, s)).astype(f) * mask[..., None],
        col.OTHERS_ACTIONS: rng.uniform(-1, 1, (B, n, a)).astype(f) * mask[..., None],
        col.OTHERS_MASK: mask,
        col.NEXT_OTHERS_STATE: rng.standard_normal((B, n, s)).astype(f) * next_mask[..., None],
        col.NEXT_OTHERS_OBS: rng.random((B, n, o), dtype=f) * next_mask[..., None],
        col.NEXT_OTHERS_MASK: next_mask,
    }


def losses_and_grads(learner, cfg, precision):
    """Each loss group's (loss, flat gradient of its own network) on the fixed batch, with the learner's code path."""
    module = learner.module["shared"].unwrapped()
    batch = {k: torch.as_tensor(v) for k, v in batch_np(cfg).items()}
    config = cfg.copy(copy_frozen=False).training(precision=precision)
    torch.manual_seed(1)  # the same target-smoothing noise and CVAE samples for both precisions
    groups, _ = learner.critic_losses(module, config, batch)
    with autocast(module, precision):  # as the learner's update takes the actor loss
        groups["actor"] = (learner.actor_loss(module, config, batch)[0], module.actor)
    out = {}
    for name, (loss, net) in groups.items():
        assert loss.dtype == torch.float32, name  # losses reach backward in fp32
        grads = torch.autograd.grad(loss, list(net.parameters()))
        assert all(g.dtype == torch.float32 for g in grads), name
        out[name] = (float(loss.detach()), torch.cat([g.flatten() for g in grads]))
    return out


def test_bf16_losses_and_gradients_agree_with_fp32():
    cfg, learner = build_learner()
    fp32, bf16 = losses_and_grads(learner, cfg, "fp32"), losses_and_grads(learner, cfg, "bf16")
    assert set(fp32) == set(bf16) == {"local_critic", "central_critic", "actor"}
    for name in fp32:
        (l32, g32), (l16, g16) = fp32[name], bf16[name]
        assert l16 != l32 or not torch.equal(g16, g32), name  # bf16 really changed the arithmetic
        assert l16 == pytest.approx(l32, rel=LOSS_RTOL), name
        assert float(torch.nn.functional.cosine_similarity(g32, g16, dim=0)) > GRAD_COSINE, name


@pytest.mark.parametrize("precision,dtype", [("fp32", torch.float32), ("bf16", torch.bfloat16)])
def test_every_linear_layer_of_an_update_runs_in_the_configured_precision(precision, dtype):
    cfg, learner = build_learner(precision=precision, policy_delay=1)  # a policy step: targets, critics and actor all run
    module = learner.module["shared"].unwrapped()
    seen: dict[str, set] = {}
    hooks = [
        layer.register_forward_hook(lambda mod, args, out, name=name: seen.setdefault(name, set()).add(out.dtype))
        for name, layer in module.named_modules()
        if isinstance(layer, torch.nn.Linear)
    ]
    learner.update(
        batch=MultiAgentBatch({"shared": SampleBatch(batch_np(cfg))}, env_steps=B), timesteps={"num_env_steps_sampled_lifetime": 0}
    )
    for hook in hooks:
        hook.remove()
    for prefix in ("actor.", "local_q.", "central.", "actor_target.", "local_q_target.", "central_target."):
        assert any(name.startswith(prefix) for name in seen), prefix  # each network's layers ran
    assert {name: dtypes for name, dtypes in seen.items() if dtypes != {dtype}} == {}
    # parameters, gradients' optimizer state and the targets stay fp32
    assert all(p.dtype == torch.float32 for p in module.parameters())
    for optim in learner._optimizer_parameters:
        for state in optim.state.values():
            assert all(v.dtype == torch.float32 for v in state.values() if torch.is_tensor(v) and v.is_floating_point())


def test_a_bf16_update_trains():
    cfg, learner = build_learner(precision="bf16", policy_delay=1)
    module = learner.module["shared"].unwrapped()
    nets = (module.actor, module.local_q, module.central)
    before = [[p.detach().clone() for p in net.parameters()] for net in nets]
    res = learner.update(
        batch=MultiAgentBatch({"shared": SampleBatch(batch_np(cfg))}, env_steps=B), timesteps={"num_env_steps_sampled_lifetime": 0}
    )
    for key in ("local_critic_loss", "central_critic_loss", "actor_loss"):
        v = res["shared"][key]
        assert np.isfinite(float(v.peek() if hasattr(v, "peek") else v)), key
    for old, net in zip(before, nets):
        assert not all(torch.equal(a, b) for a, b in zip(old, net.parameters()))


@pytest.mark.parametrize("bad", ["fp16", "bfloat16", None])
def test_unknown_precision_is_refused(bad):
    with pytest.raises(ValueError, match=rf"'precision': {bad!r}; allowed: 'auto', 'fp32', 'bf16'"):
        make_config(precision=bad).validate()


@pytest.fixture
def fresh_capability_cache():
    native_bf16.cache_clear()
    yield
    native_bf16.cache_clear()


@pytest.mark.usefixtures("fresh_capability_cache")
@pytest.mark.parametrize("mkldnn_bf16", [True, False])
def test_auto_is_bf16_exactly_on_a_cpu_with_native_bf16(monkeypatch, mkldnn_bf16):
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: mkldnn_bf16)
    cpu = torch.device("cpu")
    assert resolve_precision("auto", cpu) == ("bf16" if mkldnn_bf16 else "fp32")
    assert (resolve_precision("fp32", cpu), resolve_precision("bf16", cpu)) == ("fp32", "bf16")  # explicit values win
    _, learner = build_learner(precision="auto")
    module = learner.module["shared"].unwrapped()
    with autocast(module, "auto"):
        out = module.actor(torch.ones(2, module.actor.net[0].in_features))
    assert out.dtype == (torch.bfloat16 if mkldnn_bf16 else torch.float32)


@pytest.mark.usefixtures("fresh_capability_cache")
@pytest.mark.parametrize("cuda_bf16", [True, False])
def test_auto_on_cuda_asks_that_gpu_for_native_bf16(monkeypatch, cuda_bf16):
    asked = []
    monkeypatch.setattr(torch.cuda, "device", lambda device: asked.append(device) or contextlib.nullcontext())
    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda including_emulation=True: cuda_bf16 and not including_emulation)
    monkeypatch.setattr(torch.ops.mkldnn, "_is_mkldnn_bf16_supported", lambda: not cuda_bf16)  # the host CPU is not asked
    gpu = torch.device("cuda", 1)
    assert resolve_precision("auto", gpu) == ("bf16" if cuda_bf16 else "fp32")
    assert asked == [gpu]
    assert resolve_precision("auto", torch.device("meta")) == "fp32"  # no other device counts as native


def test_cig_td3_defaults_to_auto_and_the_reduced_protocol_to_fp32():
    from coin_app.algorithms import registry

    spec = registry.get("cig_td3")
    assert spec.presets["paper"].precision == "auto" and spec.presets["reduced"].precision == "fp32"
    assert registry.get("itd3").presets["paper"].precision == "fp32"
    with pytest.raises(ValueError, match=re.escape("precision='fp16'; allowed: auto | fp32 | bf16")):
        td3_learner.resolve_precision("fp16", torch.device("cpu"))
