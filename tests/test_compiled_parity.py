"""The compiled kernels (issue 59) against the numpy step they replaced (tests/numpy_reference.py), to float64 round-off."""

import numpy as np
import pytest
from numpy_reference import NumpyRaycastVehicles, NumpyRoadMap, NumpySimulator
from numpy_reference import boxes_overlap as numpy_boxes_overlap
from numpy_reference import candidate_clearance as numpy_candidate_clearance
from numpy_reference import ego_features as numpy_ego_features
from numpy_reference import footprint_samples as numpy_footprint_samples
from numpy_reference import friction_bicycle_step as numpy_friction_bicycle_step
from numpy_reference import heuristic_actions as numpy_heuristic_actions
from numpy_reference import lidar_scan as numpy_lidar_scan
from numpy_reference import local_state as numpy_local_state
from numpy_reference import rollout_clearance as numpy_rollout_clearance
from numpy_reference import turn_matrices as numpy_turn_matrices

from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.generator import generate, training_rng
from coin_app.sim.arena.heuristic import CANDIDATES, candidate_clearance, heuristic_actions, planning_actions, rollout_clearance
from coin_app.sim.collision import boxes_overlap, footprint_samples
from coin_app.sim.config import make_config
from coin_app.sim.dynamics import friction_bicycle_step
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.road_map import load_map
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.sensors import ego_features, lidar_scan, local_state
from coin_app.sim.simulator import DrivingSimulator
from coin_app.sim.vehicle import RaycastVehicles, chassis_basis, turn_matrices

STATE = ("pos", "rot", "vel", "ang")


def _ulps(got: np.ndarray, want: np.ndarray) -> None:
    """Equal to a few ulp: numpy's arctan2, hypot and exp take SIMD paths on some CPUs (AVX-512 here) that round the
    last bit otherwise than the C library the kernels call; pure arithmetic is checked to the bit elsewhere."""
    np.testing.assert_allclose(got, want, rtol=1e-13, atol=1e-13)


def test_turn_matrices_equal_the_numpy_ones_to_the_bit():
    w = np.random.default_rng(0).normal(0.0, 3.0, (200, 3))
    w[0] = 0.0
    np.testing.assert_array_equal(turn_matrices(w, 0.02), numpy_turn_matrices(w, 0.02))


def test_car_kernel_steps_every_state_as_the_numpy_step_did():
    """Cars at rest, settling, driving, sliding at full lock, tipped over and airborne: each env step from the same state agrees
    to round-off (a few ulp of the state's scale), over 150 steps of random actions (the states synchronised after each)."""
    rng = np.random.default_rng(1)
    n = 24
    new, old = RaycastVehicles(n), NumpyRaycastVehicles(n)
    new.place(np.arange(n), rng.uniform(-50, 50, (n, 2)), rng.uniform(-3, 3, n), rng.uniform(0, 25, n), settled=True)
    new.place(np.arange(4), rng.uniform(-50, 50, (4, 2)), rng.uniform(-3, 3, 4))  # spawned: falling onto the suspension
    new.rot[4] = chassis_basis(np.array([0.3]), np.array([2.0]))[0]  # tipped over
    new.pos[5, 2] = 2.0  # in the air
    slots = rng.permutation(n)[: n - 3]  # a subset, in no order
    skids = 0
    for _ in range(150):
        for name in STATE:
            getattr(old, name)[:] = getattr(new, name)
        action = rng.uniform(-1.0, 1.0, (len(slots), 2))
        xy, heading = new.step(slots, action)
        xy_old, heading_old = old.step(slots, action)
        np.testing.assert_allclose(xy, xy_old, rtol=0, atol=1e-12)
        np.testing.assert_allclose(heading, heading_old, rtol=0, atol=1e-13)
        for name in STATE:
            np.testing.assert_allclose(getattr(new, name), getattr(old, name), rtol=1e-13, atol=1e-13)
        lateral = np.abs(np.einsum("nij,nj->ni", new.rot[slots], new.vel[slots])[:, 0])
        skids += int((lateral > 1.0).sum())
    untouched = np.setdiff1d(np.arange(n), slots)
    assert skids > 100  # the friction circle was reached (sliding sideways at over 1 m/s)
    assert np.array_equal(new.vel[untouched], old.vel[untouched])


