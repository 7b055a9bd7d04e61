"""Tests of the RLlib MultiAgentEnv adapter (coin_app.adapters.rllib_env); RLlib's env checker over every scenario is in
test_scenario_conformance.py."""

import math

import gymnasium as gym
import numpy as np
import pytest
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.env.multi_agent_episode import MultiAgentEpisode
from ray.tune.registry import ENV_CREATOR, _global_registry

from coin_app.adapters.rllib_env import CoinMultiAgentEnv, register_envs
from coin_app.algorithms.common import policy_mapping_fn, shared_policy_config
from coin_app.sim.driving_env import DrivingEnv

BRAKE = np.array([0.0, -1.0], np.float32)
SPIN = np.array([1.0, 1.0], np.float32)  # full steering and full throttle: leaves the road


def _episode(env):
    return MultiAgentEpisode(
        observation_space=gym.spaces.Dict(env.observation_spaces),
        action_space=gym.spaces.Dict(env.action_spaces),
        agent_to_module_mapping_fn=policy_mapping_fn,
    )


def test_spaces_cover_every_possible_id():
    env = CoinMultiAgentEnv({"scenario": "roundabout", "num_agents": 4, "horizon": 50})
    # 4 initial agents + at most min(8, 4) = 4 respawns per step of the horizon
    assert env.possible_agents == [f"agent{i}" for i in range(4 + 4 * 50)]
    assert set(env.observation_spaces) == set(env.action_spaces) == set(env.possible_agents)
    obs_space, act_space = env.get_observation_space("agent0"), env.get_action_space("agent0")
    assert obs_space == gym.spaces.Box(0.0, 1.0, (91,), np.float32)
    assert act_space == gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
    for aid in env.possible_agents:
        assert env.get_observation_space(aid) is obs_space and env.get_action_space(aid) is act_space
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(infos) == set(env.agents) == {"agent0", "agent1", "agent2", "agent3"}
    assert all(obs_space.contains(o) for o in obs.values())


def test_respawning_episode_flags_and_rllib_episode():
    """agent0 drives off the road, everyone else brakes; replacements spawn until the horizon."""
    max_steps, horizon = 20, 30
    env = CoinMultiAgentEnv({"num_agents": 2, "horizon": horizon, "max_agent_steps": max_steps, "delay_done": 0})
    obs, infos = env.reset(seed=0)
    episode = _episode(env)
    episode.add_env_reset(observations=obs, infos=infos)
    born = dict.fromkeys(obs, 0)
    seen_done_mid_episode = False
    t = agent0_end = 0
    while True:
        t += 1
        assert episode.get_agents_to_act() == set(env.agents)  # RLlib asks exactly the acting agents
        actions = {a: SPIN if a == "agent0" else BRAKE for a in env.agents}
        obs, rew, term, trunc, infos = env.step(actions)
        episode.add_env_step(observations=obs, actions=actions, rewards=rew, infos=infos, terminateds=term, truncateds=trunc)
        assert set(rew) == set(actions) and set(infos) == set(obs)
        assert set(term) == set(trunc) == set(actions) | {"__all__"}
        for a in obs:
            if a not in actions:
                born[a] = t
                assert t < horizon, "no respawn at or after the horizon"
        if "agent0" in actions and term["agent0"]:
            agent0_end = t
            assert infos["agent0"]["out_of_road"] and not trunc["agent0"]
        for a in actions:
            if a != "agent0":  # a braking car stays alive exactly max_steps own steps
                timed_out = t - born[a] == max_steps
                assert trunc[a] == timed_out and not term[a] and infos[a]["max_step"] == timed_out
        if term["__all__"]:
            break
        assert trunc["__all__"] is False and not episode.is_done
        seen_done_mid_episode |= any(term[a] or trunc[a] for a in actions)
    assert 0 < agent0_end < t and seen_done_mid_episode
    # episode end: the last acting agents all timed out and nothing spawned after the horizon
    assert env.agents == [] and env.driving_env.episode_over
    assert all(trunc[a] for a in actions) and trunc["__all__"] is True
    assert episode.is_done
    assert set(episode.agent_episodes) == set(born) and len(born) > 2
    assert t == max(born.values()) + max_steps
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_all_present_agents_done_in_one_step_ends_episode_and_drops_newcomers():
    cfg = {"num_agents": 1, "horizon": 50, "max_agent_steps": 50, "delay_done": 0}
    env = CoinMultiAgentEnv(cfg)
    raw = DrivingEnv(scenario="intersection", **cfg)  # the same episode without the adapter
    obs, infos = env.reset(seed=0)
    raw.reset(seed=0)
    episode = _episode(env)
    episode.add_env_reset(observations=obs, infos=infos)
    for t in range(1, 51):
        obs, rew, term, trunc, infos = env.step({"agent0": SPIN})
        raw_obs, _, raw_term, _, _ = raw.step({"agent0": SPIN})
        assert infos["agent0"]["env_step"] == t
        episode.add_env_step(observations=obs, actions={"agent0": SPIN}, rewards=rew, infos=infos, terminateds=term, truncateds=trunc)
        if raw_term["agent0"]:
            break
        assert term == {"agent0": False, "__all__": False} and trunc == {"agent0": False, "__all__": False}
    else:
        pytest.fail("the spinning car never left the road")
    # without the adapter: the car left the road and its replacement spawned, episode not over
    assert set(raw_obs) == {"agent0", "agent1"} and not raw.episode_over and raw.agents == ["agent1"]
    # with it: the episode ends in exactly this step and the newcomer is never shown
    assert term == {"agent0": True, "__all__": True}
    assert trunc == {"agent0": False, "__all__": False}
    assert set(obs) == set(infos) == set(rew) == {"agent0"}
    assert infos["agent0"]["out_of_road"] and rew["agent0"] < 0
    assert env.agents == []
    assert episode.is_done and set(episode.agent_episodes) == {"agent0"}
    assert t > 1
    obs, _ = env.reset(seed=1)
    assert set(obs) == {"agent0"}


