"""CIG-TD3 learner: policy delay, no gradient leaks, target updates, ablations, seeding, resume."""

import copy
import dataclasses
import math

import numpy as np
import pytest
import torch
from fixtures import learner_update, module_of, params, same
from ray.rllib.policy.sample_batch import MultiAgentBatch, SampleBatch

from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms.cig_td3.cig_td3 import CigTd3Config
from coin_app.algorithms.cig_td3.learner import loss_config
from coin_app.algorithms.cig_td3.losses import actor_loss
from coin_app.algorithms.td3.learner import loss_config as td3_loss_config
from coin_app.algorithms.td3.learner import soft_update
from coin_app.algorithms.td3.losses import actor_loss as td3_actor_loss
from coin_app.algorithms.td3.losses import actor_objective_loss, preact_penalty
from coin_app.algorithms.td3.td3 import Td3Config

torch.set_num_threads(1)
register_envs()
ENV_CFG = {"num_agents": 4, "horizon": 50, "max_agent_steps": 50}
B, O, S, A = 16, 91, 10, 2


def make_config(**training):
    base = {"train_batch_size_per_learner": B, "hidden": 32, "latent_dim": 4, "node_width": 16, "policy_delay": 3, "warmup_steps": 0}
    return CigTd3Config().environment("coin-bottleneck-v0", env_config=ENV_CFG).debugging(seed=0).training(**{**base, **training})


def make_itd3_config(**training):
    """ITD3 (the TD3 base) with ``make_config``'s TD3 settings."""
    base = {"train_batch_size_per_learner": B, "hidden": 32, "policy_delay": 3, "warmup_steps": 0}
    return Td3Config().environment("coin-bottleneck-v0", env_config=ENV_CFG).debugging(seed=0).training(**{**base, **training})


def build_learner(**training):
    cfg = make_config(**training)
    cfg.validate()
    torch.manual_seed(0)
    return cfg, cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))


def random_batch(seed, n_others):
    rng = np.random.default_rng(seed)

    def r(*shape):
        return rng.standard_normal(shape).astype(np.float32)

    mask = rng.random((B, n_others)) < 0.6
    next_mask = rng.random((B, n_others)) < 0.6
    return {
        "obs": rng.random((B, O), dtype=np.float32),
        "state": r(B, S),
        "actions": rng.uniform(-1, 1, (B, A)).astype(np.float32),
        "rewards": r(B),
        "global_rewards": r(B),
        "terminateds": rng.random(B) < 0.2,
        "truncateds": rng.random(B) < 0.1,
        "new_obs": rng.random((B, O), dtype=np.float32),
        "new_state": r(B, S),
        "others_state": r(B, n_others, S) * mask[..., None],
        "others_actions": rng.uniform(-1, 1, (B, n_others, A)).astype(np.float32) * mask[..., None],
        "others_mask": mask,
        "next_others_state": r(B, n_others, S) * next_mask[..., None],
        "next_others_obs": rng.random((B, n_others, O), dtype=np.float32) * next_mask[..., None],
        "next_others_mask": next_mask,
    }


def update(learner, cfg, seed):
    return learner_update(learner, random_batch(seed, cfg.max_others))


def test_policy_delay_and_target_updates():
    cfg, learner = build_learner(policy_delay=3, tau=0.1)
    m = module_of(learner)
    for step in range(1, 7):
        actor0, local0, central0 = params(m.actor), params(m.local_q), params(m.central)
        targets0 = [params(t) for t in (m.actor_target, m.local_q_target, m.central_target)]
        update(learner, cfg, step)
        policy_step = step % 3 == 0
        assert same(actor0, params(m.actor)) is not policy_step, step  # actor moves only on policy steps
        assert not same(local0, params(m.local_q)) and not same(central0, params(m.central))  # critics every step
        for (main, target), old in zip(m.get_target_network_pairs(), targets0):
            new = params(target)
            if policy_step:  # soft update: target <- tau main + (1 - tau) target
                for o, n, p in zip(old, new, params(main)):
                    assert torch.allclose(n, 0.1 * p + 0.9 * o, atol=1e-6)
            else:
                assert same(old, new)


