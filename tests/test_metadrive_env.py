"""The MetaDrive backend: same interface, ids, flags, local state and metrics as the native env.

Runs only with the optional extra installed (CI installs it). MetaDrive allows one engine
per process, so every test closes its env.
"""

import numpy as np
import pytest

pytest.importorskip("metadrive", reason="the optional MetaDrive extra is not installed (pip install -r requirements-metadrive.txt)")

from coin_app.adapters.rllib_env import CoinMultiAgentEnv  # noqa: E402
from coin_app.backends.metadrive import MetaDriveDrivingEnv, open_in_this_process  # noqa: E402
from coin_app.evaluation.evaluate import evaluate_policy  # noqa: E402
from coin_app.evaluation.metrics import EpisodeRecorder  # noqa: E402
from coin_app.sim.collision import boxes_overlap  # noqa: E402
from coin_app.sim.config import make_config  # noqa: E402
from coin_app.sim.driving_env import DrivingEnv  # noqa: E402
from coin_app.sim.rendering import EpisodeTrace, write_gif  # noqa: E402
from coin_app.sim.road_map import load_map  # noqa: E402
from coin_app.sim.scenes import DRIVING_SCENARIOS  # noqa: E402
from coin_app.sim.simulator import DrivingSimulator  # noqa: E402

SMALL = {"num_agents": 4, "horizon": 60, "max_agent_steps": 60}
NATIVE_INFO_KEYS = set(DrivingEnv(make_config("intersection", num_agents=2)).reset(0)[1]["agent0"])


def forward_policy(rng):
    return lambda obs: np.stack([rng.uniform(-0.4, 0.4, len(obs)), rng.uniform(0.3, 1.0, len(obs))], 1)


METADRIVE_OBS_DIMS = {"intersection": 91, "roundabout": 91, "bottleneck": 96}  # MetaDrive's own (docs/reference/deviations.md)


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_rllib_adapter_spaces_ids_and_all_flags(scenario):
    obs_dim = METADRIVE_OBS_DIMS[scenario]
    env = CoinMultiAgentEnv({"scenario": scenario, "backend": "metadrive", **SMALL, "delay_done": 2})
    try:
        pool = set(env.possible_agents)
        assert len(pool) == 4 + 4 * 60
        obs, infos = env.reset(seed=1)
        assert sorted(obs) == [f"agent{i}" for i in range(4)] and set(infos) == set(obs)
        seen, finished = set(obs), set()
        rng = np.random.default_rng(0)
        steps = 0
        while True:  # hard constant steering: vehicles leave the road and respawn within the horizon
            acts = {a: np.array([0.6 if int(a[5:]) % 2 else -0.6, rng.uniform(0.5, 1.0)]) for a in env.agents}
            obs, rew, term, trunc, infos = env.step(acts)
            steps += 1
            assert "__all__" in term and "__all__" in trunc
            assert set(rew) == set(acts) and set(term) - {"__all__"} == set(acts) == set(trunc) - {"__all__"}
            assert set(infos) == set(obs) and set(obs) <= pool
            for aid, o in obs.items():
                assert o.shape == (obs_dim,) and o.dtype == np.float32
                assert env.observation_spaces[aid].contains(o)
                assert set(infos[aid]) == NATIVE_INFO_KEYS
                assert infos[aid]["env_step"] == steps
            new = set(obs) - set(acts)
            assert not new & seen, "respawned vehicles get new, never reused ids"
            seen |= new
            for aid in acts:
                assert not (term[aid] and trunc[aid])
                if trunc[aid]:  # a vehicle's own step limit: truncated, never terminated
                    assert infos[aid]["max_step"] and infos[aid]["episode_length"] == 60
                if term[aid]:
                    i = infos[aid]
                    assert i["arrive_dest"] or i["crash_vehicle"] or i["out_of_road"]
                if term[aid] or trunc[aid]:
                    finished.add(aid)
            if term["__all__"]:
                break
            assert not trunc["__all__"] and set(env.agents) == (set(acts) - finished) | new
        assert len(seen) > 4 and finished  # vehicles finished and respawned
        with pytest.raises(RuntimeError, match="reset"):
            env.step({})
    finally:
        env.close()
    assert not open_in_this_process()


