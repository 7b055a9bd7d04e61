"""The GAT attention figure's data: crossing conflicts by hand, the critic's own attention, one edge per neighbour and step."""

import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from fixtures import acting_counts

from coin_app.algorithms.cig_td3.critic import CentralCritic, CentralCriticConfig
from coin_app.evaluation import attention
from coin_app.evaluation.attention import conflict_summary, crossing_conflict, ego_attention
from coin_app.sim.config import make_config

EAST, NORTH = 0.0, math.pi / 2


def conflict(pos_j, heading_j, speed_j, speed_i=10.0):
    """Ego at the origin heading east at ``speed_i``; the other at ``pos_j``."""
    one = lambda x: np.array([x], dtype=float)  # noqa: E731
    return bool(crossing_conflict(np.zeros((1, 2)), one(EAST), one(speed_i), np.array([pos_j], float), one(heading_j), one(speed_j))[0])


@pytest.mark.parametrize(
    "pos_j,heading_j,speed_j,speed_i,expected",
    [
        ((20, -20), NORTH, 10, 10, True),  # both reach (20, 0) after 2 s
        ((20, -40), NORTH, 10, 10, False),  # the other after 4 s: beyond the 3 s horizon
        ((20, -35), NORTH, 10, 10, False),  # the other after 3.5 s: beyond the horizon too
        ((20, -35), NORTH, 20, 10, True),  # 2 s against 1.75 s
        ((20, -5), NORTH, 10, 10, True),  # 2 s against 0.5 s: 1.5 s apart, the limit (included)
        ((20, -4), NORTH, 10, 10, False),  # 2 s against 0.4 s: 1.6 s apart
        ((0, 5), EAST, 10, 10, False),  # parallel: no crossing
        ((-20, -20), NORTH, 10, 10, False),  # the meeting point is behind the ego
        ((20, 20), NORTH, 10, 10, False),  # ... and behind the other
        ((20, -20 * math.tan(math.radians(20))), math.radians(20), 10, 10, False),  # 20 degrees: not a crossing
        ((2, -2), NORTH, 0, 0, True),  # at rest the speed counts as 1 m/s: both 2 s from the point
    ],
)
def test_crossing_conflicts_by_hand(pos_j, heading_j, speed_j, speed_i, expected):
    assert conflict(pos_j, heading_j, speed_j, speed_i) is expected


def gat_critic(obs_dim, graph_radius=None):
    torch.manual_seed(0)
    cfg = CentralCriticConfig(obs_dim=obs_dim, latent_dim=4, hidden=16, node_width=8, graph_radius=graph_radius)
    return CentralCritic(cfg).eval()


def test_ego_attention_is_the_critics_own_for_each_ego_and_its_envs_vehicles():
    critic = gat_critic(6)
    rng = np.random.default_rng(0)
    b, s = 5, critic.cfg.state_dim
    obs, state, action = (rng.standard_normal((b, d)).astype(np.float32) for d in (6, s, 2))
    env = np.array([0, 1, 0, 0, 1])
    alphas, rows = ego_attention(critic, obs, state, action, env)
    assert alphas.shape == (b, 3) and rows.tolist() == [[2, 3], [4, -1], [0, 3], [0, 2], [1, -1]]  # each env's others in row order
    for i, (alpha, row) in enumerate(zip(alphas, rows, strict=True)):
        assert (alpha[1:][row < 0] == 0).all()  # past the env's vehicles
        alpha = alpha[: 1 + (row >= 0).sum()]
        others = [j for j in range(b) if env[j] == env[i] and j != i][::-1]  # alone and in reverse order
        t = lambda a: torch.as_tensor(a)[None]  # noqa: E731
        with torch.no_grad():
            critic.q1(
                t(obs[i]), t(state[i]), t(action[i]), t(state[others]), t(action[others]), torch.ones(1, len(others), dtype=torch.bool)
            )
        alone = critic.q1_branch.graph.last_attention[1][0, 0, 0].numpy()
        np.testing.assert_allclose(alpha, np.concatenate([alone[:1], alone[1:][::-1]]), rtol=1e-5, atol=1e-7)
        assert alpha.sum() == pytest.approx(1.0, abs=1e-5) and (alpha > 0).all()


def test_collected_edges_are_every_neighbour_at_every_step(monkeypatch):
    config = make_config("intersection", num_agents=6, horizon=60, max_agent_steps=60)
    torch.manual_seed(0)
    actor = torch.nn.Sequential(torch.nn.Linear(config.obs_dim, 2), torch.nn.Tanh())
    critic = gat_critic(config.obs_dim)
    monkeypatch.setattr(attention, "gat_module", lambda checkpoint: SimpleNamespace(actor=actor, central=critic))
    monkeypatch.setattr(attention, "scenario_of", lambda checkpoint: config)
    sample = attention.collect_attention(Path("checkpoint"), [5], min_neighbours=1, near_m=100.0)
    # the same episode by hand: at each env step every acting vehicle has the n - 1 others as neighbours (full graph)
    expected = [step for step, n in acting_counts(config, actor, 5) for _ in range(n * (n - 1))]
    edges = sample.edges
    assert sorted(edges["env_step"].tolist()) == sorted(expected)
    per_ego = edges.groupby(["env_step", "ego"])
    assert (per_ego["alpha"].sum() < 1.0).all()  # the rest is the ego's attention to itself
    assert (per_ego.size() == per_ego["degree"].first() - 1).all()
    np.testing.assert_allclose(edges["share"], edges["alpha"] * edges["degree"], rtol=1e-6)
    assert (edges["ego"] != edges["other"]).all() and (edges["distance"] > 0).all()
    summary = conflict_summary(edges)
    assert summary["count"].sum() == len(edges)
