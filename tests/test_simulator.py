"""Simulator rules: observations, rewards, terminations, respawn, seeding and bad input."""

import math

import numpy as np
import pytest

from coin_app.sim.collision import boxes_overlap
from coin_app.sim.config import make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.sensors import line_detector
from coin_app.sim.simulator import ACTIVE, DYING, EMPTY, DrivingSimulator
from coin_app.sim.vehicle import RaycastVehicles

L = 4.515


def route_of(sim, spawn_lane_key, destination):
    m = sim.map
    lane = m.lane_index[spawn_lane_key]
    return next(i for i in m.routes_by_spawn_lane[lane] if m.routes[i].destination == destination)


def lone_vehicle(scenario="intersection", **kw):
    sim = DrivingSimulator(make_config(scenario, num_agents=2, allow_respawn=False, **kw))
    sim.reset(0)
    sim.remove(1)
    return sim


def step_one(sim, a0=0.0, a1=0.0):
    act = np.zeros((sim.num_slots, 2))
    act[0] = a0, a1
    return sim.step(act)


def test_ego_features_of_a_placed_vehicle():
    sim = lone_vehicle()
    route = route_of(sim, (">>", ">>>", 1), "1X1_1_")  # straight through, right lane y = 0
    sim.place(0, (30.0, 0.0), 0.0, speed=10.0, route=route)
    obs, state = sim.observe(np.array([0]))
    o = obs[0].astype(float)
    assert obs.shape == (1, 91) and state.shape == (1, 10)
    # distances to the road edges from the left-most lane (y = 3.5): dl = 3.5 + 1.75
    assert o[0] == pytest.approx(5.25 / 18, abs=1e-6)
    assert o[1] == pytest.approx((7.0 - 5.25) / 18, abs=1e-6)
    assert o[2] == pytest.approx(0.5, abs=1e-6)  # aligned with the lane
    assert o[3] == pytest.approx((36.0 + 1) / 81, abs=1e-6)
    assert o[4:7] == pytest.approx([0.5, 0.5, 0.5], abs=1e-6)
    assert o[7] == pytest.approx(0.0, abs=1e-6)  # no yaw yet
    assert o[8] == pytest.approx(0.5, abs=1e-6)  # centred in its lane
    # checkpoint 1: end of the current road at its lateral middle (60, 1.75)
    d1 = np.array([30.0, 1.75])
    assert o[9:14] == pytest.approx([(d1[0] / 50 + 1) / 2, (d1[1] / 50 + 1) / 2, 0.0, 0.5, 0.5], abs=1e-6)
    # checkpoint 2: end of the straight junction road (90.5, 1.75), clipped to 50 m
    d2 = np.array([60.5, 1.75])
    d2 = d2 * 50 / np.linalg.norm(d2)
    assert o[14:19] == pytest.approx([(d2[0] / 50 + 1) / 2, (d2[1] / 50 + 1) / 2, 0.0, 0.5, 0.5], abs=1e-6)
    assert (o[19:] == 1.0).all()  # nobody around
    # local state: world-frame position / velocity / heading / checkpoint vectors
    m = sim.map
    s = state[0].astype(float)
    assert s[:2] == pytest.approx((np.array([30.0, 0.0]) - m.centre) / m.scale, abs=1e-6)
    assert s[2:4] == pytest.approx([10.0 / (80 / 3.6), 0.0], abs=1e-6)
    assert s[4:6] == pytest.approx([1.0, 0.0], abs=1e-6)
    assert s[6:8] == pytest.approx(d1 / 50, abs=1e-6)
    assert s[8:10] == pytest.approx(d2 / 50, abs=1e-6)


def test_turning_checkpoint_features():
    sim = lone_vehicle()
    route = route_of(sim, (">>", ">>>", 0), "1X2_1_")  # left turn: CCW arc R = 17, 90 deg
    sim.place(0, (30.0, 3.5), 0.0, route=route)
    o = sim.observe(np.array([0]))[0][0].astype(float)
    assert o[14 + 2] == pytest.approx(17.0 / (60 + 7.0), abs=1e-6)  # radius / (60 + n w)
    assert o[14 + 3] == pytest.approx(0.0)  # CCW = left turn
    assert o[14 + 4] == pytest.approx((90 / 135 + 1) / 2, abs=1e-6)


