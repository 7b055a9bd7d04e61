"""TraCo learner and losses: domain reward and target by hand, policy delay, target updates, no gradient leaks, seeding, resume."""

import copy

import numpy as np
import pytest
import torch
from fixtures import learner_update, module_of, params, same, scalar
from test_cig_td3_learner import random_batch as cig_random_batch

from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms.td3 import columns as col
from coin_app.algorithms.traco.losses import TracoLossConfig, domain_batch, domain_rewards, domains, td_targets
from coin_app.algorithms.traco.networks import DomainCritic
from coin_app.algorithms.traco.traco import TracoConfig

torch.set_num_threads(1)
register_envs()
ENV_CFG = {"num_agents": 4, "horizon": 50, "max_agent_steps": 50}
B, O, S, A = 16, 91, 10, 2


def make_config(**training):
    base = {"train_batch_size_per_learner": B, "hidden": 32, "attention_heads": 4, "policy_delay": 3, "warmup_steps": 0}
    return TracoConfig().environment("coin-bottleneck-v0", env_config=ENV_CFG).debugging(seed=0).training(**{**base, **training})


def build_learner(**training):
    cfg = make_config(**training)
    cfg.validate()
    torch.manual_seed(0)
    return cfg, cfg.build_learner(env=CoinMultiAgentEnv({"scenario": "bottleneck", **ENV_CFG}))


def random_batch(seed, n_others):
    """CIG-TD3's random transitions plus the others' rewards, the others within about 0-60 m of the ego (positions x the map scale)."""
    batch = cig_random_batch(seed, n_others)
    rng = np.random.default_rng(seed + 1000)
    mask = batch["others_mask"]
    batch["others_rewards"] = rng.standard_normal(mask.shape).astype(np.float32) * mask
    for key, scale in (("state", 0.05), ("new_state", 0.05), ("others_state", 0.2), ("next_others_state", 0.2)):
        batch[key] = batch[key] * np.float32(scale)
    return batch


def update(learner, cfg, seed):
    return learner_update(learner, random_batch(seed, cfg.max_others))


def total_loss(result):
    return scalar(result["shared"]["total_loss"])


# ----------------------------------------------------------------------------- losses by hand
def test_domain_reward_by_hand():
    r = torch.tensor([1.0, 2.0, -1.0])
    others = torch.tensor([[3.0, 5.0, 7.0], [4.0, 0.0, 0.0], [9.0, 9.0, 9.0]])
    domain = torch.tensor([[True, True, False], [True, False, False], [False, False, False]])
    # mean over {ego} and the domain: (1 + 3 + 5) / 3, (2 + 4) / 2, -1 / 1
    assert domain_rewards(r, others, domain, "mean").tolist() == [3.0, 3.0, -1.0]
    # the domain only (CoPO's nei_rewards): (3 + 5) / 2, 4, 0 for an empty domain
    assert domain_rewards(r, others, domain, "neighbours").tolist() == [4.0, 4.0, 0.0]
    assert domain_rewards(r, others, domain, "own").tolist() == [1.0, 2.0, -1.0]
    with pytest.raises(ValueError, match="'domain_reward': 'sum'; allowed: 'mean', 'neighbours', 'own'"):
        domain_rewards(r, others, domain, "sum")


class ConstQ(torch.nn.Module):
    """A twin critic returning (sum of the domain's actions' first components, its negative + 10): a target computable by hand."""

    def forward(self, obs, actions, state, others_state, others_actions, nbr_mask):
        total = (others_actions[..., 0] * nbr_mask).sum(-1) + actions[:, 0]
        return total, -total + 10.0


