"""The navigation-and-parking arena: dynamics, reward terms, success test, observation, generator, env, heuristic."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from coin_app.evaluation.arena_suite import WithMeta, evaluate_suite, policy_config, summarize
from coin_app.inference import load_policy
from coin_app.inference.switching import PAPER_OBSERVATION as PAPER
from coin_app.inference.switching import SwitchingPolicy, observation_options, observed_entities
from coin_app.sim.arena.config import RewardConfig, make_arena_config
from coin_app.sim.arena.env import ArenaEnv, arena_metrics
from coin_app.sim.arena.generator import PAPER_CASES, Layout, generate, heldout_rng, training_rng
from coin_app.sim.arena.heuristic import (
    CANDIDATES,
    CLEARANCE_CAP,
    FILTER_MARGIN,
    FOOTPRINT_OFFSET,
    FOOTPRINT_RADIUS,
    avoiding_actions,
    heuristic_actions,
    may_come_near,
    planning_actions,
    rollout_clearance,
)
from coin_app.sim.arena.observation import layout_of
from coin_app.sim.arena.reward import angle_reward, distance_reward, obstacle_reward, step_reward, time_reward
from coin_app.sim.arena.simulator import ArenaSimulator
from coin_app.sim.dynamics import friction_bicycle_step

CFG = make_arena_config()
R_VEH = math.hypot(2.5, 1.0) / 2  # a vehicle's bounding radius


# ---------------------------------------------------------------- dynamics (Eq. 1)


def test_friction_bicycle_step_by_hand():
    pos, heading, speed = np.array([[1.0, 2.0]]), np.array([0.3]), np.array([2.0])
    p, h, v = friction_bicycle_step(pos, heading, speed, np.array([1.0]), np.array([0.3]), 0.1, 2.0, 0.99)
    v_want = 0.99 * 2.0 + 1.0 * 0.1  # 2.08
    h_want = 0.3 + v_want * math.tan(0.3) * 0.1 / 2.0
    assert v[0] == pytest.approx(v_want) and h[0] == pytest.approx(h_want)
    np.testing.assert_allclose(p[0], [1.0 + v_want * 0.1 * math.cos(h_want), 2.0 + v_want * 0.1 * math.sin(h_want)])
    # reversing: the speed goes negative and the car moves backwards
    p, h, v = friction_bicycle_step(pos, heading, np.array([0.0]), np.array([-1.0]), np.array([0.0]), 0.1, 2.0, 0.99)
    assert v[0] == pytest.approx(-0.1) and p[0] @ [math.cos(0.3), math.sin(0.3)] < pos[0] @ [math.cos(0.3), math.sin(0.3)]


def test_friction_sets_the_speed_limit_and_the_coasting_decay():
    v = np.array([0.0])
    pos, h = np.zeros((1, 2)), np.zeros(1)
    for _ in range(300):  # full pedal: v_n = (p dt / (1 - beta)) (1 - beta^n) -> 10 m/s
        pos, h, v = friction_bicycle_step(pos, h, v, np.array([1.0]), np.array([0.0]), 0.1, 2.0, 0.99)
    assert v[0] == pytest.approx(10.0 * (1 - 0.99**300))
    for _ in range(50):  # coasting: v_n = beta^n v_0
        pos, h, v = friction_bicycle_step(pos, h, v, np.array([0.0]), np.array([0.0]), 0.1, 2.0, 0.99)
    assert v[0] == pytest.approx(10.0 * (1 - 0.99**300) * 0.99**50)


def test_constant_speed_and_steering_drive_a_circle_of_radius_l_over_tan():
    steer, v0 = 0.4, 3.0
    radius = 2.0 / math.tan(steer)
    pos, h, v = np.zeros((1, 2)), np.zeros(1), np.array([v0])
    pedal = np.array([(1 - 0.99) * v0 / 0.1])  # holds the speed against friction
    points = []
    for _ in range(200):
        pos, h, v = friction_bicycle_step(pos, h, v, pedal, np.array([steer]), 0.1, 2.0, 0.99)
        points.append(pos[0].copy())
    pts = np.array(points)
    # each step is a chord of length v dt turning by v dt / R: the points are the vertices of a
    # regular polygon of circumradius (v dt / 2) / sin(v dt / (2 R))
    fit = np.linalg.lstsq(np.column_stack([2 * pts, np.ones(len(pts))]), (pts**2).sum(1), rcond=None)[0]
    chord_radius = (v0 * 0.1 / 2) / math.sin(v0 * 0.1 / radius / 2)
    np.testing.assert_allclose(np.linalg.norm(pts - fit[:2], axis=1), chord_radius, rtol=1e-6)


# ---------------------------------------------------------------- reward terms (Eqs. 2-6)

RC = RewardConfig()


def test_distance_reward_sign_and_floor():
    r_hat = RC.distance_scale * (RC.distance_offset - 20.0)  # 0.5 at 20 m
    got = distance_reward(RC, np.array([20.0, 20.0, 3.0, 200.0, 200.0]), np.array([20.5, 19.5, 2.5, 201.0, 199.0]))
    # closer: +r_hat; away: -r_hat; away but inside d_c: +; far: the floor gamma, signed
    gamma = RC.min_distance_reward
    np.testing.assert_allclose(got, [r_hat, -r_hat, RC.distance_scale * (RC.distance_offset - 3.0), gamma, -gamma])


def test_angle_reward_inside_its_radius_only():
    r_dis = np.array([0.6, -0.6, 0.6, 0.6])
    got = angle_reward(RC, np.array([2.0, 2.0, 2.0, 6.0]), np.array([0.0, 0.0, math.pi, 0.0]), r_dis)
    np.testing.assert_allclose(got, [0.5 * 0.6, 0.5 * 0.6, -0.5 * 0.6, 0.0])  # |r_dis|, 0 outside d_a_min


def test_obstacle_penalty_band():
    contact = np.array([[True, False, False, False, False]])
    clearance = np.array([[-0.5, 1.0, 0.1, 5.0, np.inf]])
    band = RC.proximity_scale * RC.collision_reward
    want = RC.collision_reward + band / 1.0 + band / RC.collision_clearance  # overlap, 1 m, capped 1/d, beyond d_min, itself
    assert obstacle_reward(RC, contact, clearance)[0] == pytest.approx(want)


def test_time_success_and_truncation_terms():
    assert time_reward(RC, 150, 0.1) == pytest.approx(-RC.time_scale * 0.1 * 150)
    args = (np.array([10.0] * 3), np.array([10.5] * 3), np.zeros(3), np.zeros((3, 1), bool), np.full((3, 1), np.inf), 7, 0.1)
    r = step_reward(RC, *args, np.array([True, False, False]), np.array([False, True, False]))
    shaped = RC.distance_scale * (RC.distance_offset - 10.0) - RC.time_scale * 0.1 * 7
    np.testing.assert_allclose(r, [RC.success_reward, RC.truncation_reward, shaped])


# ---------------------------------------------------------------- the simulator on constructed layouts


def layout(starts, targets, obstacles=()):
    return Layout(np.array(starts, float), np.array(targets, float), np.array(obstacles, float).reshape(-1, 3))


def test_success_needs_position_heading_and_speed():
    env = ArenaEnv(CFG)
    # parked exactly on the target: the first (zero) action keeps it there -> success, terminated, r_succ
    obs, _ = env.reset(options={"layout": layout([[3.0, 4.0, 0.5]], [[3.0, 4.0, 0.5]])})
    _, rew, term, trunc, info = env.step({"agent0": np.zeros(2)})
    assert term["agent0"] and not trunc["agent0"] and rew["agent0"] == RC.success_reward and info["agent0"]["success"]
    assert env.episode_over and env.agents == []
    sim = env.sim
    for dx, dh, v, ok in (
        (1.2, 0.0, 0.0, True),
        (1.3, 0.0, 0.0, False),
        (0.0, 0.19, 0.0, True),
        (0.0, 0.21, 0.0, False),
        (0.0, 0.0, 0.04, True),
        (0.0, 0.0, -0.06, False),
    ):
        sim.pos = np.array([[3.0 + dx, 4.0]])
        sim.heading = np.array([0.5 + dh])
        sim.speed = np.array([v])
        assert bool(sim.is_success()[0]) is ok, (dx, dh, v)


def test_reward_through_the_simulator_with_an_obstacle_in_the_band():
    # vehicle at the origin heading +x, target 30 m ahead; an obstacle of radius 1 whose centre is 4 m to the left
    env = ArenaEnv(CFG)
    env.reset(options={"layout": layout([[0.0, 0.0, 0.0]], [[30.0, 0.0, 0.0]], [[0.0, 4.0, 1.0]])})
    _, rew, _, _, info = env.step({"agent0": np.array([0.0, 1.0])})
    x = 0.1 * 0.1  # v' = 0.1, one step of 0.1 s
    d = 30.0 - x
    clearance = math.hypot(x, 4.0) - 1.0 - R_VEH
    want = RC.distance_scale * (RC.distance_offset - d) + RC.proximity_scale * RC.collision_reward / clearance - RC.time_scale * 0.1 * 1
    assert rew["agent0"] == pytest.approx(want) and info["agent0"]["collisions"] == 0


def test_collision_events_are_rising_edges_and_the_rate_is_per_metre():
    # two vehicles overlapping side by side: one event each, no more while they stay in contact
    env = ArenaEnv(CFG)
    env.reset(options={"layout": layout([[0.0, 0.0, 0.0], [0.0, 0.8, 0.0]], [[20.0, 0.0, 0.0], [20.0, 10.0, 0.0]])})
    for _ in range(5):
        _, rew, _, _, info = env.step({a: np.zeros(2) for a in env.agents})
    assert [info[a]["collisions"] for a in ("agent0", "agent1")] == [1, 1] and info["agent0"]["collided"]
    assert rew["agent0"] < RC.collision_reward + 1.0  # the overlap penalty is in the reward every step
    # drive one car away (no contact), then back into the other: a second event
    sim = env.sim
    sim.pos[1] = [0.0, 3.0]
    env.step({a: np.zeros(2) for a in env.agents})
    sim.pos[1] = [0.0, 0.8]
    env.step({a: np.zeros(2) for a in env.agents})
    m = arena_metrics(sim)
    assert m["collisions"] == 4 and m["distance"] == 0.0 and m["collision_rate"] == 0.0
    sim.distance[:] = [2.0, 3.0]
    assert arena_metrics(sim)["collision_rate"] == pytest.approx(4 / 5.0)
    assert arena_metrics(sim)["success_to_goal_rate"] == 0.0


def test_step_limit_truncates_with_r_trunc():
    env = ArenaEnv(make_arena_config(max_steps=3))
    env.reset(options={"layout": layout([[0.0, 0.0, 0.0]], [[20.0, 0.0, 0.0]])})
    for _ in range(3):
        _, rew, term, trunc, _ = env.step({"agent0": np.zeros(2)})
    assert trunc == {"agent0": True} and term == {"agent0": False} and rew["agent0"] == RC.truncation_reward and env.episode_over


# ---------------------------------------------------------------- observation


def test_observation_target_and_closest_entity_on_constructed_layouts():
    env = ArenaEnv(CFG)
    # ego at the origin heading +y; target at (3, 4) heading 0.5; a vehicle at (-5, 0) heading 0; obstacle r 1 at (0, 10)
    obs, _ = env.reset(options={"layout": layout([[0, 0, math.pi / 2], [-5, 0, 0]], [[3, 4, 0.5], [-20, 0, 0]], [[0, 10, 1]])})
    o = obs["agent0"]
    np.testing.assert_allclose(o[0:2], [4 / 25, -3 / 25], atol=1e-6)  # (3, 4) seen from a car facing +y
    np.testing.assert_allclose(o[2:4], [math.sin(0.5 - math.pi / 2), math.cos(0.5 - math.pi / 2)], atol=1e-6)
    np.testing.assert_allclose(o[4:6], [0.0, 0.0])
    # clearances: vehicle 5 - 2 R_VEH = 2.31 m beats the obstacle's 10 - 1 - R_VEH = 7.65 m
    np.testing.assert_allclose(o[6:13], [0.0, 5 / 25, -1.0, 0.0, R_VEH / 3, 0.0, 1.0], atol=1e-6)
    # a large obstacle is nearer by clearance than a small one whose centre is nearer
    obs, _ = env.reset(options={"layout": layout([[0, 0, 0]], [[20, 0, 0]], [[7.0, 0, 3.0], [0, -5.5, 1.0]])})
    np.testing.assert_allclose(obs["agent0"][6:13], [7 / 25, 0.0, 0.0, 1.0, 1.0, 0.0, 1.0], atol=1e-6)
    # alone: the entity slots are empty
    obs, _ = env.reset(options={"layout": layout([[0, 0, 0]], [[20, 0, 0]])})
    np.testing.assert_allclose(obs["agent0"][6:13], [0, 0, 0, 1, 0, 0, 0])
    assert env.observation_space.shape == (13,)


# ---------------------------------------------------------------- generator


def pairwise_min(points):
    d = np.linalg.norm(points[:, None] - points[None], axis=-1)
    return np.min(d[np.triu_indices(len(points), 1)]) if len(points) > 1 else np.inf


@pytest.mark.parametrize("side", ["left", "both"])
def test_generator_guarantees(side):
    cfg = make_arena_config(obstacle_side=side)
    lefts = []
    for n, m in ((2, 4), (4, 8), (10, 8), (20, 4), (1, 12)):
        for k in range(6):
            lay = generate(heldout_rng(n, m, k), cfg, n, m)
            assert lay.starts.shape == (n, 3) and lay.targets.shape == (n, 3) and lay.obstacles.shape == (m, 3)
            assert pairwise_min(lay.starts[:, :2]) >= 5.0 and pairwise_min(lay.targets[:, :2]) >= 5.0
            assert np.all(np.abs(lay.starts[:, 2]) <= math.pi) and np.all(np.abs(lay.targets[:, 2]) <= math.pi)
            if n == 1:
                assert np.all(np.abs(np.concatenate([lay.starts[:, :2], lay.targets[:, :2]])) <= 25.0)
            pts = np.concatenate([lay.starts[:, :2], lay.targets[:, :2]])
            for x, y, r in lay.obstacles:
                assert 1.0 <= r <= 3.0
                assert np.min(np.linalg.norm(pts - [x, y], axis=1)) >= r + 5.0
                if n > 4:  # dense scenes may widen the ranges (3 m per 100 failed draws): clearance only
                    continue
                # on (or beside) some vehicle's straight path: along in [-7, d + 7], lateral within 7 m
                ok = []
                for s, t in zip(lay.starts[:, :2], lay.targets[:, :2]):
                    u = (t - s) / np.linalg.norm(t - s)
                    along, lateral = (np.array([x, y]) - s) @ u, (np.array([x, y]) - s) @ [-u[1], u[0]]
                    ok.append((-7 <= along <= np.linalg.norm(t - s) + 7, lateral))
                assert any(a and abs(lat) <= 7.0 for a, lat in ok)
                lefts.append(any(a and 0 <= lat <= 7.0 for a, lat in ok))
    assert all(lefts) if side == "left" else not all(lefts)


def test_short_generator_starts_near_the_targets():
    cfg = make_arena_config(generator="short")
    for k in range(20):
        lay = generate(training_rng(k), cfg, 8, 8)
        d = np.linalg.norm(lay.starts[:, :2] - lay.targets[:, :2], axis=1)
        assert np.all(d >= 1.0) and pairwise_min(lay.starts[:, :2]) >= 5.0
        assert np.all(d <= 7.5 + 3.0 * 5)  # 7.5 m unless the widening rule had to step in


def test_test_sets_are_fixed_and_disjoint_from_training():
    assert len(PAPER_CASES) == 24 and len(set(PAPER_CASES)) == 24
    assert (20, 8) in PAPER_CASES and (6, 12) not in PAPER_CASES
    code = "from coin_app.sim.arena.generator import *; from coin_app.sim.arena.config import make_arena_config as m; import numpy as np\n"
    code += "print(np.round(generate(heldout_rng(4, 4, 3), m(), 4, 4).obstacles, 9).tolist())"
    other = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert other == str(np.round(generate(heldout_rng(4, 4, 3), CFG, 4, 4).obstacles, 9).tolist())  # same in a fresh process
    test = {generate(heldout_rng(4, 4, k), CFG, 4, 4).starts.tobytes() for k in range(30)}
    train = {generate(training_rng(k), CFG, 4, 4).starts.tobytes() for k in range(30)}
    assert not test & train


# ---------------------------------------------------------------- env and heuristic


def test_env_reset_is_seeded_and_counts_vary_within_the_ranges():
    env = ArenaEnv(make_arena_config(num_vehicles=1, max_vehicles=8, num_obstacles=0, max_obstacles=8))
    assert len(env.possible_agents) == 8
    sizes = set()
    for seed in range(30):
        obs, _ = env.reset(seed)
        sizes.add((len(obs), len(env.sim.layout.obstacles)))
        again, _ = ArenaEnv(env.config).reset(seed)
        assert all(np.array_equal(obs[a], again[a]) for a in obs)
    assert len({n for n, _ in sizes}) > 4 and len({m for _, m in sizes}) > 4 and max(sizes)[0] <= 8


def test_heuristic_parks_a_lone_vehicle_every_time():
    results = []
    for seed in range(10):
        env = ArenaEnv(make_arena_config(num_vehicles=1, num_obstacles=0))
        obs, _ = env.reset(seed)
        while env.agents:
            actions = heuristic_actions(np.stack([obs[a] for a in env.agents]))
            obs, _, _, _, _ = env.step(dict(zip(env.agents, actions)))
        results.append(arena_metrics(env.sim))
    assert all(r["success_to_goal_rate"] == 1.0 for r in results)
    assert all(r["steps"] < 400 for r in results)


def test_arena_passes_pettingzoo_and_rllib_env_checks():
    from pettingzoo.test import parallel_api_test
    from ray.rllib.utils.pre_checks.env import check_multiagent_environments

    from coin_app.adapters.pettingzoo_env import CoinParallelEnv
    from coin_app.adapters.rllib_env import CoinMultiAgentEnv

    parallel_api_test(CoinParallelEnv("arena", num_vehicles=3, num_obstacles=2, max_steps=30), num_cycles=40)
    env = CoinMultiAgentEnv({"scenario": "arena", "num_vehicles": 3, "num_obstacles": 2, "max_steps": 30})
    check_multiagent_environments(env)
    obs, _ = env.reset(seed=1)
    done = False
    while not done:
        obs, _, term, trunc, _ = env.step({a: env.action_spaces[a].sample() for a in env.agents})
        done = term["__all__"]
    assert trunc["__all__"] and env.agents == []  # every vehicle hit the 30-step limit
    with pytest.raises(ValueError, match="not available for the arena"):
        CoinParallelEnv("arena", render_mode="rgb_array")


def test_hovering_near_the_target_earns_less_than_parking_at_any_step():
    """The time penalty must outgrow the near-target shaping (the paper's reason for Eq. 6).

    A vehicle 2 m behind its target, aligned and still, collects the distance reward (inside d_c
    it is positive even without progress) and the angle reward every step; compare hovering to
    the step limit (then r_trunc) with hovering k - 1 steps and parking at step k, for every k.
    """
    limit, d = CFG.max_steps, 2.0
    hover = distance_reward(RC, np.array([d]), np.array([d]))[0]
    hover += angle_reward(RC, np.array([d]), np.array([0.0]), np.array([hover]))[0]
    steps = np.arange(1, limit + 1)
    per_step = hover + np.array([time_reward(RC, t, CFG.dt) for t in steps])
    hover_to_limit = per_step[:-1].sum() + RC.truncation_reward
    park_at = np.concatenate([[0.0], np.cumsum(per_step[:-1])]) + RC.success_reward  # hover k - 1 steps, park at k
    assert hover > 0.5 and park_at.min() > hover_to_limit + 50.0
    # the same check catches a time penalty too weak for the success reward
    weak = RewardConfig(time_scale=0.01, success_reward=50.0)
    per_weak = hover + np.array([time_reward(weak, t, CFG.dt) for t in steps])
    assert (np.concatenate([[0.0], np.cumsum(per_weak[:-1])]) + weak.success_reward).min() < per_weak[:-1].sum() + weak.truncation_reward


def _observation(entity_xy, entity_radius=1.0, speed=2.0, target_xy=(20.0, 0.0)) -> np.ndarray:
    """One vehicle at the origin heading +x, its target ahead and aligned, one obstacle at ``entity_xy`` (m; None: none)."""
    obs = np.zeros((1, 13))
    obs[0, 0:2] = np.array(target_xy) / 25.0
    obs[0, 3] = 1.0  # target heading = the vehicle's
    obs[0, 4] = speed / 10.0
    obs[0, 9] = 1.0
    if entity_xy is not None:
        obs[0, 6:8] = np.array(entity_xy) / 25.0
        obs[0, 10] = entity_radius / 3.0
        obs[0, 12] = 1.0
    return obs


def test_avoiding_driver_swerves_only_from_an_entity_ahead_and_short_of_the_target():
    plain = heuristic_actions(_observation(None))
    np.testing.assert_allclose(avoiding_actions(_observation(None)), plain)  # nothing near: the plain driver
    for elsewhere in ((-5.0, 0.5), (5.0, 6.0), (25.0, 0.5), (30.0, 0.0)):  # behind, off to the side, beyond the target
        obs = _observation(elsewhere)
        np.testing.assert_allclose(avoiding_actions(obs), heuristic_actions(obs))
    # 5 m ahead, 0.5 m to the left: clearance 5.02 - 1 - 1.35 = 2.7 m, inside the look-ahead 4 + 2 m/s: full lock right
    left = avoiding_actions(_observation((5.0, 0.5)))
    assert left[0, 0] == -1.0 and left[0, 1] <= heuristic_actions(_observation((5.0, 0.5)))[0, 1]
    assert avoiding_actions(_observation((5.0, -0.5)))[0, 0] == 1.0  # on the right: full lock left
    # 2.5 m ahead: clearance 0.15 m, under 0.5 m: full brake as well
    assert avoiding_actions(_observation((2.5, 0.0)))[0, 1] == -1.0
    # crawling: at 3 m/s the pedal asks for 2.5 m/s, (2.5 - 0.99 * 3) / 0.1 = -4.7, clipped to -1
    assert avoiding_actions(_observation((6.0, 0.3), speed=3.0))[0, 1] == -1.0


def test_avoiding_driver_collides_less_than_the_plain_one_among_obstacles():
    plain = summarize(evaluate_suite("heuristic", [(1, 8)], 10, workers=1, log=lambda s: None))
    avoiding = summarize(evaluate_suite("avoiding", [(1, 8)], 10, workers=1, log=lambda s: None))
    assert avoiding.collision_rate[0] < plain.collision_rate[0]
    assert avoiding.success_to_goal_rate[0] > plain.success_to_goal_rate[0]


def test_rollout_clearance_of_a_vehicle_at_rest_and_an_oncoming_vehicle_by_hand():
    # at rest, steering 0, pedal 0: the vehicle stays at the origin; the entity (bounding radius 1.2 m) starts 8 m ahead
    # heading back at 3 m/s (relative heading pi: sin 0, cos -1), so after t steps its centre is at 8 - 0.3 t m
    obs = _observation((8.0, 0.0), entity_radius=1.2, speed=0.0)
    obs[0, 8:10] = (0.0, -1.0)
    obs[0, 11] = 0.3
    got = rollout_clearance(obs, np.zeros((1, 1, 2)), horizon=10)
    # the front circle at +0.625 m is the closer one: 8 - 3 - 0.625 - 1.2 - r at t = 10
    assert got[0, 0] == pytest.approx(8.0 - 3.0 - FOOTPRINT_OFFSET - 1.2 - FOOTPRINT_RADIUS)
    assert rollout_clearance(_observation(None), np.zeros((1, 3, 2)), horizon=5).tolist() == [[math.inf] * 3]


def test_planning_driver_keeps_the_plain_action_unless_its_rollout_comes_too_close():
    for elsewhere in (None, (-5.0, 0.5), (5.0, 8.0)):  # nothing near, behind, far to the side
        obs = _observation(elsewhere)
        np.testing.assert_array_equal(planning_actions(obs), heuristic_actions(obs))
    # a 1 m obstacle 5 m straight ahead at 3 m/s: the plain driver goes straight into it; the filter's choice, driven by
    # the simulator for the filter's horizon against the real obstacle, never touches it
    obs = _observation((5.0, 0.0), speed=3.0)
    plain, planned = heuristic_actions(obs), planning_actions(obs, horizon=15, margin=0.3)
    assert abs(plain[0, 0]) < 0.05 and not np.allclose(planned, plain)
    cfg = make_arena_config(num_vehicles=1, num_obstacles=1)

    def contact(action):
        sim = ArenaSimulator(cfg)
        layout = Layout(starts=np.array([[0.0, 0.0, 0.0]]), targets=np.array([[20.0, 0.0, 0.0]]), obstacles=np.array([[5.0, 0.0, 1.0]]))
        sim.reset(layout)
        sim.speed[:] = 3.0
        hit = False
        for _ in range(15):
            sim.step(action)
            hit |= bool(sim.contact.any())
        return hit

    assert contact(plain) and not contact(planned)


def test_planning_driver_beats_the_avoiding_one_among_vehicles():
    avoiding = summarize(evaluate_suite("avoiding", [(6, 0)], 10, workers=1, log=lambda s: None))
    planning = summarize(evaluate_suite("planning", [(6, 0)], 10, workers=1, log=lambda s: None))
    assert planning.success_to_goal_rate[0] > avoiding.success_to_goal_rate[0]
    assert planning.collision_rate[0] < avoiding.collision_rate[0]


@pytest.mark.parametrize("folder", ["pair", "pair_planning", "pair_features"])
def test_the_committed_pair_loads_without_ray_and_parks_lone_vehicles(folder):
    # a fresh interpreter: loading the pair file and its two .npz policies must not import torch or Ray
    # (pair_features ships inside the package as the shipped policy nav_ppo-arena, loaded by name)
    arena = Path(__file__).resolve().parents[1] / "docs" / "arena"
    pair = "nav_ppo-arena" if folder == "pair_features" else str(arena / folder / "nav.json")
    code = (
        f"import sys; from coin_app.inference import load_policy; load_policy({pair!r}); "
        "print(sorted(m for m in ('ray', 'torch') if m in sys.modules))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]"
    policy = load_policy(pair)
    options = observation_options(policy)  # the observation it was trained on, from its metadata
    assert options == ({"observed_entities": 6, "candidate_features": True} if folder == "pair_features" else PAPER)
    env = ArenaEnv(make_arena_config(num_vehicles=1, num_obstacles=0, **options))
    parked = 0
    for k in range(10):  # the suite's first 10 held-out 1x0 scenarios (docs/arena: 49, 50 and 50 of 50 park)
        obs, _ = env.reset(options={"layout": generate(heldout_rng(1, 0, k), env.config, 1, 0)})
        while env.agents:
            obs, _, _, _, _ = env.step(dict(zip(env.agents, policy(np.stack([obs[a] for a in env.agents])))))
        m = arena_metrics(env.sim)
        parked += m["success_to_goal_rate"] == 1.0
        assert m["collisions"] == 0
    assert parked >= 8


# ---------------------------------------------------------------- several observed entities (our option)


def test_observing_several_entities_orders_them_by_clearance_and_pads_absent_ones():
    starts = [[0, 0, math.pi / 2], [-5, 0, 0], [0, -9, 0]]
    lay = layout(starts, [[3, 4, 0.5], [-20, 0, 0], [20, -9, 0]], [[0, 10, 1]])
    one, _ = ArenaEnv(CFG).reset(options={"layout": lay})
    env = ArenaEnv(make_arena_config(observed_entities=4))
    assert env.observation_space.shape == (6 + 7 * 4,)
    obs, _ = env.reset(options={"layout": lay})
    o = obs["agent0"]
    np.testing.assert_array_equal(o[:13], one["agent0"])  # the first block is the paper's observation, bit for bit
    # clearances from the ego (origin, heading +y): vehicle at (-5, 0) 5 - 2 R_VEH; obstacle (0, 10) r 1: 10 - 1 - R_VEH;
    # vehicle at (0, -9): 9 - 2 R_VEH. The vehicle at (0, -9) lies straight behind: x = -9 in the ego frame
    assert 5 - 2 * R_VEH < 9 - 2 * R_VEH < 10 - 1 - R_VEH
    np.testing.assert_allclose(o[13:20], [-9 / 25, 0.0, math.sin(-math.pi / 2), math.cos(-math.pi / 2), R_VEH / 3, 0.0, 1.0], atol=1e-6)
    np.testing.assert_allclose(o[20:27], [10 / 25, 0.0, 0.0, 1.0, 1 / 3, 0.0, 1.0], atol=1e-6)
    np.testing.assert_array_equal(o[27:34], [0, 0, 0, 1, 0, 0, 0])  # only three other entities: the fourth block is empty
    for bad in (0, 17, True, 2.0):
        with pytest.raises(ValueError, match="observed_entities"):
            make_arena_config(observed_entities=bad)


def _several(rng: np.random.Generator, n: int, k: int) -> np.ndarray:
    """Random observations (n, 6 + 7 k): each entity block present or empty, near or far, moving or not."""
    obs = np.zeros((n, 6 + 7 * k))
    obs[:, 0:2] = rng.uniform(-0.8, 0.8, (n, 2))
    head = rng.uniform(-math.pi, math.pi, n)
    obs[:, 2], obs[:, 3], obs[:, 4] = np.sin(head), np.cos(head), rng.uniform(-0.2, 0.6, n)
    for b in range(k):
        block = obs[:, 6 + 7 * b : 13 + 7 * b]
        h = rng.uniform(-math.pi, math.pi, n)
        block[:, 0:2] = rng.uniform(-1, 1, (n, 2)) * rng.choice([0.15, 1.0], (n, 1))
        block[:, 2], block[:, 3] = np.sin(h), np.cos(h)
        block[:, 4], block[:, 5], block[:, 6] = rng.uniform(0.2, 1.0, n), rng.uniform(0, 0.5, n), rng.random(n) < 0.8
    return obs


def test_planning_driver_checks_every_observed_entity_like_rolling_out_all_of_them():
    # brute force: every entity block rolled out for every candidate, the least clearance kept, the same choice rule
    rng = np.random.default_rng(3)
    for k in (1, 3):
        obs = _several(rng, 300, k)
        nominal = heuristic_actions(obs)
        cand = np.concatenate([nominal[:, None, :], np.broadcast_to(CANDIDATES, (300, *CANDIDATES.shape))], axis=1)
        views = [np.concatenate([obs[:, :6], obs[:, 6 + 7 * b : 13 + 7 * b]], 1) for b in range(k)]
        least = np.min([rollout_clearance(v, cand, 25) for v in views], axis=0)
        cost = np.where(least >= 0.6, ((cand - nominal[:, None]) ** 2).sum(-1), 1e6 - least)
        np.testing.assert_array_equal(planning_actions(obs), cand[np.arange(300), np.argmin(cost, 1)])


def test_pairs_that_cannot_come_near_keep_the_margin_under_every_action():
    rng = np.random.default_rng(4)
    obs = _several(rng, 2000, 1)
    obs[:, 12] = 1.0
    far = ~may_come_near(obs, 25, 0.6)
    assert 100 < far.sum() < 1900  # both kinds occur
    every = np.broadcast_to(CANDIDATES, (int(far.sum()), *CANDIDATES.shape))
    assert rollout_clearance(obs[far], every, 25).min() >= 0.6


def test_several_entities_see_more_and_the_suite_observes_what_a_policy_was_trained_on():
    # with every vehicle in view the planning driver avoids the collisions the closest-only one meets (15 vehicles, training seeds)
    cfg1, cfg6 = make_arena_config(), make_arena_config(observed_entities=6)
    hits = {}
    for cfg in (cfg1, cfg6):
        env, hit = ArenaEnv(cfg), 0
        for k in range(4):
            obs, _ = env.reset(options={"layout": generate(training_rng(900 + k), cfg, 15, 4)})
            while env.agents:
                obs, *_ = env.step(dict(zip(env.agents, planning_actions(np.stack([obs[a] for a in env.agents])))))
            hit += int(env.sim.collided.sum())
        hits[cfg.observed_entities] = hit
    assert hits[6] < hits[1] / 2
    # the suite's config follows the policy: a learned one's metadata, or the count given for a scripted driver
    learned = WithMeta(heuristic_actions, {"scenario": "arena", "env_config": {"observed_entities": 6}})
    assert policy_config(learned, 400, "arena").obs_dim == 6 + 7 * 6
    assert policy_config(heuristic_actions, 400, "arena", observed=3).observed_entities == 3
    assert policy_config(heuristic_actions, 400, "arena").observed_entities == 1
    with pytest.raises(ValueError, match="contradict"):
        policy_config(learned, 400, "arena", observed=3)
    paper = WithMeta(heuristic_actions, {"scenario": "arena", "env_config": {}})
    with pytest.raises(ValueError, match="observes 6 entities"):
        SwitchingPolicy(learned, paper, 7.5)
    assert SwitchingPolicy(learned, learned, 7.5).meta["env_config"] == {"observed_entities": 6}
    assert observed_entities(SwitchingPolicy(paper, paper, 7.5)) == 1


# ---------------------------------------------------------------- candidate features (our option, not the paper's)


def test_an_observation_width_names_its_layout_and_other_widths_are_refused():
    for k in range(1, 17):
        assert layout_of(6 + 7 * k) == (k, False)
        assert layout_of(6 + 7 * k + 44) == (k, True)
    for width in (0, 6, 12, 14, 6 + 7 + 43, 6 + 7 + 45):
        with pytest.raises(ValueError, match=f"got {width}"):
            layout_of(width)
    assert make_arena_config(observed_entities=3, candidate_features=True).obs_dim == 6 + 21 + 44
    with pytest.raises(ValueError, match="candidate_features=1; allowed: True or False"):
        make_arena_config(candidate_features=1)


def test_candidate_features_are_the_capped_clearances_of_rolling_out_every_candidate_against_every_entity():
    plain_cfg = make_arena_config(observed_entities=3)
    cfg = make_arena_config(observed_entities=3, candidate_features=True)
    envs = {c.candidate_features: ArenaEnv(c) for c in (plain_cfg, cfg)}
    layout = generate(training_rng(31), cfg, 8, 4)
    obs = {flag: env.reset(options={"layout": layout})[0] for flag, env in envs.items()}
    seen = 0
    for _ in range(30):
        rows = np.stack([obs[True][a] for a in envs[True].agents])
        base = np.stack([obs[False][a] for a in envs[False].agents])
        assert rows.shape[1] == 6 + 21 + 44
        np.testing.assert_array_equal(rows[:, :27], base)  # the paper's part is untouched
        # brute force: every candidate (the plain driver's action first) against every present entity, no pruning
        cand = np.concatenate([heuristic_actions(base)[:, None], np.broadcast_to(CANDIDATES, (len(base), 21, 2))], 1)
        views = [np.concatenate([base[:, :6], base[:, 6 + 7 * b : 13 + 7 * b]], 1) for b in range(3)]
        least = np.min([rollout_clearance(v, cand, 25) for v in views], axis=0)
        np.testing.assert_allclose(rows[:, 27:49], np.minimum(least, CLEARANCE_CAP) / CLEARANCE_CAP, atol=1e-6)
        np.testing.assert_array_equal(rows[:, 49:], least >= FILTER_MARGIN)
        seen += int((least < FILTER_MARGIN).sum())
        # the drivers read past the features: the same actions with and without them
        actions = planning_actions(rows)
        np.testing.assert_array_equal(actions, planning_actions(base))
        for flag, env in envs.items():
            obs[flag] = env.step(dict(zip(env.agents, actions)))[0]
    assert seen > 0  # some candidates were inadmissible
    # the features' time is recorded (the suite counts it as the policy's), and is 0 without them
    assert envs[True].sim.feature_time > 0.0 and envs[False].sim.feature_time == 0.0


def test_the_suite_and_the_switching_policy_carry_the_candidate_features():
    featured = WithMeta(heuristic_actions, {"scenario": "arena", "env_config": {"observed_entities": 6, "candidate_features": True}})
    plain = WithMeta(heuristic_actions, {"scenario": "arena", "env_config": {"observed_entities": 6}})
    assert policy_config(featured, 400, "arena").obs_dim == 6 + 42 + 44
    assert policy_config(plain, 400, "arena").obs_dim == 6 + 42
    pair = SwitchingPolicy(featured, featured, 7.5)
    assert pair.meta["env_config"] == {"observed_entities": 6, "candidate_features": True}
    assert observation_options(pair) == {"observed_entities": 6, "candidate_features": True}
    with pytest.raises(ValueError, match="6 entities and the candidate features, the short-range one 6 entities;"):
        SwitchingPolicy(featured, plain, 7.5)
