"""The rollout iterator: batched and dict-env paths equal a hand-written DrivingEnv loop; it stops when it should."""

import numpy as np
import pytest

from coin_app.sim.config import make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.rollout import BatchedEnvs, DictEnvs, rollout
from coin_app.sim.simulator import DrivingSimulator

CFG = make_config("bottleneck", num_agents=6, horizon=80, max_agent_steps=80)
NO_RESPAWN = make_config("bottleneck", num_agents=6, horizon=100, max_agent_steps=100, allow_respawn=False)
SEEDS = [3, 4, 5]


def policy(obs):
    # row-wise and deterministic: steer towards checkpoint 1, throttle from the speed feature
    steer = np.clip(4.0 * (obs[:, 10] - 0.5), -1, 1)
    throttle = np.where(obs[:, 3] < 0.35, 0.6, -0.1)
    return np.stack([steer, throttle], 1)


def by_hand(config, seed, max_steps=10_000):
    """One episode through DrivingEnv directly, one agent at a time: [(obs, rewards, terms, truncs, infos), ...] from the reset on."""
    env = DrivingEnv(config)
    obs, infos = env.reset(seed=seed)
    steps = [(obs, {}, {}, {}, infos)]
    latest = dict(obs)
    while not env.episode_over and len(steps) <= max_steps:
        out = env.step({a: policy(latest[a][None])[0] for a in env.agents})
        latest.update(out[0])
        steps.append(out)
    return steps


def per_env(steps):
    """Rollout steps regrouped as {env: [its dicts at t = 0, 1, ...]}, checking the t's are consecutive."""
    out = {}
    for step in steps:
        for e, result in step.results.items():
            assert len(out.setdefault(e, [])) == step.t
            out[e].append(tuple(result))
    return out


@pytest.mark.parametrize("config", [CFG, NO_RESPAWN], ids=["respawn", "no_respawn"])
def test_batched_and_dict_paths_equal_a_hand_written_loop(config):
    batched = per_env(rollout(BatchedEnvs(DrivingSimulator(config, num_envs=len(SEEDS))), policy, SEEDS, 10_000))
    dict_envs = per_env(rollout(DictEnvs([DrivingEnv(config) for _ in SEEDS]), policy, SEEDS, 10_000))
    for e, seed in enumerate(SEEDS):
        ref = by_hand(config, seed)
        assert len(batched[e]) == len(dict_envs[e]) == len(ref)  # each env reported until its episode ended, no longer
        np.testing.assert_equal(batched[e], ref)
        np.testing.assert_equal(dict_envs[e], ref)
    if config is CFG:
        assert any(len({a for r in batched[e] for a in r[4]}) > config.num_agents for e in batched)  # a vehicle respawned


def test_stops_when_every_episode_is_over():
    envs = BatchedEnvs(DrivingSimulator(NO_RESPAWN, num_envs=len(SEEDS)))
    steps = list(rollout(envs, policy, SEEDS, 10_000))
    lengths = [len(by_hand(NO_RESPAWN, s)) - 1 for s in SEEDS]
    assert len(set(lengths)) == len(SEEDS)  # the episodes end at different steps
    assert [s.t for s in steps] == list(range(max(lengths) + 1))
    assert envs.episode_over.all()
    assert [max(s.t for s in steps if e in s.results) for e in range(len(SEEDS))] == lengths  # each env reported until its end


def test_stops_at_max_steps():
    for envs in (BatchedEnvs(DrivingSimulator(CFG, num_envs=2)), DictEnvs([DrivingEnv(CFG), DrivingEnv(CFG)])):
        steps = list(rollout(envs, policy, [7, 8], 5))
        assert [s.t for s in steps] == [0, 1, 2, 3, 4, 5]
        assert not envs.episode_over.any()
        assert all(sorted(s.results) == [0, 1] for s in steps)
        np.testing.assert_equal([tuple(s.results[1]) for s in steps], by_hand(CFG, 8, max_steps=5))


def test_bad_policy_shape_and_seed_count_are_refused():
    for envs in (BatchedEnvs(DrivingSimulator(CFG, num_envs=1)), DictEnvs([DrivingEnv(CFG)])):
        with pytest.raises(ValueError, match=r"shape \(6, 3\); expected \(6, 2\)"):
            list(rollout(envs, lambda o: np.zeros((len(o), 3)), [0], 3))
        with pytest.raises(ValueError, match="shape"):
            list(rollout(envs, lambda o: np.zeros((len(o) + 1, 2)), [0], 3))
        with pytest.raises(ValueError, match="one seed per env"):
            list(rollout(envs, policy, [0, 1], 3))