def test_domain_target_by_hand():
    # one ego at the origin, three next-step others at 10 m, 39.9 m and 40.1 m (scale 1): the domain at t+1 is the first two
    actor = torch.nn.Identity()  # mu_targ(o') = o' (2-d observations here), no smoothing noise
    batch = {
        col.NEXT_OBS: torch.tensor([[0.5, 0.0]]),
        col.NEXT_STATE: torch.zeros(1, S),
        col.NEXT_OTHERS_STATE: torch.zeros(1, 3, S),
        col.NEXT_OTHERS_OBS: torch.tensor([[[0.25, 0.0], [-1.0, 0.0], [0.75, 0.0]]]),
        col.NEXT_OTHERS_MASK: torch.tensor([[True, True, True]]),
        col.STATE: torch.zeros(1, S),
        col.OTHERS_STATE: torch.zeros(1, 3, S),
        col.OTHERS_MASK: torch.tensor([[True, False, True]]),
        col.REWARDS: torch.tensor([2.0]),
        col.TERMINATEDS: torch.tensor([False]),
        col.TRUNCATEDS: torch.tensor([False]),
    }
    batch[col.NEXT_OTHERS_STATE][0, :, 0] = torch.tensor([10.0, 39.9, 40.1])
    batch[col.OTHERS_STATE][0, :, 1] = torch.tensor([30.0, 0.0, 50.0])
    cfg = TracoLossConfig(gamma=0.5, target_noise=0.0, domain_radius=40.0, position_scale=1.0)
    d0, d1 = domains(batch, cfg)
    assert d0.tolist() == [[True, False, False]] and d1.tolist() == [[True, True, False]]
    y, y_local = td_targets(batch, d1, torch.tensor([2.0]), actor, ConstQ(), None, cfg)
    # Q1 = 0.5 + 0.25 - 1.0 = -0.25, Q2 = 10.25: y = 2 + 0.5 * min = 1.875 (the far vehicle's 0.75 is left out)
    assert y_local is None and y.tolist() == [1.875]
    batch[col.TRUNCATEDS] = torch.tensor([True])  # a time-out bootstraps by default; it is terminal with timeout_bootstrap=False
    assert td_targets(batch, d1, torch.tensor([2.0]), actor, ConstQ(), None, cfg)[0].tolist() == [1.875]
    paper = TracoLossConfig(gamma=0.5, target_noise=0.0, domain_radius=40.0, position_scale=1.0, timeout_bootstrap=False)
    assert td_targets(batch, d1, torch.tensor([2.0]), actor, ConstQ(), None, paper)[0].tolist() == [2.0]
    batch[col.TRUNCATEDS] = torch.tensor([False])
    batch[col.TERMINATEDS] = torch.tensor([True])
    assert td_targets(batch, d1, torch.tensor([2.0]), actor, ConstQ(), None, cfg)[0].tolist() == [2.0]


# ----------------------------------------------------------------------------- the learner
def test_policy_delay_and_target_updates():
    cfg, learner = build_learner(policy_delay=3, tau=0.1)
    m = module_of(learner)
    assert m.local_q is None and set(learner._module_optimizers["shared"]) == {"shared_actor", "shared_domain_critic", "shared_baseline"}
    for step in range(1, 7):
        actor0, domain0, base0 = params(m.actor), params(m.domain_q), params(m.baseline)
        targets0 = [params(t) for _, t in m.get_target_network_pairs()]
        res = update(learner, cfg, step)
        policy_step = step % 3 == 0
        assert same(actor0, params(m.actor)) is not policy_step, step  # actor moves only on policy steps
        assert not same(domain0, params(m.domain_q)) and not same(base0, params(m.baseline))  # critics every step
        assert scalar(res["shared"]["domain_size_mean"]) > 0
        for (main, target), old in zip(m.get_target_network_pairs(), targets0):
            new = params(target)
            if policy_step:  # soft update: target <- tau main + (1 - tau) target
                for o, n, p in zip(old, new, params(main)):
                    assert torch.allclose(n, 0.1 * p + 0.9 * o, atol=1e-6)
            else:
                assert same(old, new)
    assert len(m.get_target_network_pairs()) == 2  # actor and domain critic; the baseline regresses on the critic's target


def test_actor_step_does_not_touch_critics():
    cfg_a, with_actor = build_learner(policy_delay=3, individual_critic=True)
    cfg_b, without_actor = build_learner(policy_delay=1000, individual_critic=True)
    for learner, cfg in ((with_actor, cfg_a), (without_actor, cfg_b)):
        torch.manual_seed(7)
        for step in (1, 2, 3):
            update(learner, cfg, step)
    ma, mb = module_of(with_actor), module_of(without_actor)
    assert not same(params(ma.actor), params(mb.actor))
    for name in ("domain_q", "baseline", "local_q"):
        assert same(params(getattr(ma, name)), params(getattr(mb, name))), name


