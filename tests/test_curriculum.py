"""A curriculum over traffic density: fewer vehicles at reset (and as the respawn cap) for a first phase of training.

The simulator's cap is checked against the smaller scenario itself (an episode capped at n vehicles of a 30-vehicle
config is the n-vehicle config's episode, vehicle by vehicle), against its own timing (episodes in progress keep their
cap) and its refusals; the TD3 family's training step moves every env runner to the scenario's count when the first
phase ends.
"""

import numpy as np
import pytest
import torch
from fixtures import tiny

from coin_app.sim.config import make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.training import build_config

torch.set_num_threads(1)


def _drive(env, steps):
    """Observations and rewards by agent id over ``steps`` steps of a fixed observation-dependent policy."""
    obs, _ = env.reset(seed=7)
    record = [{a: o.copy() for a, o in obs.items()}]
    for _ in range(steps):
        if env.episode_over:
            break
        actions = {a: np.array([np.tanh(3 * (obs[a][1] - 0.5)), 1.0 - 2 * obs[a][20]]) for a in env.agents}
        obs, rewards, terms, truncs, _ = env.step(actions)
        record.append(({a: o.copy() for a, o in obs.items()}, dict(rewards), dict(terms), dict(truncs)))
    return record


def test_a_capped_episode_is_the_smaller_scenarios_episode():
    capped = DrivingEnv(make_config("intersection", num_agents=30))
    capped.set_num_agents(5)
    small = DrivingEnv(make_config("intersection", num_agents=5))
    got, want = _drive(capped, 400), _drive(small, 400)
    assert len(got) == len(want) > 100
    assert sum(len(step[0]) - len(step[1]) for step in want[1:]) > 0  # vehicles respawned in the smaller scenario
    for g, w in zip(got[1:], want[1:]):
        assert g[0].keys() == w[0].keys() and g[1:] == w[1:]
        for agent in w[0]:
            np.testing.assert_array_equal(g[0][agent], w[0][agent])
    assert max(len(step[0]) for step in got[1:]) <= 5


def test_the_cap_takes_effect_at_the_next_episode_only():
    env = DrivingEnv(make_config("intersection", num_agents=12))
    obs, _ = env.reset(seed=3)
    assert len(obs) == 12
    env.set_num_agents(4)  # the episode in progress keeps its 12
    env.step({a: np.array([0.0, 1.0]) for a in env.agents})
    assert len(env.agents) == 12 and env.sim.agent_cap[0] == 12
    obs, _ = env.reset(seed=3)
    assert len(obs) == 4 and env.sim.agent_cap[0] == 4


@pytest.mark.parametrize("bad", [0, 13, 2.0, True])
def test_a_bad_vehicle_count_is_refused_in_one_line(bad):
    env = DrivingEnv(make_config("intersection", num_agents=12))
    with pytest.raises(ValueError, match=r"num_agents=.*allowed: an integer from 1 to the scenario's num_agents \(12\)"):
        env.set_num_agents(bad)


@pytest.mark.parametrize(
    "settings,match",
    [
        ({"curriculum_agents": 2}, r"curriculum_agents=2 with curriculum_steps=0; allowed: both > 0"),
        ({"curriculum_steps": 100}, r"curriculum_agents=0 with curriculum_steps=100; allowed: both > 0"),
        ({"curriculum_agents": 6, "curriculum_steps": 100}, r"curriculum_agents=6; allowed: 1 to 5"),
    ],
)
def test_a_bad_curriculum_is_refused_before_any_work(settings, match):
    _, base = tiny("itd3", "intersection", num_agents=6)
    with pytest.raises(ValueError, match=match):
        build_config("itd3", "intersection", {**base, **settings}, 0)


@pytest.mark.usefixtures("ray_session")
def test_the_training_step_moves_every_env_to_the_full_count_after_the_first_phase(tmp_path):
    # 6 vehicles, 2 in the first 50 env steps; episodes of at most 40 steps end (all vehicles out by their step limit)
    _, settings = tiny("cig_td3", "intersection", num_agents=6, curriculum_agents=2, curriculum_steps=50, eval_every=0)
    algo = build_config("cig_td3", "intersection", settings, 0).build_algo()
    sim = algo.env_runner.vector_env.sim
    caps, live = [], []
    for k in range(160):
        if k == 20:  # a run restored in the first phase gives its new env runner the phase's count again
            algo.save_to_path(str(tmp_path / "ckpt"))
            restored = build_config("cig_td3", "intersection", settings, 0).build_algo()
            restored.restore_from_path(str(tmp_path / "ckpt"))
            assert restored.env_runner.vector_env.sim._next_cap == 6  # a fresh runner: the scenario's count
            restored.training_step()
            assert restored.env_runner.vector_env.sim._next_cap == 2
            restored.stop()
        algo.training_step()
        caps.append(int(sim.agent_cap[0]))
        live.append(int((sim.status != 0).sum()))
    steps = algo.env_runner.num_env_steps_sampled_lifetime
    assert steps == 160
    first_full = caps.index(6)
    assert set(caps[:first_full]) == {2} and set(caps[first_full:]) == {6}
    assert max(live[:first_full]) <= 2 and max(live[first_full:]) == 6
    assert 50 <= first_full + 1 <= 50 + 45  # the first episode started after the phase's end (its steps counted 1-based)
    assert algo.metrics.peek("curriculum_agents") == 6
    algo.stop()
