"""The CPPO / MFPO critic inputs of real sampled episodes (respawns, chunks) equal brute-force vectors per env step."""

import copy

import numpy as np
import pytest
from fixtures import NO_BRAKES

from coin_app.algorithms.ppo_family.centralized import CRITIC_OBS, CriticInputs
from coin_app.sim.road_map import load_map
from coin_app.training import build_config

# cars that leave the road fast (no brakes) so that vehicles respawn within the sample
SETTINGS = {"num_agents": 5, "horizon": 60, "max_agent_steps": 60, "delay_done": 0, "dynamics": NO_BRAKES}
SETTINGS |= {"train_batch_size_per_learner": 100, "rollout_fragment_length": 50}
SETTINGS |= {"minibatch_size": 50, "num_epochs": 1, "hidden": 8}


@pytest.fixture(scope="module")
def sampled(ray_session):
    """Sampled episodes, and the train batch the CPPO learner's connector pipeline makes of them."""
    algo = build_config("cppo", "intersection", SETTINGS, 0).build_algo()
    try:
        eps = algo.env_runner.sample(num_timesteps=150, random_actions=True)
        learner = algo.learner_group._learner
        batch = learner._learner_connector(rl_module=learner.module, batch={}, episodes=copy.deepcopy(eps), shared_data={})
    finally:
        algo.stop()
    return eps, batch["shared"]


@pytest.fixture(scope="module")
def episodes(sampled):
    return sampled[0]


def brute_force_rows(episodes, scale, radius, k):
    """Per batch row: the own obs and the sorted neighbours [(dist, obs, action)] at its env step of its episode."""
    present = {}  # episode id -> [(env_step, agent, obs, action, pos)] over every row of the episode
    for ma in episodes:
        for aid, sa in ma.agent_episodes.items():
            infos = sa.get_infos(slice(0, len(sa)))
            for t in range(len(sa)):
                pos = np.asarray(infos[t]["state"][:2]) * scale
                present.setdefault(ma.id_, []).append((infos[t]["env_step"], aid, sa.get_observations(t), sa.get_actions(t), pos))
    rows = []
    for sa in CriticInputs(mode="concat", radius=1, num_neighbours=1, position_scale=1).single_agent_episode_iterator(episodes, False):
        infos = sa.get_infos(slice(0, len(sa)))
        for t in range(len(sa)):
            step, me = infos[t]["env_step"], np.asarray(infos[t]["state"][:2]) * scale
            cand = [
                (np.linalg.norm(p - me), o, a)
                for s, other, o, a, p in present[sa.multi_agent_episode_id]
                if s == step and other != sa.agent_id
            ]
            rows.append((sa.get_observations(t), sorted((c for c in cand if c[0] < radius), key=lambda c: c[0])[:k]))
    return rows


def run_piece(episodes, mode, radius, k):
    piece = CriticInputs(mode=mode, radius=radius, num_neighbours=k, position_scale=load_map("intersection").scale)
    obs = np.concatenate(
        [np.asarray(sa.get_observations(slice(0, len(sa)))) for sa in piece.single_agent_episode_iterator(episodes, False)]
    )
    return piece(rl_module=None, batch={"shared": {"obs": obs}}, episodes=episodes)["shared"][CRITIC_OBS]


def test_concat_input_equals_brute_force(episodes):
    assert any(len(ma.agent_episodes) > 5 for ma in episodes)  # respawned vehicles are in the sample
    scale = load_map("intersection").scale
    got = run_piece(episodes, "concat", 40.0, 4)
    rows = brute_force_rows(episodes, scale, 40.0, 4)
    assert len(got) == len(rows) and any(len(nb) > 0 for _, nb in rows)
    for vec, (own, nb) in zip(got, rows):
        want = np.zeros(91 + 4 * 93, np.float32)
        want[:91] = own
        for j, (_, o, a) in enumerate(nb):
            want[91 + 93 * j : 91 + 93 * j + 91] = o
            want[91 + 93 * j + 91 : 91 + 93 * (j + 1)] = a
        np.testing.assert_allclose(vec, want, atol=1e-6)


def test_pipeline_rows_ignore_the_artificial_bootstrap_rows(sampled):
    """In the learner pipeline every episode gets one artificial last row repeating its last info; real rows never see them."""
    episodes, batch = sampled
    real = batch["loss_mask"].numpy()
    assert (~real).sum() == sum(len(ma.agent_episodes) for ma in episodes)  # one artificial row per agent episode
    got = batch[CRITIC_OBS].numpy()[real]
    rows = brute_force_rows(episodes, load_map("intersection").scale, 40.0, 4)
    assert len(got) == len(rows)
    for vec, (own, nb) in zip(got, rows):
        assert np.count_nonzero(vec[91:]) == 0 if not nb else np.allclose(vec[91 : 91 + 91], nb[0][1], atol=1e-6)
        np.testing.assert_allclose(vec[:91], own, atol=1e-6)
        for j in range(len(nb), 4):  # no extra neighbour beyond the brute-force ones
            assert not vec[91 + 93 * j : 91 + 93 * (j + 1)].any()


def test_mean_field_input_equals_brute_force(episodes):
    scale = load_map("intersection").scale
    got = run_piece(episodes, "mean_field", 10.0, 4)
    rows = brute_force_rows(episodes, scale, 10.0, 10_000)
    for vec, (own, nb) in zip(got, rows):
        mean = np.mean([np.concatenate([o, a]) for _, o, a in nb], 0) if nb else np.zeros(93)
        np.testing.assert_allclose(vec, np.concatenate([own, mean]), atol=1e-5)


def test_misaligned_batch_is_refused(episodes):
    piece = CriticInputs(mode="concat", radius=40.0, num_neighbours=4, position_scale=1.0)
    with pytest.raises(RuntimeError, match="not aligned"):
        piece(rl_module=None, batch={"shared": {"obs": np.zeros((3, 91), np.float32)}}, episodes=episodes)