@pytest.mark.parametrize("model", ["raycast", "bicycle"])
def test_progress_reward_on_a_straight_lane(model):
    sim = lone_vehicle(dynamics={"model": model})
    sim.place(0, (30.0, 0.0), 0.0, speed=10.0, route=route_of(sim, (">>", ">>>", 1), "1X1_1_"))
    res = step_one(sim, 0.0, 0.0)
    if model == "bicycle":  # coasting: 10 m/s less 0.3636 m/s^2 for 0.1 s, then x += v dt
        v1 = 10.0 - 0.036363636363636
        assert sim.pos[0] == pytest.approx([30.0 + v1 * 0.1, 0.0], abs=1e-9)
    moved, v1 = sim.pos[0, 0] - 30.0, sim.speed[0]  # on this lane (heading east) progress is the x travelled
    assert 0.7 < moved < 1.01 and abs(sim.pos[0, 1]) < 1e-6 and 9.9 < v1 <= 10.0
    assert res.reward[0] == pytest.approx(moved + 0.1 * v1 * 3.6 / 80, abs=1e-9)
    assert not res.terminated[0] and res.global_reward[0] == pytest.approx(res.reward[0])
    # driving backwards along the lane is penalised by the same progress term
    sim.place(0, (30.0, 0.0), math.pi, speed=5.0)
    res = step_one(sim, 0.0, 0.0)
    moved, v1 = sim.pos[0, 0] - 30.0, sim.speed[0]
    assert moved < -0.35 and res.reward[0] == pytest.approx(moved + 0.1 * v1 * 3.6 / 80, abs=1e-9)


def test_arrival_reward_and_removal():
    sim = lone_vehicle()
    route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
    end_lane = sim.map.route_final_lane[route]
    end = sim.map.end[end_lane]  # (150.5, 0): right-most lane of the east exit
    sim.place(0, (end[0] - 5.5, end[1]), 0.0, speed=10.0, route=route)  # 0.8-1.0 m in a step: within 5 m of the end
    sim.ref_idx[0] = 2
    res = step_one(sim, 0.0, 0.5)
    assert res.arrive_dest[0] and res.reward[0] == 10.0 and res.terminated[0]
    assert sim.status[0] == EMPTY and res.episode_over[0]


def test_dying_vehicles_block_then_disappear_after_delay_done():
    sim = DrivingSimulator(make_config("intersection", num_agents=2, allow_respawn=False, delay_done=3))
    sim.reset(0)
    route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
    sim.place(0, (30.0, -0.9), 0.0, route=route)  # off road at once
    sim.place(1, (20.0, 0.0), 0.0, speed=0.0, route=route)
    statuses = []
    for _ in range(5):
        act = np.zeros((sim.num_slots, 2))
        act[1] = 0.0, -1.0  # braking at rest: stays put and alive
        sim.step(act)
        statuses.append(int(sim.status[0]))
    assert statuses == [DYING, DYING, DYING, EMPTY, EMPTY]


@pytest.mark.parametrize("delay", [1, 3, 25])
def test_a_wreck_is_an_obstacle_to_the_crash_test_for_delay_done_minus_one_steps(delay):
    """MetaDrive's agent manager counts a wreck down before the physics (``before_step``): one that became dying at
    step t is in the crash test at steps t+1 .. t+delay_done-1 only. A vehicle put onto the wreck before step t+k
    crashes exactly for k < delay_done."""
    got = []
    for k in range(1, delay + 2):
        sim = DrivingSimulator(make_config("intersection", num_agents=2, allow_respawn=False, delay_done=delay))
        sim.reset(0)
        route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
        sim.place(0, (30.0, -0.9), 0.0, route=route)  # off road at once: dying from step 1 (t = 1)
        sim.place(1, (-20.0, 0.0), 0.0, speed=0.0, route=route)  # far behind, at rest
        hold = np.zeros((sim.num_slots, 2))
        hold[1] = 0.0, -1.0
        assert sim.step(hold).out_of_road[0] and sim.status[0] == DYING
        for _ in range(k - 1):
            sim.step(hold)
        sim.place(1, (float(sim.pos[0, 0]) + 1.0, float(sim.pos[0, 1])), float(sim.heading[0]), route=route)
        got.append(bool(sim.step(hold).crash_vehicle[1]))  # step t + k
    assert got == [k < delay for k in range(1, delay + 2)]


