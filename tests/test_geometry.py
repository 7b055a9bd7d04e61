"""Lidar, collisions, off-road tests and lane geometry against analytic constructions."""

import math

import numpy as np
import pytest

from coin_app.sim.collision import boxes_overlap
from coin_app.sim.config import make_config
from coin_app.sim.road_map import load_map
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.sensors import lidar_scan
from coin_app.sim.simulator import DrivingSimulator

L, W = 4.515, 1.852
HALF = (L / 2, W / 2)


def scan(others, heading=0.0, n=72, rng=50.0):
    """Lidar of an observer at the origin against boxes given as (x, y, heading)."""
    o = np.array(others, dtype=float).reshape(-1, 3)
    return lidar_scan(np.zeros((1, 2)), np.array([heading]), np.zeros(len(o), dtype=int), o[:, :2], o[:, 2], HALF, n, rng)[0]


def test_lidar_car_ahead_and_beside_match_metadrive_measurements():
    # MetaDrive: a car 10 m ahead reads 7.74 m on beam 0; a car in the left lane 2.57 m on beam 18
    ahead = scan([(10.0, 0.0, 0.0)])
    assert ahead[0] == pytest.approx(10.0 - L / 2, abs=1e-9)
    assert np.count_nonzero(ahead < 50.0) >= 1 and ahead[36] == 50.0
    left = scan([(0.0, 3.5, 0.0)])
    assert left[18] == pytest.approx(3.5 - W / 2, abs=1e-9)


def test_lidar_known_range_and_bearing_in_rotated_frames():
    # a box facing the observer at bearing 45 deg, range 20, observer heading 30 deg -> beam 3
    b = math.radians(45.0)
    d = scan([(20 * math.cos(b), 20 * math.sin(b), b)], heading=math.radians(30.0))
    assert d[3] == pytest.approx(20.0 - L / 2, abs=1e-9)
    # an oblique beam through a box side: observer at origin, box at (0, 10) heading 0,
    # beam 17 (85 deg) hits the near long side y = 10 - W/2 at distance (10 - W/2)/sin(85)
    d = scan([(0.0, 10.0, 0.0)])
    assert d[17] == pytest.approx((10 - W / 2) / math.sin(math.radians(85.0)), abs=1e-9)
    assert d[19] == pytest.approx((10 - W / 2) / math.sin(math.radians(95.0)), abs=1e-9)


def test_lidar_range_limit_nearest_box_wins_and_self_exclusion():
    assert (scan([(60.0, 0.0, 0.0)]) == 50.0).all()
    d = scan([(30.0, 0.0, 0.0), (12.0, 0.0, 1.0)])
    near = 12.0 - np.hypot(L / 2, W / 2)  # the rotated box is closer than its half-length...
    assert d[0] < 30.0 - L / 2 and d[0] >= near
    # the observer's own box is never seen: pairs exclude it by construction in the simulator
    sim = DrivingSimulator(make_config("intersection", num_agents=2))
    sim.reset(0)
    sim.place(0, (30.0, 3.5), 0.0)
    sim.place(1, (40.0, 3.5), 0.0)
    obs, _ = sim.observe(np.array([0, 1]))
    lidar = obs[:, 19:] * 50.0
    assert lidar[0, 0] == pytest.approx(10.0 - L / 2, abs=1e-5)  # beams start at the centre
    assert lidar[1, 36] == pytest.approx(10.0 - L / 2, abs=1e-5)
    assert (np.delete(lidar[0], [0, 1, 71]) == 50.0).all()


def test_box_overlap_thresholds_match_metadrive():
    one = np.ones(1)
    h = np.broadcast_to(np.array(HALF), (1, 2))

    def hit(dx, dy, dh=0.0):
        return bool(boxes_overlap(np.zeros((1, 2)), 0 * one, h, np.array([[dx, dy]]), dh * one, h)[0])

    assert hit(4.50, 0.0) and not hit(4.52, 0.0)  # head to tail
    assert hit(0.0, 1.84) and not hit(0.0, 1.86)  # side by side
    # T-bone: rotated 90 deg in front, the gap closes at L/2 + W/2
    assert hit(L / 2 + W / 2 - 0.01, 0.0, math.pi / 2) and not hit(L / 2 + W / 2 + 0.01, 0.0, math.pi / 2)


def inside_box(pts, cx, cy, h):
    c, s = math.cos(h), math.sin(h)
    x = (pts[:, 0] - cx) * c + (pts[:, 1] - cy) * s
    y = -(pts[:, 0] - cx) * s + (pts[:, 1] - cy) * c
    return (np.abs(x) <= L / 2) & (np.abs(y) <= W / 2)