def test_actor_step_does_not_touch_critics():
    # identical learners and batches; one does the actor step in update 3, the other never does
    # (each learner runs on its own freshly seeded RNG stream: target noise and CVAE samples)
    cfg_a, with_actor = build_learner(policy_delay=3)
    cfg_b, without_actor = build_learner(policy_delay=1000)
    for learner, cfg in ((with_actor, cfg_a), (without_actor, cfg_b)):
        torch.manual_seed(7)
        for step in (1, 2, 3):
            update(learner, cfg, step)
    ma, mb = module_of(with_actor), module_of(without_actor)
    assert not same(params(ma.actor), params(mb.actor))
    assert same(params(ma.local_q), params(mb.local_q)) and same(params(ma.central), params(mb.central))


def test_same_seed_same_losses_for_50_updates():
    def run():
        cfg, learner = build_learner(policy_delay=2)
        losses = []
        for step in range(50):
            res = update(learner, cfg, step)
            losses.append(
                float(res["shared"]["total_loss"].peek()) if hasattr(res["shared"]["total_loss"], "peek") else res["shared"]["total_loss"]
            )
        return losses

    a, b = run(), run()
    assert a == b and len(set(a)) > 10


def test_learner_state_round_trip_continues_identically():
    cfg, learner = build_learner(policy_delay=2)
    for step in range(5):
        update(learner, cfg, step)
    state = copy.deepcopy(learner.get_state())
    cont = [update(learner, cfg, step) for step in range(5, 9)]
    _, restored = build_learner(policy_delay=2)
    torch.manual_seed(123)  # the restored RNG state must win over this
    restored.set_state(state)
    again = [update(restored, cfg, step) for step in range(5, 9)]

    def val(r):
        v = r["shared"]["total_loss"]
        return float(v.peek()) if hasattr(v, "peek") else float(v)

    assert [val(r) for r in cont] == [val(r) for r in again]
    assert same(params(module_of(learner).actor), params(module_of(restored).actor))
    assert same(params(module_of(learner).central_target), params(module_of(restored).central_target))


@pytest.mark.parametrize(
    "switch,check",
    [
        ({}, lambda m: m.central is not None and m.central.cfg.local_module == "cvae" and m.central.cfg.global_module == "gat"),
        ({"local_module": "attention", "vae_weight": 0.0}, lambda m: m.central.cfg.local_module == "attention"),
        ({"local_module": "none", "vae_weight": 0.0}, lambda m: m.central.cfg.local_module == "none"),
        ({"global_module": "gcn"}, lambda m: m.central.cfg.global_module == "gcn"),
        ({"global_module": "graphsage"}, lambda m: m.central.cfg.global_module == "graphsage"),
        ({"global_module": "none"}, lambda m: m.central.cfg.global_module == "none"),
        ({"graph": 40.0}, lambda m: m.central.cfg.graph_radius == 40.0),
    ],
)
def test_each_ablation_switch_changes_only_what_it_names(switch, check):
    cfg, learner = build_learner(**switch)
    m = module_of(learner)
    assert check(m)
    _, ref = build_learner()
    r = module_of(ref)
    # actor and local critics never change with a centralized-critic switch
    assert [p.shape for p in m.actor.parameters()] == [p.shape for p in r.actor.parameters()]
    assert [p.shape for p in m.local_q.parameters()] == [p.shape for p in r.local_q.parameters()]
    update(learner, cfg, 0)  # and it trains


def test_itd3_has_no_central_critic_and_trains():
    cfg = make_itd3_config()
    cfg.validate()
    learner = cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))
    m = module_of(learner)
    assert {name for name, _ in m.named_children()} == {"actor", "local_q", "actor_target", "local_q_target"}
    assert set(learner._module_optimizers["shared"]) == {"shared_actor", "shared_local_critic"}
    update(learner, cfg, 0)


@pytest.mark.parametrize(
    "training,match",
    [
        ({"global_critic": False}, "counterfactual_baseline=True needs global_critic"),
        ({"local_module": "transformer"}, "'local_module': 'transformer'; allowed: 'cvae'"),
        ({"global_module": "none", "graph": 40.0}, "sparse graph radius needs a graph module"),
        ({"local_module": "none"}, "vae_weight=1.0 but local_module='none'"),
        ({"graph": -3}, r"'graph': -3; allowed: 'full' or a finite number > 0"),
        ({"policy_delay": 0}, "'policy_delay': 0; allowed: an integer >= 1"),
        ({"tau": 2.0}, r"'tau': 2.0; allowed: a finite number in \(0, 1\]"),
    ],
)
def test_invalid_configs_are_refused(training, match):
    with pytest.raises(ValueError, match=match):
        make_config(**training).validate()