def physics_poses(sim, slots, actions, env_steps):
    """(env_steps * 5 + 1, n, 3): the chassis pose (x, y, heading) of ``slots`` before the first physics step and after each,
    from a copy of their chassis stepped one physics step at a time (the crash and line tests' instants, independently)."""
    twin = RaycastVehicles(len(slots))
    for name in ("pos", "rot", "vel", "ang"):
        getattr(twin, name)[:] = getattr(sim.bodies, name)[slots]
    poses = []
    for m in range(env_steps * 5 + 1):
        if m:
            twin.step(np.arange(len(slots)), actions, substeps=1)
        poses.append(np.column_stack([twin.pos[:, :2], np.arctan2(twin.rot[:, 1, 1], twin.rot[:, 0, 1])]))
    return np.array(poses)


def first_step_at(instants_hit, shown=False):
    """The env step (1-based) whose instants include the first hit: the chassis before each of its 5 physics steps and after
    the last (poses 5 (t - 1) .. 5 t), or with ``shown`` only the pose MetaDrive shows after it (pose 5 t - 1)."""
    m = int(np.argmax(instants_hit))
    assert instants_hit[m], "no hit in the poses computed"
    return next(t for t in range(1, 100) if (5 * t - 1 >= m if shown else 5 * t >= m))


def test_a_car_crashes_in_the_step_where_its_chassis_first_touches_during_the_physics_steps():
    """MetaDrive's crash test is Bullet's: a contact callback in every physics step's collision detection and a contact test
    after the last one, on the chassis, which is one physics step ahead of the pose MetaDrive shows. A car coasting at 12 m/s
    onto one at rest crashes in the step whose chassis poses (before each physics step and after the last) first overlap,
    computed from a copy of both chassis stepped one physics step at a time; for some gaps that is a step earlier than the
    shown poses would say."""
    differs = 0
    for gap in np.arange(0.3, 2.4, 0.1):
        sim = DrivingSimulator(make_config("intersection", num_agents=2, allow_respawn=False))
        sim.reset(0)
        route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
        sim.place(0, (10.0, 0.0), 0.0, speed=12.0, route=route)
        sim.place(1, (10.0 + L + gap, 0.0), 0.0, speed=0.0, route=route)
        act = np.zeros((sim.num_slots, 2))
        act[1] = 0.0, -1.0
        poses = physics_poses(sim, np.array([0, 1]), act[:2], 4)
        hit = boxes_overlap(
            poses[:, 0, :2],
            poses[:, 0, 2],
            np.broadcast_to(sim.half, (len(poses), 2)),
            poses[:, 1, :2],
            poses[:, 1, 2],
            np.broadcast_to(sim.half, (len(poses), 2)),
        )
        want = first_step_at(hit)
        got = next(t for t in range(1, 5) if sim.step(act).crash_vehicle[0])
        assert got == want, gap
        differs += want != first_step_at(hit, shown=True)
    assert differs >= 2


def test_the_lidar_sees_the_others_chassis_from_the_shown_pose():
    """MetaDrive casts its lidar from the pose it shows against the other bodies where Bullet has them: one physics step
    ahead of their shown pose. A car at rest sees one driving away at 15 m/s ahead of it at the front of that one's chassis
    after the step's last physics step (from a copy stepped one physics step at a time), 0.3 m beyond its shown tail."""
    sim = DrivingSimulator(make_config("intersection", num_agents=2, allow_respawn=False))
    sim.reset(0)
    route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
    sim.place(0, (10.0, 0.0), 0.0, speed=0.0, route=route)
    sim.place(1, (25.0, 0.0), 0.0, speed=15.0, route=route)
    act = np.zeros((sim.num_slots, 2))
    act[0] = 0.0, -1.0
    chassis = physics_poses(sim, np.array([0, 1]), act[:2], 1)[5, 1]
    lidar = sim.step(act).obs[0, 19:].astype(float) * 50.0
    assert lidar[0] == pytest.approx(chassis[0] - L / 2 - sim.pos[0, 0], abs=1e-4)
    assert lidar[0] - (sim.pos[1, 0] - L / 2 - sim.pos[0, 0]) == pytest.approx(15.0 * 0.02, abs=0.01)