def test_lane_queries_equal_the_numpy_ones():
    rng = np.random.default_rng(2)
    for name in DRIVING_SCENARIOS:
        m, ref = load_map(name), NumpyRoadMap(name)
        lane = rng.integers(0, m.num_lanes, 500)
        pos = rng.uniform(m.bounds[:2], m.bounds[2:], (500, 2))
        s = rng.uniform(-5, 60, 500)
        for got, want in zip(m.local_coordinates(lane, pos), ref.local_coordinates(lane, pos)):
            _ulps(got, want)
        _ulps(m.heading_at(lane, s), ref.heading_at(lane, s))
        _ulps(m.position(lane, s, pos[:, 0] / 50), ref.position(lane, s, pos[:, 0] / 50))
        _ulps(m.right_normal(lane, pos), ref.right_normal(lane, pos))
        contains = m.hull_contains(pos)
        np.testing.assert_array_equal(contains, ref.hull_contains(pos))
        assert contains.any() and not contains.all()


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_ego_features_equal_the_numpy_ones(scenario):
    """The 19 ego and navigation numbers and both checkpoints of every vehicle along heuristic traffic, to round-off, and
    the local states (float32) to the bit."""
    sim = DrivingSimulator(make_config(scenario))
    sim.reset(3)
    driver, ref_map = HeuristicDriver(sim), NumpyRoadMap(scenario)
    m = sim.map
    for _ in range(40):
        sim.step(driver.act_all())
        i = np.nonzero(sim.status == 1)[0]
        ref_road = m.route_roads[sim.route[i], sim.ref_idx[i]]
        next_road = m.route_roads[sim.route[i], np.minimum(sim.ref_idx[i] + 1, m.route_nroads[sim.route[i]] - 1)]
        args = (
            sim.pos[i],
            sim.heading[i],
            sim.heading_prev[i],
            sim.speed[i],
            sim.action[i],
            sim.lane[i],
            ref_road,
            next_road,
            80.0,
            50.0,
            0.1,
        )
        for got, want in zip(ego_features(m, *args), numpy_ego_features(ref_map, *args)):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-13)
        _, ck1, ck2 = ego_features(m, *args)
        state = (sim.pos[i], sim.vel[i], sim.heading[i], ck1, ck2, m.centre, m.scale, 22.0, 50.0)
        np.testing.assert_array_equal(local_state(*state), numpy_local_state(*state))


def test_boxes_footprints_and_lidar_equal_the_numpy_ones():
    rng = np.random.default_rng(3)
    n = 4000
    c1, c2 = rng.uniform(-4, 4, (n, 2)), rng.uniform(-4, 4, (n, 2))
    h1, h2 = rng.uniform(-4, 4, n), rng.uniform(-4, 4, n)
    half1, half2 = rng.uniform(0.2, 3, (n, 2)), rng.uniform(0.2, 3, (n, 2))
    hit = boxes_overlap(c1, h1, half1, c2, h2, half2)
    np.testing.assert_array_equal(hit, numpy_boxes_overlap(c1, h1, half1, c2, h2, half2))
    assert 0.2 < hit.mean() < 0.8
    np.testing.assert_array_equal(footprint_samples(c1, h1, 2.3, 0.9), numpy_footprint_samples(c1, h1, 2.3, 0.9))
    pos, hd = rng.uniform(-30, 30, (40, 2)), rng.uniform(-4, 4, 40)
    pos[1] = pos[0] + 0.5  # an observer inside another's box
    i, j = np.nonzero(~np.eye(40, dtype=bool))
    scan = lidar_scan(pos, hd, i, pos[j], hd[j], (2.3, 0.9), 72, 50.0)
    np.testing.assert_array_equal(scan, numpy_lidar_scan(pos, hd, i, pos[j], hd[j], (2.3, 0.9), 72, 50.0))
    assert (scan < 50.0).mean() > 0.1 and (scan == 0.0).any()


def _episode(scenario: str, num_envs: int, steps: int, seed: int) -> dict[str, int]:
    """Step the compiled and the numpy simulators side by side under heuristic traffic with noise (and every fifth step
    uniform random actions); assert equal events and round-off-equal numbers at every step; count the events."""
    cfg = make_config(scenario)
    new, old = DrivingSimulator(cfg, num_envs), NumpySimulator(cfg, num_envs)
    new.reset(seed)
    old.reset(seed)
    driver = HeuristicDriver(new)
    rng = np.random.default_rng(seed)
    counts = dict.fromkeys(("arrive_dest", "crash_vehicle", "out_of_road", "respawned", "resets"), 0)
    for k in range(steps):
        if k % 5 == 4:
            actions = rng.uniform(-1.0, 1.0, (new.num_slots, 2))
        else:
            actions = np.clip(driver.act_all() + rng.normal(0.0, 0.15, (new.num_slots, 2)), -1.0, 1.0)
        got, want = new.step(actions), old.step(actions)
        for f in ("acted", "spawned", "agent_num", "arrive_dest", "crash_vehicle", "out_of_road", "max_step", "terminated", "truncated"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f"{f} at step {k}")
        for f in ("episode_length", "episode_over", "env_step"):
            np.testing.assert_array_equal(getattr(got, f), getattr(want, f), err_msg=f"{f} at step {k}")
        # observations and states are float32: equal up to a float32 rounding of a round-off-equal float64
        np.testing.assert_allclose(got.obs, want.obs, rtol=0, atol=3e-7, err_msg=f"obs at step {k}")
        np.testing.assert_allclose(got.state, want.state, rtol=0, atol=3e-7, err_msg=f"state at step {k}")
        np.testing.assert_allclose(got.reward, want.reward, rtol=1e-12, atol=1e-12, err_msg=f"reward at step {k}")
        for f in ("status", "lane", "ref_idx", "route"):
            np.testing.assert_array_equal(getattr(new, f), getattr(old, f), err_msg=f"{f} at step {k}")
        for f in ("pos", "heading", "speed", "vel"):
            np.testing.assert_allclose(getattr(new, f), getattr(old, f), rtol=1e-12, atol=1e-12, err_msg=f"{f} at step {k}")
        for f in ("arrive_dest", "crash_vehicle", "out_of_road"):
            counts[f] += int(getattr(got, f).sum())
        counts["respawned"] += int(got.spawned.sum())
        # the car amplifies round-off where it slides (1e-15 grows to 1e-8 in ~150 steps on either path): continue both from
        # the numpy step's state, so that every step is compared from the same state and no event flips on round-off
        for f in ("pos", "prev_pos", "vel", "heading", "heading_prev", "speed", "yaw_rate"):
            getattr(new, f)[:] = getattr(old, f)
        for f in STATE:
            getattr(new.bodies, f)[:] = getattr(old.bodies, f)
        over = np.nonzero(got.episode_over)[0]
        if len(over):
            seeds = [seed + 1000 + k + e for e in over.tolist()]
            new.reset_envs(over, seeds)
            old.reset_envs(over, seeds)
            counts["resets"] += len(over)
    return counts