def test_same_seed_same_losses_for_50_updates():
    def run():
        cfg, learner = build_learner(policy_delay=2)
        return [total_loss(update(learner, cfg, step)) for step in range(50)]

    a, b = run(), run()
    assert a == b and len(set(a)) > 10


def test_learner_state_round_trip_continues_identically():
    cfg, learner = build_learner(policy_delay=2, individual_critic=True)
    for step in range(5):
        update(learner, cfg, step)
    state = copy.deepcopy(learner.get_state())
    cont = [total_loss(update(learner, cfg, step)) for step in range(5, 9)]
    _, restored = build_learner(policy_delay=2, individual_critic=True)
    torch.manual_seed(123)  # the restored RNG state must win over this
    restored.set_state(state)
    again = [total_loss(update(restored, cfg, step)) for step in range(5, 9)]
    assert cont == again
    for name in ("actor", "domain_q", "baseline", "domain_q_target", "local_q_target"):
        assert same(params(getattr(module_of(learner), name)), params(getattr(module_of(restored), name))), name


@pytest.mark.parametrize(
    "switch,check",
    [
        ({"counterfactual_baseline": False}, lambda m: m.baseline is None),
        ({"individual_critic": True}, lambda m: m.local_q is not None and m.local_q_target is not None),
        ({"neighbour_features": "absolute"}, lambda m: m.domain_q.q1.attention.neighbour_features == "absolute"),
        ({"attention_heads": 2}, lambda m: m.domain_q.q1.attention.heads == 2),
        ({"null_token": False}, lambda m: "null" not in dict(m.domain_q.q1.attention.named_parameters())),
        ({"domain_reward": "neighbours", "domain_radius": 10.0}, lambda m: True),
    ],
)
def test_each_switch_builds_and_trains(switch, check):
    cfg, learner = build_learner(**switch)
    assert check(module_of(learner))
    assert np.isfinite(total_loss(update(learner, cfg, 0)))


@pytest.mark.parametrize(
    "training,match",
    [
        ({"hidden": 30}, "hidden=30 is not a multiple of attention_heads=4"),
        ({"domain_weight": 0.0}, "domain_weight=0 without individual_critic"),
        ({"domain_radius": -1.0}, r"'domain_radius': -1.0; allowed: a finite number > 0"),
        ({"domain_reward": "sum"}, "'domain_reward': 'sum'; allowed: 'mean', 'neighbours', 'own'"),
    ],
)
def test_invalid_configs_are_refused(training, match):
    with pytest.raises(ValueError, match=match):
        make_config(**training).validate()


def test_compacting_the_domain_slots_changes_no_output():
    # the learner cuts the others to the largest domain in the batch; the critic must give the same values (order-invariant attention)
    torch.manual_seed(0)
    batch = {k: torch.as_tensor(v) for k, v in random_batch(3, 14).items()}
    cfg = TracoLossConfig(domain_radius=40.0, position_scale=100.0)
    d0, d1 = domains(batch, cfg)
    small, c0, c1 = domain_batch(batch, cfg)
    k = int(d0.sum(-1).max())
    assert 0 < k < 14 and c0.shape == (B, k) and small[col.OTHERS_STATE].shape == (B, k, S)
    assert torch.equal(c0.sum(-1), d0.sum(-1)) and torch.equal(c1.sum(-1), d1.sum(-1))  # every domain member kept
    critic = DomainCritic(O, S, A, hidden=32, heads=4)
    full = critic(batch[col.OBS], batch[col.ACTIONS], batch[col.STATE], batch[col.OTHERS_STATE], batch[col.OTHERS_ACTIONS], d0)
    cut = critic(small[col.OBS], small[col.ACTIONS], small[col.STATE], small[col.OTHERS_STATE], small[col.OTHERS_ACTIONS], c0)
    for a, b in zip(full, cut):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)