def test_a_car_leaves_the_road_in_the_step_after_which_its_chassis_touches_a_solid_line():
    """Line contacts are Bullet's contact test after the physics steps: the chassis after the last one, not the pose shown. A
    car drifting at 2 degrees toward the side line (its inner edge at y = -1.7125: the line at -1.75, 0.075 m wide) leaves
    the road in the first step after which the lowest corner of its footprint is at or below that edge."""
    differs = 0
    half = np.array([L / 2, 1.852 / 2])
    for y0 in np.arange(-0.6, -0.4, 0.005):
        sim = lone_vehicle()
        route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
        sim.place(0, (10.0, y0), math.radians(-2.0), speed=10.0, route=route)
        poses = physics_poses(sim, np.array([0]), np.zeros((1, 2)), 16)[:, 0]
        lowest = poses[:, 1] - half[0] * np.abs(np.sin(poses[:, 2])) - half[1] * np.cos(poses[:, 2])
        touch = lowest <= -1.7125
        touch[np.arange(len(touch)) % 5 != 0] = False  # tested only after the last physics step of a step
        want = first_step_at(touch)
        got = next(t for t in range(1, 13) if step_one(sim).out_of_road[0])
        assert got == want, y0
        shown = lowest <= -1.7125
        shown[np.arange(len(shown)) % 5 != 4] = False
        differs += want != first_step_at(shown, shown=True)
    assert differs >= 2


@pytest.mark.parametrize("per_step", [1, 2, 0])
def test_respawns_per_step_caps_how_many_vehicles_enter_in_one_step(per_step):
    """Six vehicles stand still and time out together at step 3 (vanishing at once, delay_done 0); their replacements
    enter ``respawns_per_step`` per step (MetaDrive: one), or all at once with 0 (the intersection has 8 entry places),
    and time out 3 steps after they entered."""
    sim = DrivingSimulator(
        make_config("intersection", num_agents=6, horizon=50, max_agent_steps=3, delay_done=0, respawns_per_step=per_step)
    )
    sim.reset(0)
    hold = np.zeros((sim.num_slots, 2))
    hold[:, 1] = -1.0
    counts = [int(sim.step(hold).spawned.sum()) for _ in range(6)]
    want = {1: [0, 0, 1, 1, 1, 1], 2: [0, 0, 2, 2, 2, 2], 0: [0, 0, 6, 0, 0, 6]}[per_step]
    assert counts == want


def test_respawns_per_step_is_checked():
    for bad in (-1, 1.5, True):
        with pytest.raises(ValueError, match="respawns_per_step"):
            make_config("intersection", respawns_per_step=bad)


def drive_off_policy(sim, t):
    act = np.zeros((sim.num_slots, 2))
    act[:, 0] = 1.0  # full left lock and throttle: off the road within a few seconds
    act[:, 1] = 1.0
    return act


def test_respawn_fresh_ids_cap_and_horizon():
    cfg = make_config("intersection", num_agents=6, horizon=60, delay_done=4)
    sim = DrivingSimulator(cfg)
    res = sim.reset(3)
    seen = {int(n) for n in res.agent_num[res.spawned]}
    assert seen == set(range(6))
    spawn_steps = []
    step = 0
    while not res.episode_over[0]:
        res = sim.step(drive_off_policy(sim, step))
        step += 1
        new = [int(n) for n in res.agent_num[res.spawned]]
        assert not (set(new) & seen), "an agent id was reused"
        if new:
            assert sorted(new) == list(range(max(seen) + 1, max(seen) + 1 + len(new)))  # consecutive numbers
            spawn_steps.append(int(res.env_step[0]))
        seen |= set(new)
        assert ((sim.status == ACTIVE) | (sim.status == DYING)).sum() <= cfg.num_agents
        assert len(new) <= 8
        assert step < 2000
    assert spawn_steps and max(spawn_steps) < cfg.horizon  # respawn stops at the horizon
    assert step >= cfg.horizon


def test_per_agent_time_limit_is_a_truncation():
    sim = DrivingSimulator(make_config("intersection", num_agents=2, horizon=1000, max_agent_steps=5, allow_respawn=False))
    sim.reset(0)
    for _ in range(5):
        act = np.zeros((sim.num_slots, 2))
        act[:, 1] = -1.0  # stand still
        res = sim.step(act)
    assert res.max_step[:2].all() and res.truncated[:2].all() and not res.terminated[:2].any()
    assert (res.episode_length[:2] == 5).all()


def random_actions(sim, rng):
    return rng.uniform(-1, 1, (sim.num_slots, 2)) * np.array([0.4, 1.0]) + np.array([0.0, 0.3])