def test_local_state_matches_metadrive_vehicles():
    env = MetaDriveDrivingEnv(scenario="roundabout", num_agents=6)
    try:
        m = load_map("roundabout")
        obs, infos = env.reset(seed=3)
        rng = np.random.default_rng(1)
        for _ in range(25):
            obs, _, _, _, infos = env.step({a: np.array([rng.uniform(-0.2, 0.2), 0.8]) for a in env.agents})
        checked = 0
        for aid in env.agents:
            v, s = env.md.agents[aid], infos[aid]["state"]
            h = v.heading_theta
            np.testing.assert_allclose(s[:2], (np.asarray(v.position) - m.centre) / m.scale, atol=1e-5)
            np.testing.assert_allclose(s[2:4], np.asarray(v.velocity) / (80 / 3.6), atol=1e-5)
            np.testing.assert_allclose(s[4:6], [np.cos(h), np.sin(h)], atol=1e-6)
            # checkpoint 1 = middle of the current reference road's end = mean of its lane ends
            ck = np.mean([np.asarray(lane.end) for lane in v.navigation.current_ref_lanes], 0)
            d = ck - np.asarray(v.position)
            d = d * min(1.0, 50.0 / np.linalg.norm(d)) / 50.0
            np.testing.assert_allclose(s[6:8], d, atol=1e-5)
            # MetaDrive's own observation of checkpoint 1 (ego frame, forward component)
            assert abs(obs[aid][9] - (np.dot(s[6:8], [np.cos(h), np.sin(h)]) + 1) / 2) < 1e-4
            assert np.hypot(*s[8:10]) <= 1 + 1e-6
            checked += 1
        assert checked >= 3
    finally:
        env.close()


def test_metrics_agree_with_raw_metadrive_infos():
    env = MetaDriveDrivingEnv(scenario="intersection", **SMALL)
    raw_step = env.md.step
    raw = []

    def recording_step(actions):
        out = raw_step(actions)
        raw.append(out)
        return out

    env.md.step = recording_step
    try:
        rec = EpisodeRecorder()
        obs, infos = env.reset(seed=5)
        rec.reset(infos)
        policy = forward_policy(np.random.default_rng(2))
        while not env.episode_over:
            agents = list(env.agents)
            acts = dict(zip(agents, policy(np.stack([obs[a] for a in agents]))))
            new_obs, rewards, terms, truncs, infos = env.step(acts)
            obs.update(new_obs)
            rec.step(infos, terms, truncs, rewards)
        got = rec.metrics()
    finally:
        env.close()
    # independent count over MetaDrive's own per-agent infos: each vehicle's first done step decides
    vehicles, outcome = set(obs) | {f"agent{i}" for i in range(4)}, {}
    for o, r, tm, tc, info in raw:
        vehicles |= set(o)
        for aid in tm:
            if aid == "__all__" or aid in outcome or not (tm[aid] or tc[aid]):
                continue
            i = info[aid]
            outcome[aid] = "arrive" if i["arrive_dest"] else "crash" if i["crash_vehicle"] else "oor" if i["out_of_road"] else "time"
            if outcome[aid] in ("crash", "oor"):
                assert r[aid] == -5.0  # the paper's penalty reached MetaDrive (its own default is -10)
    n = len(vehicles)
    counts = {k: sum(v == k for v in outcome.values()) for k in ("arrive", "crash", "oor")}
    assert got["num_vehicles"] == n > 4
    assert got["num_crashed"] == counts["crash"] and got["num_out_of_road"] == counts["oor"]
    assert got["num_arrived"] == counts["arrive"]
    assert got["success_rate"] == pytest.approx(counts["arrive"] / n)
    assert got["collision_rate"] == pytest.approx(counts["crash"] / n)
    assert got["safety"] == -(counts["crash"] + counts["oor"])
    assert counts["crash"] + counts["oor"] > 0
    assert got["env_steps"] == len(raw)


