"""Tests of the PettingZoo parallel adapter (coin_app.adapters.pettingzoo_env); the API checker over every scenario is in
test_scenario_conformance.py."""

import importlib.util
import re

import numpy as np
import pytest

from coin_app.adapters.pettingzoo_env import CoinParallelEnv
from coin_app.sim.config import make_config

# every vehicle times out after 10 own steps and vanishes at once (delay_done=0), so replacements spawn mid-episode
# at env steps 10 and 20 whatever the random actions do, all in the same step (no cap on respawns per step)
RESPAWN_CFG = {"num_agents": 4, "horizon": 30, "max_agent_steps": 10, "delay_done": 0, "respawns_per_step": 0}


def _num(aid):
    m = re.fullmatch(r"agent(\d+)", aid)
    assert m, aid
    return int(m.group(1))


def test_newcomers_get_zero_reward_and_false_flags():
    env = CoinParallelEnv("intersection", **RESPAWN_CFG)
    env.reset(seed=0)
    for t in range(1, 11):
        acting = list(env.agents)
        obs, rew, term, trunc, infos = env.step({a: np.array([0.0, -1.0], np.float32) for a in acting})
        assert set(obs) == set(rew) == set(term) == set(trunc) == set(infos)
        if t < 10:
            assert set(obs) == set(acting)
    # step 10: the four initial cars time out, four new ones spawn in the same step
    assert all(trunc[a] and not term[a] for a in acting)
    new = sorted(set(obs) - set(acting), key=_num)
    assert new == ["agent4", "agent5", "agent6", "agent7"]
    for a in new:
        assert rew[a] == 0.0 and term[a] is False and trunc[a] is False
        assert env.observation_space(a).contains(obs[a])
        assert infos[a]["episode_length"] == 0
    assert sorted(env.agents, key=_num) == new


def test_ids_are_fresh_and_unique_across_respawns():
    env = CoinParallelEnv("roundabout", num_agents=3, horizon=40, max_agent_steps=7, delay_done=0)
    rng = np.random.default_rng(5)
    for episode_seed in (11, 12):
        obs, _ = env.reset(seed=episode_seed)
        assert sorted(obs, key=_num) == ["agent0", "agent1", "agent2"] == sorted(env.agents, key=_num)
        seen, finished = set(obs), set()
        steps = 0
        while env.agents:
            prev_max = max(_num(a) for a in seen)
            obs, rew, term, trunc, _ = env.step({a: rng.uniform(-1, 1, 2) for a in env.agents})
            steps += 1
            assert not (set(obs) & finished), "a finished id came back"
            new = [a for a in obs if a not in seen]
            assert all(_num(a) > prev_max for a in new), "new ids must be numbered after every earlier id"
            seen |= set(obs)
            finished |= {a for a in rew if term[a] or trunc[a]}
            assert not (set(env.agents) & finished)
        # ids are handed out consecutively from agent0 and all belong to the pool
        assert seen == {f"agent{i}" for i in range(len(seen))}
        assert seen <= set(env.possible_agents)
        assert seen == finished
        assert len(seen) > 3 * 5, "expected many respawns (a time-out every 7 steps for 40 steps)"
        assert steps >= 40


def test_spaces_are_cached_per_agent_and_pool_is_bounded():
    env = CoinParallelEnv("bottleneck", num_agents=2, horizon=20)
    # pool: initial agents + at most min(8, num_agents) respawns per step of the horizon
    assert env.possible_agents == [f"agent{i}" for i in range(2 + 2 * 20)]
    for a in ("agent0", "agent41"):
        assert env.observation_space(a) is env.observation_space(a)
        assert env.action_space(a) is env.action_space(a)
        assert env.observation_space(a).shape == (91,)
        assert env.action_space(a).shape == (2,)
        assert np.all(env.action_space(a).low == -1) and np.all(env.action_space(a).high == 1)
    assert env.action_space("agent0") is not env.action_space("agent1")
    with pytest.raises(KeyError, match="agent42"):
        env.observation_space("agent42")
    with pytest.raises(KeyError):
        env.action_space("car0")


def test_constructor_forms_and_errors():
    cfg = make_config("roundabout", num_agents=3, horizon=10)
    env = CoinParallelEnv(cfg)
    assert env.config is cfg and env.driving_env.scenario == "roundabout"
    assert len(env.possible_agents) == 3 + 3 * 10
    assert CoinParallelEnv.metadata["name"] == "coin_driving_v0"
    with pytest.raises(ValueError, match="not both"):
        CoinParallelEnv(cfg, horizon=5)
    with pytest.raises(ValueError, match="bogus"):
        CoinParallelEnv("intersection", bogus=1)
    with pytest.raises(ValueError, match="render_mode"):
        CoinParallelEnv("intersection", render_mode="human")


def test_render():
    env = CoinParallelEnv("intersection", num_agents=2, horizon=10)
    env.reset(seed=0)
    with pytest.warns(UserWarning, match="render_mode"):
        assert env.render() is None  # no render_mode
    env = CoinParallelEnv("intersection", num_agents=2, horizon=10, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    if importlib.util.find_spec("coin_app.sim.rendering") is None:
        assert frame is None
    else:
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
        assert frame.std() > 0  # not a blank image
    env.close()
    assert env.agents == []