def rollout(sim, seed, steps=120):
    res = sim.reset(seed)
    rng = np.random.default_rng(seed)
    out = [res.obs.copy()]
    for _ in range(steps):
        res = sim.step(random_actions(sim, rng))
        out.append(np.concatenate([res.obs.ravel(), res.reward, sim.pos.ravel()]))
    return out


def test_same_seed_same_episode_and_different_seed_differs():
    cfg = make_config("roundabout", num_agents=12)
    a = rollout(DrivingSimulator(cfg), 7)
    b = rollout(DrivingSimulator(cfg), 7)
    c = rollout(DrivingSimulator(cfg), 8)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[0], c[0])


def test_batched_env_reproduces_single_env():
    cfg = make_config("bottleneck", num_agents=8)
    batch = DrivingSimulator(cfg, num_envs=3)
    single = DrivingSimulator(cfg)
    rb = batch.reset([5, 6, 7])
    rs = single.reset(6)
    rows = batch.env_slots(1)
    for t in range(80):
        # actions depend only on the agent number and the step, so both runs act alike
        def acts(sim, t=t):
            n = sim.agent_num.astype(float)
            return np.stack([0.3 * np.sin(n + 0.1 * t), 0.5 + 0.5 * np.cos(2 * n + 0.05 * t)], 1)

        rb, rs = batch.step(acts(batch)), single.step(acts(single))
        assert np.array_equal(rb.obs[rows], rs.obs) and np.array_equal(rb.reward[rows], rs.reward)
        assert np.array_equal(rb.agent_num[rows][rb.acted[rows]], rs.agent_num[rs.acted])


def test_observations_are_in_unit_box_under_random_driving():
    for sc in DRIVING_SCENARIOS:
        sim = DrivingSimulator(make_config(sc))
        res = sim.reset(0)
        rng = np.random.default_rng(0)
        for _ in range(60):
            res = sim.step(random_actions(sim, rng))
            rows = res.obs[res.acted | res.spawned]
            assert rows.shape[1] == 91 and rows.min() >= 0.0 and rows.max() <= 1.0
            assert np.isfinite(res.state).all()


def test_nan_action_error_names_the_agent():
    env = DrivingEnv(scenario="intersection", num_agents=3)
    env.reset(seed=0)
    acts = {a: np.zeros(2) for a in env.agents}
    acts["agent1"] = np.array([np.nan, 0.0])
    with pytest.raises(ValueError, match=r"agent1.*finite"):
        env.step(acts)
    with pytest.raises(ValueError, match=r"agent99"):
        env.step({**{a: np.zeros(2) for a in env.agents}, "agent99": np.zeros(2)})
    with pytest.raises(ValueError, match=r"missing actions.*agent2"):
        env.step({"agent0": np.zeros(2), "agent1": np.zeros(2)})


def test_out_of_range_actions_are_clipped():
    a = lone_vehicle()
    b = lone_vehicle()
    for sim in (a, b):
        sim.place(0, (30.0, 0.0), 0.0, speed=5.0, route=0)
    step_one(a, 5.0, 7.0)
    step_one(b, 1.0, 1.0)
    assert np.array_equal(a.pos, b.pos) and np.array_equal(a.action, b.action)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        ({"horizon": 0}, "horizon"),
        ({"num_agents": 49}, "num_agents.*48"),
        ({"lidar_range": -1.0}, "lidar_range"),
        ({"crash_penalty": float("nan")}, "crash_penalty"),
        ({"colour": 3}, "unknown config key.*colour"),
        ({"dynamics": {"dt": 0.0}}, "dynamics.dt"),
        ({"dynamics": {"gravity": 9.8}}, "unknown dynamics key.*gravity"),
        ({"allow_respawn": "yes"}, "allow_respawn"),
        ({"backend": "carla"}, "backend.*native | metadrive"),
        ({"metadrive_assets": "maybe"}, "metadrive_assets.*skip | download"),
        ({"backend": "metadrive", "dynamics": {"dt": 0.04}}, "'dynamics' with backend 'metadrive'"),
        ({"dynamics": {"dt": 0.05}}, "'dynamics.dt': 0.05; allowed: a multiple of 0.02 s with model 'raycast'"),
        ({"dynamics": {"model": "unicycle"}}, "'dynamics.model': 'unicycle'; allowed: raycast | bicycle"),
        ({"backend": "metadrive", "vehicle_width": 2.0}, "'vehicle_width' with backend 'metadrive'.*1.852"),
        ({"backend": "metadrive", "horizon": 100, "max_agent_steps": 50}, "max_agent_steps.*equal to horizon \\(100\\)"),
        ({"backend": "metadrive", "obs_layout": "bottleneck96"}, "obs_layout.*'standard' on the MetaDrive intersection"),
    ],
)
def test_bad_config_is_refused_with_a_clear_message(kwargs, match):
    with pytest.raises(ValueError, match=match):
        make_config("intersection", **kwargs)


