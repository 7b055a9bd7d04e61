"""The heuristic driver: route paths and single-vehicle success on every scenario."""

import numpy as np
import pytest

from coin_app.sim.config import make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.heuristic import HeuristicDriver, route_paths, single_vehicle_outcomes
from coin_app.sim.road_map import load_map
from coin_app.sim.rollout import DictEnvs, rollout
from coin_app.sim.scenes import DRIVING_SCENARIOS

SCENARIOS = list(DRIVING_SCENARIOS)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_single_vehicle_arrives_in_at_least_99_percent_of_200_spawns(scenario):
    outcomes = single_vehicle_outcomes(scenario, list(range(200)))
    arrived = sum(o == "arrive_dest" for o in outcomes)
    assert arrived >= 198, {o: outcomes.count(o) for o in set(outcomes)}


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_route_paths_are_continuous_and_end_on_the_final_road(scenario):
    m = load_map(scenario)
    for route, path in zip(m.routes, route_paths(scenario)):
        step = np.linalg.norm(np.diff(path, axis=0), axis=1)
        assert step.max() < 1.6  # 1 m samples; lane changes spread over 12 m
        start = m.position(np.array([route.spawn_lane]), np.zeros(1), np.zeros(1))[0]
        assert np.linalg.norm(path[0] - start) < 1e-6
        # the path passes the end of the final road (any of its lanes)
        final_road = m.lane_road[route.final_lane]
        ends = m.end[m.road_lanes[final_road][m.road_lanes[final_road] >= 0]]
        assert np.min(np.linalg.norm(path[:, None, :] - ends[None], axis=2)) < 0.6


def test_batched_outcomes_equal_one_env_at_a_time():
    seeds = [3, 11, 42]
    together = single_vehicle_outcomes("intersection", seeds)
    alone = [single_vehicle_outcomes("intersection", [s])[0] for s in seeds]
    assert together == alone


def test_driver_as_rollout_policy_equals_its_dict_actions():
    config = make_config("intersection", num_agents=12, horizon=300)
    env = DrivingEnv(config)
    via_rollout = [tuple(step.results[0]) for step in rollout(DictEnvs([env]), HeuristicDriver(env), [5], 10_000)]
    env = DrivingEnv(config)
    driver = HeuristicDriver(env)
    obs, infos = env.reset(seed=5)
    by_hand = [(obs, {}, {}, {}, infos)]
    while not env.episode_over:
        by_hand.append(env.step(driver.actions()))
    np.testing.assert_equal(via_rollout, by_hand)
    outcomes = {k for *_, infos in by_hand for i in infos.values() for k in ("arrive_dest", "crash_vehicle") if i[k]}
    assert outcomes == {"arrive_dest", "crash_vehicle"}  # a busy episode, not a trivial one


def test_driver_refuses_a_batch_that_is_not_its_acting_vehicles():
    env = DrivingEnv(make_config("intersection", num_agents=4))
    driver = HeuristicDriver(env)
    env.reset(seed=0)
    with pytest.raises(ValueError, match="4 acting vehicles"):
        driver(np.zeros((3, env.config.obs_dim)))