@pytest.mark.parametrize(
    ("overrides", "limit", "max_step"),
    [
        ({"max_agent_steps": 5}, 5, True),  # the vehicle's own step limit
        ({"max_agent_steps": 100, "force_stop_factor": 1, "horizon": 6}, 6, False),  # force stop of the env
    ],
)
def test_time_out_is_truncation_not_termination(overrides, limit, max_step):
    env = CoinMultiAgentEnv({"scenario": "bottleneck", "num_agents": 2, **overrides})
    env.reset(seed=3)
    for t in range(1, limit + 1):
        obs, rew, term, trunc, infos = env.step({a: BRAKE for a in env.agents})
        assert set(obs) == {"agent0", "agent1"}
        for a in ("agent0", "agent1"):
            assert term[a] is False
            assert trunc[a] is (t == limit)
            assert infos[a]["max_step"] is (max_step and t == limit)
            assert not infos[a]["crash_vehicle"] and not infos[a]["out_of_road"]
        assert term["__all__"] is trunc["__all__"] is (t == limit)
    assert env.agents == []


def test_bad_env_config_key_names_the_key():
    with pytest.raises(ValueError, match="no_such_key") as err:
        CoinMultiAgentEnv({"scenario": "intersection", "no_such_key": 3})
    assert "horizon" in str(err.value)  # the allowed keys are listed
    with pytest.raises(ValueError, match="scenario"):
        CoinMultiAgentEnv({"scenario": "highway"})
    with pytest.raises(ValueError, match="num_agents"):
        CoinMultiAgentEnv({"num_agents": 0})


def test_register_envs_merges_overrides_onto_the_scenario():
    ids = register_envs()
    assert ids == ["coin-intersection-v0", "coin-roundabout-v0", "coin-bottleneck-v0", "coin-arena-v0"]
    arena = _global_registry.get(ENV_CREATOR, "coin-arena-v0")({"num_vehicles": 2, "num_obstacles": 1})
    assert arena.driving_env.scenario == "arena" and arena.config.num_vehicles == 2 and len(arena.possible_agents) == 2
    for env_id, scenario in zip(ids, ["intersection", "roundabout", "bottleneck"]):
        env = _global_registry.get(ENV_CREATOR, env_id)({"num_agents": 3, "preset": "metadrive_compat"})
        assert isinstance(env, CoinMultiAgentEnv)
        assert env.config.scenario == scenario and env.config.num_agents == 3
        assert env.config.crash_penalty == 10.0  # the preset was applied
    default = _global_registry.get(ENV_CREATOR, "coin-roundabout-v0")({})
    assert default.config.num_agents == 40  # the roundabout's own default
    with pytest.raises(ValueError, match="contradicts"):
        _global_registry.get(ENV_CREATOR, "coin-bottleneck-v0")({"scenario": "intersection"})


def test_every_agent_maps_to_the_shared_module():
    assert {policy_mapping_fn(f"agent{i}", None) for i in range(50)} == {"shared"}
    assert policy_mapping_fn("agent3", None, worker=None) == "shared"
    cfg = shared_policy_config(PPOConfig())
    assert set(cfg.policies) == {"shared"}
    assert cfg.policy_mapping_fn("agent17", None) == "shared"


def test_outcome_counts_match_the_episode_metrics():
    """The adapter's per-agent outcome counts (logged each iteration) equal the evaluation recorder's on one episode."""
    from coin_app.evaluation.metrics import EpisodeRecorder
    from coin_app.sim.heuristic import HeuristicDriver

    env = CoinMultiAgentEnv({"scenario": "intersection", "num_agents": 12, "horizon": 400})
    obs, infos = env.reset(seed=3)
    driver = HeuristicDriver(env.driving_env)
    recorder = EpisodeRecorder()
    recorder.reset(infos)
    steps, speeds = 0, 0.0
    while True:
        acting = list(env.agents)
        obs, rew, term, trunc, infos = env.step(driver.actions())
        recorder.step(infos, {a: v for a, v in term.items() if a != "__all__"}, {a: v for a, v in trunc.items() if a != "__all__"}, rew)
        steps += len(acting)
        speeds += sum(math.hypot(*infos[a]["state"][2:4]) * env.config.max_speed for a in acting)
        if term["__all__"]:
            break
    m = recorder.metrics()
    counts = {"finished": m["num_vehicles"], "succeeded": m["num_arrived"], "collided": m["num_crashed"], "agent_steps": steps}
    assert {k: env.outcomes[k] for k in counts} == counts
    assert env.outcomes["speed_sum"] == pytest.approx(speeds, rel=1e-6)  # float32 states
    assert 1.0 < speeds / steps < env.config.max_speed  # vehicles that drive, below the speed cap
    assert m["num_arrived"] > 0 and m["num_crashed"] > 0  # the heuristic both arrives and crashes in dense traffic


def test_outcome_speeds_are_zero_when_every_vehicle_brakes():
    # the bicycle model stands still under the brake (MetaDrive's car jitters at +-0.2 m/s: test_vehicle.py)
    env = CoinMultiAgentEnv({"scenario": "intersection", "num_agents": 6, "horizon": 50, "dynamics": {"model": "bicycle"}})
    env.reset(seed=1)
    for _ in range(30):
        env.step(dict.fromkeys(env.agents, np.array([0.0, -1.0])))
    assert env.outcomes["agent_steps"] == 6 * 30 and env.outcomes["speed_sum"] == 0.0