def test_metadrive_backend_config_follows_metadrive():
    # no MetaDrive needed: the config alone says what the MetaDrive backend will run
    cfg = make_config("bottleneck", backend="metadrive", horizon=200)
    assert cfg.obs_layout == "bottleneck96" and cfg.obs_dim == 96 and cfg.max_agent_steps == 200
    assert make_config("roundabout", backend="metadrive").obs_dim == 91
    with pytest.raises(ValueError, match="obs_layout.*'bottleneck96' on the MetaDrive bottleneck"):
        make_config("bottleneck", backend="metadrive", obs_layout="standard")
    with pytest.raises(ValueError, match="native simulator cannot run backend 'metadrive'.*make_driving_env"):
        DrivingSimulator(cfg)


def test_metadrive_config_mapping():
    from coin_app.backends.metadrive import metadrive_config

    cfg = make_config("bottleneck", backend="metadrive", crash_penalty=7.0, lidar_range=30.0, num_agents=12, delay_done=3)
    md = metadrive_config(cfg)
    assert md["crash_vehicle_penalty"] == md["crash_object_penalty"] == 7.0 and md["out_of_road_penalty"] == 5.0
    assert md["vehicle_config"]["lidar"] == {"num_lasers": 72, "distance": 30.0, "num_others": 0}
    assert md["vehicle_config"]["side_detector"]["distance"] == 50.0 and md["vehicle_config"]["lane_line_detector"]["distance"] == 20.0
    assert (md["num_agents"], md["delay_done"], md["horizon"], md["use_render"]) == (12, 3, 1000, False)


def test_unknown_scenario_and_preset():
    with pytest.raises(ValueError, match="unknown scenario 'highway'.*intersection"):
        make_config("highway")
    with pytest.raises(ValueError, match="unknown preset.*metadrive_compat"):
        make_config("intersection", preset="fast")


def test_unseeded_resets_continue_the_seeded_stream():
    def episodes(first_seed):
        sim = DrivingSimulator(make_config("intersection", num_agents=5))
        starts = [sim.reset(first_seed).obs.copy()]
        starts += [sim.reset(None).obs.copy() for _ in range(3)]
        return starts

    a, b = episodes(11), episodes(11)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[1], a[2])  # later episodes differ from each other


def test_own_arm_destinations_switch():
    m = DrivingSimulator(make_config("intersection")).map
    returns = {(m.lane_keys[r.spawn_lane][:2], r.destination) for r, ret in zip(m.routes, m.route_returns) if ret}
    # exactly one return route per spawn road of the intersection: the U-turn to its own exit
    assert returns == {
        ((">>", ">>>"), "->>"),
        (("-1X0_1_", "-1X0_0_"), "1X0_1_"),
        (("-1X1_1_", "-1X1_0_"), "1X1_1_"),
        (("-1X2_1_", "-1X2_0_"), "1X2_1_"),
    }
    for own, expect_returns in ((True, True), (False, False)):
        sim = DrivingSimulator(make_config("intersection", num_agents=48, own_arm_destinations=own))
        seen = set()
        for seed in range(5):
            sim.reset(seed)
            seen |= set(m.route_returns[sim.route[:48]].tolist())
        assert (True in seen) is expect_returns and False in seen