def test_unregistered_env_is_refused():
    with pytest.raises(ValueError, match="registered envs"):
        CigTd3Config().environment("CartPole-v1").validate()


def test_more_than_one_learner_is_refused():
    with pytest.raises(ValueError, match="num_learners=2"):
        make_config().learners(num_learners=2).validate()


def test_actor_has_three_hidden_layers_of_hidden_units():
    for layers in (3, 2):
        _, learner = build_learner(actor_layers=layers)
        linears = [m for m in module_of(learner).actor.net if isinstance(m, torch.nn.Linear)]
        assert [(lin.in_features, lin.out_features) for lin in linears] == [(O, 32)] + [(32, 32)] * (layers - 1) + [(32, A)]
        assert isinstance(module_of(learner).actor.net[-1], torch.nn.Tanh)


def _actor_loss_of(module, batch_np, cfg):
    """ITD3's actor loss (Eq. 12's individual term) on a batch with the module's current networks, re-evaluated independently."""
    batch = {k: torch.as_tensor(v) for k, v in batch_np.items()}
    return float(td3_actor_loss(module.actor, module.local_q, batch, td3_loss_config(cfg))[0])


@pytest.mark.parametrize("order", ["critic_first", "joint"])
def test_actor_loss_is_taken_on_the_updated_critics(order):
    # ITD3 (no centralized critic, so the actor loss draws no CVAE latent): exactly reproducible
    cfg = make_itd3_config(policy_delay=1, update_order=order)
    cfg.validate()
    torch.manual_seed(0)
    learner = cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))
    m = module_of(learner)
    batch = random_batch(5, cfg.max_others)
    before = copy.deepcopy(m)
    logged = []
    learner_actor_loss = learner.actor_loss

    def recorded(module, config, batch):
        loss, stats = learner_actor_loss(module, config, batch)
        logged.append(float(loss.detach()))
        return loss, stats

    learner.actor_loss = recorded
    learner.update(batch=MultiAgentBatch({"shared": SampleBatch(batch)}, env_steps=B), timesteps={"num_env_steps_sampled_lifetime": 0})
    updated_critics = copy.deepcopy(m)
    updated_critics.actor.load_state_dict(before.actor.state_dict())  # the actor loss is taken before the actor's own step
    on_updated, on_old = _actor_loss_of(updated_critics, batch, cfg), _actor_loss_of(before, batch, cfg)
    assert abs(on_updated - on_old) > 1e-4  # the critic step moved the loss, so the two orders are distinguishable
    assert logged == [pytest.approx(on_updated if order == "critic_first" else on_old, abs=1e-6)]
    assert not same(params(before.actor), params(m.actor)) and not same(params(before.local_q), params(m.local_q))


def test_actor_waits_actor_start_steps_after_the_warm_up():
    cfg, learner = build_learner(policy_delay=1, warmup_steps=100, actor_start_steps=50)
    m = module_of(learner)
    for step, env_steps in enumerate((120, 149, 150)):
        actor0 = params(m.actor)
        batch = random_batch(step, cfg.max_others)
        learner.update(
            batch=MultiAgentBatch({"shared": SampleBatch(batch)}, env_steps=B), timesteps={"num_env_steps_sampled_lifetime": env_steps}
        )
        assert same(actor0, params(m.actor)) is (env_steps < 150), env_steps


def test_preact_penalty_gradient_by_hand():
    pre = torch.tensor([[3.0, -0.5], [-2.5, 1.0]], requires_grad=True)
    # weight 0.1, threshold 1: only |u| > 1 counts: (3 - 1)^2 and (2.5 - 1)^2 over 4 entries
    loss = preact_penalty(pre, 0.1, 1.0)
    assert float(loss) == pytest.approx(0.1 * (2.0**2 + 1.5**2) / 4)
    (grad,) = torch.autograd.grad(loss, pre)
    # d/du = 0.1 * 2 (|u| - 1) sign(u) / 4 where |u| > 1, else 0
    assert torch.allclose(grad, torch.tensor([[0.1 * 2 * 2.0 / 4, 0.0], [-0.1 * 2 * 1.5 / 4, 0.0]]))
    plain = preact_penalty(pre, 0.1)
    assert float(plain) == pytest.approx(0.1 * (9 + 0.25 + 6.25 + 1) / 4)  # threshold 0: w * mean(u^2)