def scripted(obs):
    # steer towards checkpoint 1 (its lateral feature), hold ~30 km/h
    steer = np.clip(4.0 * (obs[:, 10] - 0.5), -1, 1)
    throttle = np.where(obs[:, 3] < 0.35, 0.6, -0.1)
    return np.stack([steer, throttle], 1)


def test_scripted_policy_metrics_repeat_exactly():
    cfg = make_config("intersection", backend="metadrive", **SMALL)
    first = evaluate_policy(scripted, cfg, [11, 12])
    np.testing.assert_equal(evaluate_policy(scripted, cfg, [11, 12]), first)  # NaN == NaN here (no arrivals)
    np.testing.assert_equal(evaluate_policy(scripted, cfg, [12]), first[1:])  # an episode depends on its seed only
    assert first[0]["episode_return"] != first[1]["episode_return"]
    # with an engine already open here, the episodes run in a worker process: same numbers
    env = MetaDriveDrivingEnv(cfg)
    try:
        np.testing.assert_equal(evaluate_policy(scripted, cfg, [11, 12]), first)
    finally:
        env.close()


def test_one_engine_per_process_topdown_rendering_and_no_3d(tmp_path):
    env = MetaDriveDrivingEnv(scenario="bottleneck", num_agents=4)
    try:
        with pytest.raises(RuntimeError, match="one engine per process"):
            MetaDriveDrivingEnv(scenario="intersection")
        trace = EpisodeTrace()
        _, infos = env.reset(seed=0)
        trace.record(env, infos)
        frames = [env.render("topdown", size=(160, 120))]
        for _ in range(10):
            _, _, _, _, infos = env.step({a: np.array([0.0, 1.0]) for a in env.agents})
            trace.record(env, infos)
            frames.append(env.render("topdown", size=(160, 120)))
        assert frames[0].shape == (120, 160, 3) and frames[0].dtype == np.uint8
        assert not np.array_equal(frames[0], frames[-1])  # the cars moved
        paths = trace.trajectories()
        assert len(paths) == 4 and all(len(p) == 11 for p in paths.values())
        assert all(1.0 < np.linalg.norm(p[-1] - p[0]) < 2.5 for p in paths.values())  # ~ a t^2 / 2 = 1.45 m
        assert write_gif(frames, tmp_path / "md.gif").stat().st_size > 0
        md_frame = env.render("metadrive_topdown", size=(100, 100))
        assert md_frame.ndim == 3 and md_frame.shape[2] == 3
        with pytest.raises(RuntimeError, match="3D assets"):
            env.render("rgb_array")
    finally:
        env.close()
    MetaDriveDrivingEnv(scenario="intersection").close()  # a new engine after close()