def box_points(cx, cy, h, n=80):
    u, v = np.meshgrid(np.linspace(-L / 2, L / 2, n), np.linspace(-W / 2, W / 2, n // 2))
    c, s = math.cos(h), math.sin(h)
    return np.stack([cx + u.ravel() * c - v.ravel() * s, cy + u.ravel() * s + v.ravel() * c], 1)


def test_box_overlap_agrees_with_dense_point_sampling():
    rng = np.random.default_rng(1)
    h = np.broadcast_to(np.array(HALF), (1, 2))
    checked = 0
    for _ in range(400):
        cx, cy, hh = rng.uniform(-6, 6), rng.uniform(-4, 4), rng.uniform(-np.pi, np.pi)
        sampled = inside_box(box_points(cx, cy, hh), 0, 0, 0).any() or inside_box(box_points(0, 0, 0), cx, cy, hh).any()
        sat = bool(boxes_overlap(np.zeros((1, 2)), np.zeros(1), h, np.array([[cx, cy]]), np.array([hh]), h)[0])
        # sampling can only miss thin overlaps: where it sees one, SAT must too
        if sampled:
            assert sat
        elif sat:
            # SAT-only overlaps must be slivers: a slightly shrunk box no longer overlaps
            shrunk = np.broadcast_to(np.array(HALF) - 0.08, (1, 2))
            assert not boxes_overlap(np.zeros((1, 2)), np.zeros(1), shrunk, np.array([[cx, cy]]), np.array([hh]), shrunk)[0]
        checked += 1
    assert checked == 400


def place_one(scenario, x, y, heading, speed=0.0, route=0, **overrides):
    sim = DrivingSimulator(make_config(scenario, num_agents=1, allow_respawn=False, **overrides))
    sim.reset(0)
    sim.place(0, (x, y), heading, speed, route)
    return sim


def flags(sim):
    p, h = sim.pos[:1], sim.heading[:1]
    return bool(sim.map.hull_contains(p).any()), bool(sim._touches_solid_line(p, h)[0]), bool(sim._on_sidewalk(p, h)[0])


def test_side_line_and_sidewalk_thresholds():
    # intersection lane (>>, >>>, 1) runs along +x at y = 0; its right edge is a solid side line
    # at y = -1.75 and a sidewalk from y = -1.95 to -3.95. r = lateral offset to the right.
    for r, line, walk in [(0.0, False, False), (0.78, False, False), (0.80, True, False), (1.0, True, False), (1.05, True, True)]:
        on, ln, sw = flags(place_one("intersection", 30.0, -r, 0.0))
        assert on is True
        assert ln is line, r
        assert sw is walk, r
    # touching the solid yellow centre line from the left lane (y = 3.5, line at 5.25)
    assert flags(place_one("intersection", 30.0, 3.5 + 0.80, 0.0))[1]
    assert not flags(place_one("intersection", 30.0, 3.5 + 0.78, 0.0))[1]
    # broken white lane divider (y = 1.75) never counts
    assert not flags(place_one("intersection", 30.0, 1.75, 0.0))[1]
    # far from every lane: not on a lane
    assert not flags(place_one("intersection", 30.0, -30.0, 0.0))[0]


@pytest.mark.parametrize("solid", [True, False])
def test_bottleneck_neck_centre_line_is_solid_as_coin_ran_it_or_broken_as_metadrive_builds_it(solid):
    # the neck (x 60..120, one lane each way at y = 10.5 and 14) has its centre line at y = 12.25
    on, line, _ = flags(place_one("bottleneck", 90.0, 12.25, 0.0, solid_center_line=solid))
    assert on and line is solid  # touching it is off-road only when it is solid
    # from the eastbound lane's centre (y = 10.5) the car touches it between 0.78 and 0.80 m to the left, as any solid line
    assert flags(place_one("bottleneck", 90.0, 10.5 + 0.80, 0.0, solid_center_line=solid))[1] is solid
    assert not flags(place_one("bottleneck", 90.0, 10.5 + 0.78, 0.0, solid_center_line=solid))[1]
    # the side detector's left beam from the eastbound lane sees the solid centre line 1.75 m away, else the far road edge
    sim = place_one("bottleneck", 90.0, 10.5, 0.0, obs_layout="bottleneck96", solid_center_line=solid)
    left = sim.observe(np.array([0]))[0][0, 0] * 50
    assert left == pytest.approx((12.25 if solid else 15.75) - 10.5 - 0.0375, abs=1e-4)
    assert make_config("bottleneck").solid_center_line and not make_config("bottleneck", "metadrive_compat").solid_center_line


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_lane_coordinates_round_trip(scenario):
    m = load_map(scenario)
    rng = np.random.default_rng(0)
    lane = rng.integers(0, m.num_lanes, 500)
    s = rng.uniform(0, 1, 500) * m.length[lane]
    r = rng.uniform(-1.75, 1.75, 500)
    s2, r2 = m.local_coordinates(lane, m.position(lane, s, r))
    assert np.allclose(s, s2, atol=1e-9) and np.allclose(r, r2, atol=1e-9)
    # right normal is perpendicular to the lane heading
    p = m.position(lane, s, np.zeros(500))
    h = m.heading_at(lane, s)
    n = m.right_normal(lane, p)
    assert np.allclose(n[:, 0] * np.cos(h) + n[:, 1] * np.sin(h), 0, atol=1e-9)
    assert np.allclose(n[:, 0] * np.sin(h) - n[:, 1] * np.cos(h), 1, atol=1e-9)


def test_route_lengths_match_map_data():
    # the JSON records each route's length along lane 0; recompute it from our lane lengths
    import json

    from coin_app.sim.road_map import MAP_DIR

    for name in DRIVING_SCENARIOS:
        m = load_map(name)
        data = json.loads((MAP_DIR / f"{name}.json").read_text())
        for route, rec in zip(m.routes, data["destinations"]["routes"]):
            total = sum(m.length[m.road_first_lane[rd]] for rd in route.roads)
            assert total == pytest.approx(rec["total_length_lane0"], abs=1e-4)


def test_bottleneck96_detectors_match_metadrive_measurement():
    # MetaDrive (measured): lane 1 of the bottleneck's first block at y = 7 reads
    # side detector [left, back, right, front] = [5.2125, 50, 8.7125, 44.3] m
    sim = DrivingSimulator(make_config("bottleneck", num_agents=2, allow_respawn=False, obs_layout="bottleneck96"))
    sim.reset(0)
    sim.remove(1)
    sim.place(0, (30.0, 7.0), 0.0, route=1)
    obs = sim.observe(np.array([0]))[0][0].astype(float)
    assert obs.shape == (96,)
    side = obs[:4] * 50
    assert side[:3] == pytest.approx([12.25 - 7 - 0.0375, 50.0, 7 + 1.75 - 0.0375], abs=1e-4)
    assert side[3] == pytest.approx(44.3, abs=0.1)
    # lane-line detector (20 m, broken lines too): a dash of the divider at y = 8.75 on the left
    assert obs[10] * 20 == pytest.approx(8.75 - 7 - 0.0375, abs=1e-4)
    # a sideways beam passes through a gap between dashes: at x = 3 (gap 2..4 m) it reaches the
    # solid centre line at y = 12.25
    sim.place(0, (3.0, 7.0), 0.0, route=1)
    obs = sim.observe(np.array([0]))[0][0].astype(float)
    assert obs[10] * 20 == pytest.approx(12.25 - 7 - 0.0375, abs=1e-4)
    # the remaining layout is MetaDrive's: heading, speed, steering, action, yaw, nav, lidar
    std = DrivingSimulator(make_config("bottleneck", num_agents=2, allow_respawn=False))
    std.reset(0)
    std.remove(1)
    std.place(0, (3.0, 7.0), 0.0, route=1)
    ref = std.observe(np.array([0]))[0][0]
    assert np.array_equal(obs[4:10], ref[2:8]) and np.array_equal(obs[14:], ref[9:])


def test_sector_lidar_equals_brute_force_ray_casting():
    from coin_app.sim.collision import ray_box_distance

    rng = np.random.default_rng(4)
    for _ in range(30):
        n = 12
        pos = rng.uniform(-30, 30, (n, 2))
        hd = rng.uniform(-np.pi, np.pi, n)
        obs_i, box_j = np.nonzero(~np.eye(n, dtype=bool))
        fast = lidar_scan(pos, hd, obs_i, pos[box_j], hd[box_j], HALF, 72, 50.0)
        # brute force: every beam of every observer against every other box
        ang = hd[:, None] + np.arange(72)[None, :] * 2 * np.pi / 72
        slow = np.full((n, 72), 50.0)
        for j in range(n):
            dirs = np.stack([np.cos(ang), np.sin(ang)], -1).reshape(-1, 2)
            origin = np.repeat(pos, 72, axis=0)
            t = ray_box_distance(
                origin, dirs, np.broadcast_to(pos[j], (n * 72, 2)), np.full(n * 72, hd[j]), np.broadcast_to(np.array(HALF), (n * 72, 2))
            )
            t = t.reshape(n, 72)
            t[j] = np.inf  # a vehicle does not see itself
            slow = np.minimum(slow, t)
        assert np.allclose(fast, slow, atol=1e-9)