def test_preact_penalty_enters_the_actor_loss_and_saturation_is_logged():
    batch = {k: torch.as_tensor(v) for k, v in random_batch(3, 5).items()}
    cfg, learner = build_learner()
    m = module_of(learner)
    with torch.no_grad():
        m.actor.net[-2].bias.fill_(10.0)  # every output saturated: tanh(u) > 0.99 for u > 2.65
    base, stats = actor_loss(m.actor, m.local_q, None, batch, loss_config(cfg))
    assert float(stats["actor_saturation"]) == 1.0
    with_penalty, _ = actor_loss(m.actor, m.local_q, None, batch, dataclasses.replace(loss_config(cfg), preact_penalty=0.01))
    pre = m.actor.preactivation(batch["obs"])
    assert float(with_penalty - base) == pytest.approx(0.01 * float(pre.square().mean()), rel=1e-5)


def test_actor_action_std_is_the_batch_spread_of_each_action():
    pre = torch.tensor([[0.0, 1.0], [2.0, -1.0]])
    _, stats = actor_objective_loss(torch.zeros(2), pre, {}, 0.0, 0.0)
    # two rows: the sample std of a pair is |a - b| / sqrt(2): tanh(2) / sqrt(2) and 2 tanh(1) / sqrt(2); the smaller one
    expected = min(math.tanh(2.0), 2 * math.tanh(1.0)) / math.sqrt(2)
    assert float(stats["actor_action_std"]) == pytest.approx(expected, rel=1e-6)
    _, same = actor_objective_loss(torch.zeros(3), torch.tensor([[0.7, -0.3]] * 3), {}, 0.0, 0.0)
    assert float(same["actor_action_std"]) == 0.0  # one action for every observation: a collapsed actor
    braking = torch.tensor([[-1.0, -0.9], [0.5, -0.9], [1.5, -0.9]])  # steering varies, the pedal is always the same
    assert float(actor_objective_loss(torch.zeros(3), braking, {}, 0.0, 0.0)[1]["actor_action_std"]) == 0.0
    assert math.isnan(float(actor_objective_loss(torch.zeros(1), pre[:1], {}, 0.0, 0.0)[1]["actor_action_std"]))


def test_exploration_noise_decays_linearly_after_the_warm_up():
    cfg, learner = build_learner(
        warmup_steps=100, exploration_noise=0.05, exploration_noise_initial=0.3, exploration_noise_decay_steps=1000
    )
    m = module_of(learner)
    assert [m.noise_std(t) for t in (100, 600, 1100, 5000)] == pytest.approx([0.3, 0.175, 0.05, 0.05])
    _, constant = build_learner(exploration_noise=0.05)
    assert module_of(constant).noise_std(10) == 0.05


def test_exploration_noise_decay_can_start_after_the_warm_up():
    _, learner = build_learner(
        warmup_steps=100,
        exploration_noise=0.02,
        exploration_noise_initial=0.1,
        exploration_noise_decay_start=2000,
        exploration_noise_decay_steps=2000,
    )
    m = module_of(learner)
    # constant 0.1 from the warm-up's end to 2000 env steps, then linear to 0.02 at 4000 (hand-computed midpoint 0.06)
    assert [m.noise_std(t) for t in (100, 1999, 2000, 3000, 4000, 9000)] == pytest.approx([0.1, 0.1, 0.1, 0.06, 0.02, 0.02])


def test_learning_rates_decay_linearly_on_the_env_step_schedule():
    rates = {"actor": 1e-3, "local_critic": 2e-3, "central_critic": 3e-3}
    cfg, learner = build_learner(
        actor_lr=rates["actor"],
        critic_lr=rates["local_critic"],
        central_critic_lr=rates["central_critic"],
        lr_decay_start=100,
        lr_decay_steps=200,
        lr_final_fraction=0.1,
    )
    # constant to 100 env steps, then linear to 10 % at 300, constant after (hand-computed fractions)
    for env_steps, fraction in ((50, 1.0), (100, 1.0), (200, 0.55), (300, 0.1), (1000, 0.1)):
        learner_update(learner, random_batch(env_steps, cfg.max_others), env_steps=env_steps)
        for name, lr in rates.items():
            (group,) = learner.get_optimizer("shared", name).param_groups
            assert group["lr"] == pytest.approx(lr * fraction, rel=1e-6), (name, env_steps)