@pytest.mark.parametrize("scenario", DRIVING_SCENARIOS)
def test_native_observations_of_metadrive_poses_match_metadrive(scenario):
    """Put native vehicles where MetaDrive's are (same route and route progress): same observations."""
    from coin_app.sim.simulator import DYING, DrivingSimulator

    cfg = make_config(scenario, backend="metadrive", num_agents=20)
    env = MetaDriveDrivingEnv(cfg)
    try:
        obs, _ = env.reset(seed=4)
        rng = np.random.default_rng(0)
        last = {}
        for _ in range(60):
            acts = {a: np.array([rng.uniform(-0.1, 0.1), rng.uniform(0.2, 0.6)]) for a in env.agents}
            obs.update(env.step(acts)[0])
            last.update(acts)
        sim = DrivingSimulator(make_config(scenario, num_agents=20, obs_layout=cfg.obs_layout))
        sim.reset(0)
        for s in range(sim.num_slots):
            sim.remove(s)
        m = sim.map
        route_of = {(r.spawn_lane, r.destination): k for k, r in enumerate(m.routes)}
        ids = list(env.md.agents)
        for j, aid in enumerate(ids):
            v = env.md.agents[aid]
            nav = v.navigation
            lane = m.lane_index[tuple(v.config["spawn_lane_index"][:2]) + (int(v.config["spawn_lane_index"][2]),)]
            route = route_of[(lane, nav.checkpoints[-1])]
            sim.place(j, tuple(np.asarray(v.position)[:2]), float(v.heading_theta), speed=float(v.speed), route=route)
            sim.vel[j] = np.asarray(v.velocity)[:2]
            sim.action[j] = last[aid]
            road = m.road_index[(nav.current_road.start_node, nav.current_road.end_node)]
            sim.ref_idx[j] = list(m.route_roads[route]).index(road)  # route progress is history, as in MetaDrive
        k = len(ids)
        for v in env.md.agent_manager.dying_agents.values():  # wrecks are lidar obstacles
            sim.place(k, tuple(np.asarray(v.position)[:2]), float(v.heading_theta), route=0)
            sim.status[k] = DYING
            k += 1
        native, _ = sim.observe(np.arange(len(ids)))
    finally:
        env.close()
    md = np.stack([obs[a] for a in ids])
    ego = cfg.obs_dim - cfg.lidar_beams
    # yaw rate needs the previous heading: not compared; the bottleneck's 2 x 4 detector beams
    # meet line ends a little differently (2-D boxes vs Bullet bodies): within 1.2 m / 0.5 m
    yaw, detectors = (9, [0, 1, 2, 3, 10, 11, 12, 13]) if cfg.obs_layout == "bottleneck96" else (7, [])
    cols = [c for c in range(ego) if c != yaw and c not in detectors]
    assert len(ids) >= 15
    assert np.abs(native[:, cols] - md[:, cols]).max() < 1e-3  # ego state and navigation
    assert np.abs(native[:, detectors] - md[:, detectors]).max(initial=0.0) < 0.03
    lidar = np.abs(native[:, ego:] - md[:, ego:])
    assert (lidar > 0.01).mean() < 0.03 and lidar.mean() < 0.02  # a few edge beams hit / miss differently


def test_at_rest_metadrive_touches_where_the_native_boxes_do():
    """Two cars placed at rest head to tail crash in MetaDrive at a gap of 0 and not at 5 mm (the native box test: no
    contact margin); a lone car touches the solid yellow centre line 1.75 m beside its lane centre between 0.785 and
    0.7875 m of offset, where the native footprint does (1.75 - 0.926 - 0.0375 = 0.7865 m)."""
    env = MetaDriveDrivingEnv(make_config("intersection", backend="metadrive", num_agents=2, allow_respawn=False))
    length, width = env.config.vehicle_length, env.config.vehicle_width

    def placed(offsets):
        env.reset(seed=0)
        vehicles = list(env.md.agents.values())
        for v, (x, y) in zip(vehicles, offsets):
            v.set_position((x, y))
            v.set_heading_theta(0.0)
            v.set_velocity([1.0, 0.0], 0.0)
            v.set_angular_velocity(0.0)
        infos = env.step({a: np.zeros(2) for a in env.agents})[4]
        return vehicles, infos

    try:
        for gap, crash in ((0.0, True), (0.005, False)):
            _, infos = placed([(30.0, 3.5), (30.0 + length + gap, 3.5)])
            assert [infos[a]["crash_vehicle"] for a in sorted(infos)] == [crash, crash], gap
        for offset, touch in ((0.785, False), (0.7875, True)):
            vehicles, _ = placed([(30.0, 3.5 + offset), (-30.0, 0.0)])
            assert vehicles[0].on_yellow_continuous_line is touch, offset
    finally:
        env.close()
    native = DrivingSimulator(make_config("intersection", num_agents=1, allow_respawn=False))
    native.reset(0)
    for offset, touch in ((0.785, False), (0.7875, True)):
        assert native._touches_solid_line(np.array([[30.0, 3.5 + offset]]), np.zeros(1))[0] == touch
    half = np.array([[length / 2, width / 2]])
    for gap, crash in ((0.0, True), (0.005, False)):
        assert boxes_overlap(np.zeros((1, 2)), np.zeros(1), half, np.array([[length + gap, 0.0]]), np.zeros(1), half)[0] == crash


