"""Conformance of every scenario (VMAS style): each driving scene of coin_app/sim/scenes.py and the arena, on small settings.

The contract every env keeps, whatever its scene: reset and step return per-agent dicts over the right agents, inside the
declared spaces; the same seed gives the same episode and another seed another; agent ids are never reused within an
episode and a finished agent never acts again; PettingZoo's ``parallel_api_test`` and RLlib's
``check_multiagent_environments`` pass. Driving scenes also respawn: newcomers take fresh ids while the vehicle cap allows.
"""

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test
from ray.rllib.utils.pre_checks.env import check_multiagent_environments

from coin_app.adapters.pettingzoo_env import CoinParallelEnv
from coin_app.adapters.rllib_env import CoinMultiAgentEnv
from coin_app.backends.factory import make_driving_env
from coin_app.sim.scenarios import config_from_dict
from coin_app.sim.scenes import ARENA, DRIVING_SCENARIOS, SCENARIOS

# every vehicle times out after 10 own steps and vanishes at once (delay_done=0), so replacements enter one per step
# (MetaDrive's respawn rule) from env steps 10 and 20
DRIVING_SMALL = {"num_agents": 4, "horizon": 30, "max_agent_steps": 10, "delay_done": 0}
ARENA_SMALL = {"num_vehicles": 3, "num_obstacles": 1, "max_steps": 30}
EXPECTED_WARNING = "No agents present but not all possible_agents are terminated or truncated"  # most pool ids never appear


def small(name):
    """The small settings of scenario ``name``."""
    return ARENA_SMALL if name == ARENA else DRIVING_SMALL


def make_env(name):
    return make_driving_env(config_from_dict(name, small(name)))


def play(env, seed, policy_seed=0, max_steps=200, to_the_end=True):
    """One episode under uniform random actions: per step (acting agents, obs, rewards, terminated, truncated, infos, agents after)."""
    rng = np.random.default_rng(policy_seed)
    obs, infos = env.reset(seed=seed)
    steps = [(None, obs, None, None, None, infos, list(env.agents))]
    for _ in range(max_steps):
        if env.episode_over:
            break
        acting = list(env.agents)
        actions = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in acting}
        steps.append((acting, *env.step(actions), list(env.agents)))
    assert env.episode_over or not to_the_end, f"the episode did not end within {max_steps} steps"
    return steps


@pytest.mark.parametrize("name", SCENARIOS)
def test_reset_gives_each_agent_an_observation_inside_its_space_and_an_info(name):
    env = make_env(name)
    obs, infos = env.reset(seed=0)
    assert obs and set(obs) == set(infos) == set(env.agents) <= set(env.possible_agents)
    space = env.observation_space
    assert env.action_space.shape == (2,) and (env.action_space.low == -1).all() and (env.action_space.high == 1).all()
    for o in obs.values():
        assert o.shape == space.shape and o.dtype == np.float32 and space.contains(o)


@pytest.mark.parametrize("name", SCENARIOS)
def test_a_step_answers_every_acting_agent_and_ids_are_never_reused(name):
    env = make_env(name)
    steps = play(env, seed=1)
    seen = set(steps[0][1])
    finished = set()
    for acting, obs, rewards, terminated, truncated, infos, agents in steps[1:]:
        assert set(rewards) == set(terminated) == set(truncated) == set(acting)  # every agent that acted, no other
        newcomers = set(obs) - set(acting)
        assert set(infos) == set(obs) and not newcomers & seen  # a newcomer's id is fresh
        assert not finished & set(acting)  # a finished agent never acts again
        for a in acting:
            assert np.isfinite(rewards[a]) and isinstance(terminated[a], bool) and isinstance(truncated[a], bool)
            assert a in obs and env.observation_space.contains(obs[a])  # the final observation of one that finished too
        finished |= {a for a in acting if terminated[a] or truncated[a]}
        seen |= newcomers
        assert set(agents) == (set(acting) - finished) | newcomers
    assert seen <= set(env.possible_agents)


def _same(a, b):
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return np.array_equal(a, b)


@pytest.mark.parametrize("name", SCENARIOS)
def test_the_same_seed_gives_the_same_episode_and_another_seed_another(name):
    first, again, other = (play(make_env(name), seed, max_steps=15, to_the_end=False) for seed in (3, 3, 4))
    assert _same(first, again)
    assert not _same(first[0][1], other[0][1])  # the starts already differ


@pytest.mark.parametrize("name", DRIVING_SCENARIOS)
def test_a_driving_scene_respawns_fresh_ids_within_its_cap(name):
    env = make_env(name)
    cap = env.config.num_agents
    steps = play(env, seed=2)
    spawned_at = [len(set(obs) - set(acting)) for acting, obs, *_ in steps[1:]]
    # every vehicle times out at 10 own steps; one replacement enters per step
    assert spawned_at[9 : 9 + cap] == spawned_at[19 : 19 + cap] == [1] * cap and sum(spawned_at) == 2 * cap
    assert all(len(acting) <= cap for acting, *_ in steps[1:])
    assert spawned_at[29:] == [0] * len(spawned_at[29:])  # none after the horizon


@pytest.mark.parametrize("name", SCENARIOS)
def test_pettingzoo_parallel_api_test_passes(name):
    env = CoinParallelEnv(name, **small(name))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        parallel_api_test(env, num_cycles=100)
    messages = {str(w.message) for w in caught}
    assert messages <= {EXPECTED_WARNING}, messages


@pytest.mark.parametrize("name", SCENARIOS)
def test_rllib_env_checker_passes(name):
    check_multiagent_environments(CoinMultiAgentEnv({"scenario": name, **small(name)}))  # raises ValueError on a violation