def test_without_a_decay_the_learning_rates_stay_constant():
    cfg, learner = build_learner(actor_lr=1e-3, lr_final_fraction=0.1)  # lr_decay_steps=0: the fraction is unused
    for env_steps in (0, 10_000, 1_000_000):
        learner_update(learner, random_batch(1, cfg.max_others), env_steps=env_steps)
        assert learner.get_optimizer("shared", "actor").param_groups[0]["lr"] == pytest.approx(1e-3)


def test_updates_before_a_decay_starts_equal_the_constant_rates_bit_for_bit():
    """A scheduled rate starts as the same python float as a constant one (RLlib's own start is a float32 tensor)."""
    rates = {"actor_lr": 6e-4, "critic_lr": 1e-3, "central_critic_lr": 1e-3}
    learners = []
    for decay in ({}, {"lr_decay_start": 10_000, "lr_decay_steps": 10_000, "lr_final_fraction": 0.1}):
        cfg, learner = build_learner(**rates, **decay)  # the same initial weights (seeded)
        torch.manual_seed(1)  # the same target-policy noise
        for step in range(6):  # both sides of a policy step (delay 3); the decay is 10k env steps away
            learner_update(learner, random_batch(step, cfg.max_others), env_steps=step)
        learners.append(learner)
    constant, scheduled = learners
    a, b = module_of(constant).state_dict(), module_of(scheduled).state_dict()
    assert all(torch.equal(a[k], b[k]) for k in a)
    groups = [learner.get_optimizer("shared", "actor").param_groups[0]["lr"] for learner in (constant, scheduled)]
    assert groups == [6e-4, 6e-4] and all(type(g) is float for g in groups)


def test_soft_update_is_taus_blend_of_every_state_tensor():
    main, target = torch.nn.BatchNorm1d(3), torch.nn.BatchNorm1d(3)  # parameters, float and integer buffers
    with torch.no_grad():
        for t in (*main.parameters(), main.running_mean, main.running_var):
            t.uniform_(-1, 1)
    main.num_batches_tracked.fill_(7)
    old = {k: v.clone() for k, v in target.state_dict().items()}
    soft_update(main, target, 0.25)
    for k, v in target.state_dict().items():
        expected = main.state_dict()[k] if k == "num_batches_tracked" else 0.25 * main.state_dict()[k] + 0.75 * old[k]
        assert torch.allclose(v.float(), expected.float(), atol=1e-7), k


@pytest.mark.parametrize("clip", [None, 0.01])
def test_grad_clip_bounds_every_optimizers_gradient_norm(clip):
    # one declaration in td3/settings.py: --set takes it, and RLlib's own gradient post-processing reads it for each optimizer
    from coin_app.algorithms import registry
    from coin_app.training import build_config

    overrides = registry.tiny_settings("itd3", "bottleneck") | ({} if clip is None else {"grad_clip": clip})
    cfg = build_config("itd3", "bottleneck", overrides, 0)
    assert cfg.grad_clip == clip
    learner = cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))
    grads = {ref: torch.full_like(p, 3.0) for ref, p in learner._params.items()}
    out = learner.postprocess_gradients(grads)
    optimizers = learner.get_optimizers_for_module("shared")
    assert len(optimizers) >= 2  # the actor's and the critics'
    for _, optimizer in optimizers:
        refs = learner._optimizer_parameters[optimizer]
        n = sum(learner._params[r].numel() for r in refs)
        norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(out[r]) for r in refs])).item()
        expected = 3.0 * math.sqrt(n) if clip is None else clip  # clipping rescales the whole group to the bound
        assert norm == pytest.approx(expected, rel=1e-4)
    with pytest.raises(ValueError, match=r"^bad value for 'grad_clip': -1; allowed: None or a finite number > 0$"):
        build_config("itd3", "bottleneck", {"grad_clip": -1}, 0)