def test_metadrive_lets_one_vehicle_enter_per_step():
    """MetaDrive's spawn manager marks every place it finds free as used at its first query of a step, so one vehicle
    enters per step even when several left together with entry places free: the native default (``respawns_per_step``
    1) follows it."""
    env = MetaDriveDrivingEnv(make_config("intersection", backend="metadrive", num_agents=8, horizon=80, max_agent_steps=80, delay_done=0))
    try:
        env.reset(seed=3)
        rng = np.random.default_rng(0)
        backlog, entered = 0, []
        while not env.episode_over and env.md.episode_step < 80:
            acts = {a: np.array([0.8 if int(a[5:]) % 2 else -0.8, rng.uniform(0.6, 1.0)]) for a in env.agents}
            obs, _, term, trunc, _ = env.step(acts)
            backlog += sum(bool(term[a] or trunc[a]) for a in acts)  # vehicles gone, to be replaced
            new = len(set(obs) - set(acts))
            backlog -= new
            entered.append((new, backlog))
    finally:
        env.close()
    assert max(n for n, _ in entered) == 1
    assert sum(n for n, _ in entered) >= 4 and max(b for _, b in entered) >= 2  # replacements queued behind the one per step


@pytest.mark.parametrize("per_step", [1, 0])
def test_native_steps_taken_from_metadrive_states_agree_with_metadrive(per_step):
    """A recorded case of the closed loop: before every MetaDrive step, every vehicle (and wreck) is put into the native
    simulator, which takes the same step with the same actions. Vehicles leave the road, wrecks count down, and their
    replacements queue for the entry places. With MetaDrive's rule (``respawns_per_step`` 1) the respawn counts agree at
    every step; with the rule the native simulator had before (0) they part. Poses agree to centimetres. Crashes agree
    vehicle for vehicle: both test the chassis before every physics step and after the last (tested on the shown pose
    after the step, the native simulator had missed 4 of MetaDrive's 6 crashed vehicles here). A native exit is always a
    MetaDrive one; MetaDrive's line contacts within millimetres, the chassis' tilt (docs/reference/deviations.md), make
    2 of its 20 exits here that the native footprint test does not see (5 before line contacts were tested after the
    last physics step)."""
    from coin_app.backends.shadow import shadow_episode

    cfg = make_config("intersection", backend="metadrive", num_agents=16, delay_done=3)
    rng = np.random.default_rng(0)

    def policy(obs):
        return np.stack([rng.uniform(-0.7, 0.7, len(obs)), rng.uniform(0.2, 1.0, len(obs))], 1)

    out = shadow_episode(cfg, policy, 4, 120, {"respawns_per_step": per_step})
    md, native = np.array(out["spawned_md"]), np.array(out["spawned_native"])
    assert out["out_of_road_md"].count(True) >= 10 and md.sum() >= 10  # exits and respawns happened
    if per_step == 0:
        assert (native > md).any()  # where several left together, every free place was filled at once
        return
    assert np.array_equal(md, native) and md.max() == 1
    crash_md, crash_native = np.array(out["crash_vehicle_md"]), np.array(out["crash_vehicle_native"])
    assert np.array_equal(crash_md, crash_native) and crash_md.sum() >= 4
    exit_md, exit_native = np.array(out["out_of_road_md"]), np.array(out["out_of_road_native"])
    assert not (exit_native & ~exit_md).any() and (exit_md & ~exit_native).sum() <= 2
    assert out["arrive_dest_md"] == out["arrive_dest_native"] and out["max_step_md"] == out["max_step_native"]
    assert max(out["pos_err"]) < 0.02 and max(out["speed_err"]) < 0.5  # m, km/h
