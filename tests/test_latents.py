"""CVAE latents for the t-SNE figure: the same z_ij the centralized critic computes, pairs drawn correctly."""

from pathlib import Path
from types import SimpleNamespace

import numpy as np
import torch
from fixtures import acting_counts

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig
from coin_app.evaluation import latents
from coin_app.evaluation.latents import _pair_means, _pick_pairs
from coin_app.sim.config import make_config


def test_pair_means_equal_the_critics_own_latents():
    torch.manual_seed(0)
    critic = CentralCritic(CentralCriticConfig(obs_dim=6, state_dim=3, act_dim=2, latent_dim=4, hidden=16, node_width=8)).eval()
    b, n = 2, 3
    obs, state, action = torch.randn(b, 6), torch.randn(b, 3), torch.randn(b, 2)
    o_state, o_action = torch.randn(b, n, 3), torch.randn(b, n, 2)
    mask = torch.tensor([[1, 1, 0], [1, 1, 1]], dtype=torch.bool)
    with torch.no_grad():
        graph = critic._graph(state, action, o_state, o_action, mask)  # node 0 = ego, then the others
        pair_x = graph.packer.pack(torch.cat([graph.state_all, graph.action_all], -1))
        mu, _ = critic.local.encode(torch.cat([obs, state, action], -1), pair_x, graph.packer)
        grid = graph.packer.unpack(mu)  # (B, 1 + N, L)
    egos, partners = np.nonzero(mask.numpy())
    ours = _pair_means(
        critic,
        obs.numpy()[egos],
        state.numpy()[egos],
        action.numpy()[egos],
        o_state.numpy()[egos, partners],
        o_action.numpy()[egos, partners],
    )
    assert ours.shape == (5, 4)
    np.testing.assert_allclose(ours, grid[egos, partners + 1].numpy(), rtol=1e-5, atol=1e-6)


def test_pairs_are_distinct_agents_of_the_same_env():
    rng = np.random.default_rng(0)
    active = np.array([3, 4, 5, 10, 11, 20])
    env = np.array([0, 0, 0, 1, 1, 2])  # env 2 has a single vehicle: no pair
    egos, partners = _pick_pairs(active, env, 4, rng)
    assert len(egos) == 4 + 2  # env 0: 4 of its 6 ordered pairs; env 1: both of its 2
    slot_env = dict(zip(active, env))
    assert all(e != p and slot_env[e] == slot_env[p] for e, p in zip(egos, partners))
    assert len(set(zip(egos, partners))) == len(egos)
    assert 20 not in egos and 20 not in partners


def test_collected_latents_follow_the_episode(monkeypatch):
    torch.manual_seed(0)
    config = make_config("bottleneck", num_agents=5, horizon=40, max_agent_steps=40)
    actor = torch.nn.Sequential(torch.nn.Linear(config.obs_dim, 2), torch.nn.Tanh())
    with torch.no_grad():
        actor[0].bias[1] = 2.0  # full throttle: vehicles crash or leave the road, so the number acting changes
    central = CentralCritic(CentralCriticConfig(obs_dim=config.obs_dim, latent_dim=4, hidden=16, node_width=8))
    monkeypatch.setattr(latents, "cvae_module", lambda checkpoint: SimpleNamespace(actor=actor, central=central))
    monkeypatch.setattr(latents, "scenario_of", lambda checkpoint: config)
    sample = latents.collect_latents(Path("checkpoint"), [3], pairs_per_step=3, sample_seed=1)
    # the same episode by hand: min(3, n (n - 1)) ordered pairs of the n acting vehicles at every env step
    expected = [step for step, n in acting_counts(config, actor, 3) for _ in range(min(3, n * (n - 1)))]
    assert sample.env_step.tolist() == expected
    assert len(set(np.bincount(expected))) > 1  # the number of pairs changes along the episode
    assert sample.z.shape == (len(expected), 4) and np.isfinite(sample.z).all()
    assert (sample.scenario == "bottleneck").all() and (sample.distance > 0).all()