def test_the_step_observes_an_arrival_at_its_final_pose_and_the_next_step_does_not():
    """MetaDrive observes the acting vehicles before it retires the finished ones: the car behind one that arrives sees
    it, at its chassis after the step, in that step's observation, and an empty road in the next."""
    sim = DrivingSimulator(make_config("intersection", num_agents=2, allow_respawn=False))
    sim.reset(0)
    route = route_of(sim, (">>", ">>>", 1), "1X1_1_")
    end = sim.map.end[sim.map.route_final_lane[route]]  # (150.5, 0)
    sim.place(0, (end[0] - 5.5, end[1]), 0.0, speed=10.0, route=route)  # arrives in this step (test above)
    sim.ref_idx[0] = 2
    sim.place(1, (end[0] - 20.0, end[1]), 0.0, speed=0.0, route=route)
    sim.ref_idx[1] = 2
    act = np.zeros((sim.num_slots, 2))
    act[:2, 1] = 0.5, -1.0
    res = sim.step(act)
    assert res.arrive_dest[0] and sim.status[0] == EMPTY and sim.status[1] == ACTIVE
    chassis = sim._chassis_poses()[0]  # the retired car's body where the step left it
    front = res.obs[1, 19] * sim.cfg.lidar_range
    assert front == pytest.approx(chassis[0] - L / 2 - sim.pos[1, 0], abs=0.02)  # its tail, straight ahead
    act[0] = 0.0
    assert sim.step(act).obs[1, 19] == 1.0 and sim.step(act).obs[1, 19] == 1.0


def test_the_step_observes_before_the_respawn_and_a_new_agent_after_it():
    """Along a dense seeded episode: each acting vehicle's observation after a step is what the lidar sees with the
    vehicles retired by the step still there and the ones it spawned not yet (MetaDrive's order); a new agent's first
    observation sees the traffic after both. The order matters: some steps' observations differ from the traffic after
    the step."""
    sim = DrivingSimulator(make_config("intersection", num_agents=30, horizon=200))
    sim.reset(1)
    driver = HeuristicDriver(sim)
    mattered = checked = 0
    for _ in range(200):
        before = sim.status.copy()
        res = sim.step(driver.act_all())
        acted, new = np.nonzero(res.acted)[0], np.nonzero(res.spawned)[0]
        retired = acted[sim.status[acted] == EMPTY]
        if len(new):
            np.testing.assert_array_equal(res.obs[new], sim.observe(new)[0])
        if len(new) or len(retired):
            after = sim.observe(acted)[0]
            status = sim.status.copy()
            sim.status[new], sim.status[retired] = EMPTY, before[retired]
            want = sim.observe(acted)[0]
            sim.status[:] = status
            np.testing.assert_array_equal(res.obs[acted, 19:], want[:, 19:])  # the lidar
            going = sim.status[acted] == ACTIVE  # (the done ones' speeds are zeroed after their observation)
            np.testing.assert_array_equal(res.obs[acted[going]], want[going])
            checked += 1
            mattered += int(not np.array_equal(after[:, 19:], res.obs[acted, 19:]))
    assert checked >= 10 and mattered > 0


def test_line_detector_meets_line_boxes_as_bullet_does():
    """The side / lane-line detector against one 20 m line along x = 0 (a box 0.075 m wide, MetaDrive's), by hand:
    straight on, obliquely (the box's face, not the centre line), along it (the end of the box), from inside it."""
    p1, p2, hw, rng = np.array([[0.0, -10.0]]), np.array([[0.0, 10.0]]), 0.0375, 20.0
    pos = np.array([[-5.0, 0.0], [-5.0, 0.0], [0.01, -12.0], [0.01, 0.0], [5.0, 30.0]])
    heading = np.array([0.0, -math.pi / 3, math.pi / 2, 0.0, 0.0])
    got = line_detector(pos, heading, p1, p2, hw, rng) * rng  # beams [left, back, right, front]
    # straight on: the front beam meets the near face at x = -hw
    np.testing.assert_allclose(got[0], [rng, rng, rng, 5.0 - hw])
    # at -60 deg the front beam reaches x = -hw after (5 - hw) / cos 60 (at y = -8.6, on the box) and the left beam (at
    # +30 deg) after (5 - hw) / cos 30 (at y = 2.9); the others point away
    np.testing.assert_allclose(got[1], [(5.0 - hw) / math.cos(math.pi / 6), rng, rng, (5.0 - hw) / 0.5])
    # facing along the line from 2 m short of its end, 1 cm off its centre: the front beam meets the end face
    np.testing.assert_allclose(got[2], [rng, rng, rng, 2.0])
    # inside the box: Bullet's ray test sees no line it starts in
    np.testing.assert_allclose(got[3], [rng] * 4)
    # beyond the line's end, out of range: nothing
    np.testing.assert_allclose(got[4], [rng] * 4)