@pytest.mark.parametrize(
    ("scenario", "num_envs", "steps", "seed", "events"),
    [
        ("intersection", 1, 400, 7, ("arrive_dest", "crash_vehicle", "out_of_road", "respawned")),
        ("roundabout", 2, 300, 5, ("crash_vehicle", "respawned")),  # a batch of two envs (no arrival within 300 steps)
    ],
)
def test_a_long_seeded_episode_equals_the_numpy_step(scenario, num_envs, steps, seed, events):
    """Arrivals, exits, crashes and respawns happen, and every step's events, observations, rewards and states agree."""
    counts = _episode(scenario, num_envs, steps, seed=seed)
    assert all(counts[e] > 0 for e in events), counts


def test_arena_heuristic_actions_equal_the_numpy_ones():
    """Random observations: the line phase and both kinds of approach (sharp and gentle pursuit) all occur."""
    obs = np.random.default_rng(5).uniform(-1.0, 1.0, (3000, 13))
    actions = heuristic_actions(obs)
    _ulps(actions, numpy_heuristic_actions(obs))
    assert len(np.unique(np.abs(actions[:, 1]) == 1.0)) == 2 and (np.abs(actions[:, 0]) < 1.0).mean() > 0.05


def test_friction_bicycle_equals_the_numpy_step_to_the_bit():
    rng = np.random.default_rng(4)
    n = 1000
    args = rng.uniform(-20, 20, (n, 2)), rng.uniform(-4, 4, n), rng.uniform(-8, 8, n), rng.uniform(-1, 1, n), rng.uniform(-0.8, 0.8, n)
    for got, want in zip(friction_bicycle_step(*args, 0.1, 2.0, 0.99), numpy_friction_bicycle_step(*args, 0.1, 2.0, 0.99)):
        np.testing.assert_array_equal(got, want)


def test_arena_rollouts_and_candidate_clearances_equal_the_numpy_ones():
    """Observations of 20 vehicles among obstacles (the shipped pair's six entities), along a planning-driver episode."""
    cfg = make_arena_config(observed_entities=6, candidate_features=True)
    env = ArenaEnv(cfg)
    obs, _ = env.reset(options={"layout": generate(training_rng(7), cfg, 20, 8)})
    near = 0
    for _ in range(15):
        rows = np.stack([obs[a] for a in env.agents])
        views = [np.concatenate([rows[:, :6], rows[:, 6 + 7 * b : 13 + 7 * b]], 1) for b in range(6)]
        cand = np.concatenate([views[0][:, None, :2] * 0.0 + 0.3, np.broadcast_to(CANDIDATES, (len(rows), 21, 2))], 1)
        np.testing.assert_array_equal(heuristic_actions(rows), numpy_heuristic_actions(rows))
        for v in views:
            np.testing.assert_array_equal(rollout_clearance(v, cand, 25), numpy_rollout_clearance(v, cand, 25))
        for margin in (0.6, 3.0):
            got, want = candidate_clearance(rows, margin=margin), numpy_candidate_clearance(rows, margin=margin)
            np.testing.assert_array_equal(got[0], want[0])
            np.testing.assert_array_equal(got[1], want[1])
        near += int(np.isfinite(got[1]).sum())
        obs = env.step(dict(zip(env.agents, planning_actions(rows))))[0]
    assert near > 100  # many candidates came within the cap of an entity
