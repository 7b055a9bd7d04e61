"""Shadow steps: every step of a MetaDrive episode taken again by the native simulator, from MetaDrive's own state.

Closed-loop episodes of the two simulators part within seconds (the traffic is chaotic), so whole episodes say little
about where they differ; one step from one state says it exactly. :func:`transplant` puts every vehicle MetaDrive
holds (active ones with their chassis state, route, route progress and step count; wrecks with their countdown) into a
native simulator; :func:`shadow_episode` does it before every step of an episode and compares what the step does in
each. ``benchmarks/shadow_step.py`` prints it for the COIN authors' actors (docs/results/reference/README.md).
"""

from __future__ import annotations

import collections
from dataclasses import replace
from typing import Any

import numpy as np

from coin_app.backends.metadrive import MetaDriveDrivingEnv
from coin_app.backends.vehicle_traces import _state
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.simulator import DYING, EMPTY, DrivingSimulator
from coin_app.sim.vehicle_replay import _bodies_at

FLAGS = ("arrive_dest", "crash_vehicle", "out_of_road", "max_step")


def transplant(env: MetaDriveDrivingEnv, sim: DrivingSimulator, last: dict[str, tuple[np.ndarray, float]]) -> list[str]:
    """Put every vehicle of ``env`` into ``sim`` (one env): active ones first, in ``env.agents`` order, then wrecks.

    ``last``: per agent, its previous action and heading (the observation's yaw rate and last action).
    """
    md, m = env.md, env.map
    sim.reset(0)
    sim.status[:] = EMPTY
    route_of = {(r.spawn_lane, r.destination): k for k, r in enumerate(m.routes)}
    ids = list(env.agents)
    wrecks = [(v, n) for (v, n) in md.agent_manager._dying_objects.values()]
    if len(ids) + len(wrecks) > sim.num_slots:
        raise RuntimeError(f"{len(ids)} active and {len(wrecks)} dying vehicles do not fit {sim.num_slots} slots")
    states = []
    for j, aid in enumerate(ids):
        v = md.agents[aid]
        nav = v.navigation
        lane = m.lane_index[tuple(v.config["spawn_lane_index"][:2]) + (int(v.config["spawn_lane_index"][2]),)]
        route = route_of[(lane, nav.checkpoints[-1])]
        sim.place(j, tuple(np.asarray(v.position)[:2]), float(v.heading_theta), speed=float(v.speed), route=route)
        sim.ref_idx[j] = list(m.route_roads[route]).index(m.road_index[(nav.current_road.start_node, nav.current_road.end_node)])
        sim.ep_len[j] = md.episode_lengths[aid]
        if aid in last:
            sim.action[j], sim.heading_prev[j] = last[aid]
        states.append(_state(v))
    for k, (v, left) in enumerate(wrecks, start=len(ids)):
        sim.place(k, tuple(np.asarray(v.position)[:2]), float(v.heading_theta), route=0)
        sim.status[k], sim.dying_left[k] = DYING, left
        states.append(_state(v))
    n = len(states)
    if n and sim.bodies is not None:
        x0 = np.stack(states)
        moving = np.array([md.episode_lengths[a] > 0 for a in ids] + [False] * len(wrecks))
        b = _bodies_at(x0, moving)
        for name in ("pos", "rot", "vel", "ang"):
            getattr(sim.bodies, name)[:n] = getattr(b, name)
        sim.vel[:n] = x0[:, 7:9]
    sim.env_step[:] = md.episode_step
    return ids


def ray_box_distance(origin: np.ndarray, angle: float, center: np.ndarray, heading: float, length: float, width: float) -> float:
    """Distance along the ray from ``origin`` at ``angle`` to the rectangle (``center``, ``heading``, ``length`` x
    ``width``), by the slab method; ``inf`` when the ray misses it."""
    c, s = np.cos(heading), np.sin(heading)
    rel = np.asarray(origin, float) - np.asarray(center, float)
    o = np.array([c * rel[0] + s * rel[1], -s * rel[0] + c * rel[1]])
    d = np.array([c * np.cos(angle) + s * np.sin(angle), -s * np.cos(angle) + c * np.sin(angle)])
    t_near, t_far = -np.inf, np.inf
    for k, half in ((0, length / 2), (1, width / 2)):
        if abs(d[k]) < 1e-12:
            if abs(o[k]) > half:
                return np.inf
            continue
        t1, t2 = (-half - o[k]) / d[k], (half - o[k]) / d[k]
        t_near, t_far = max(t_near, min(t1, t2)), min(t_far, max(t1, t2))
    return max(t_near, 0.0) if t_far >= max(t_near, 0.0) else np.inf


def _exact_beam(vehicles: list[Any], boxes: np.ndarray, j: int, beam: int, config: ScenarioConfig) -> float:
    """Beam ``beam`` of vehicle ``j``'s lidar by exact ray-rectangle geometry (range-normalised): from MetaDrive's shown pose
    of ``j``, against the other vehicles' chassis poses ``boxes`` (x, y, heading per vehicle, in ``vehicles`` order)."""
    v = vehicles[j]
    origin, angle = np.asarray(v.position)[:2], float(v.heading_theta) + 2 * np.pi * beam / config.lidar_beams
    hits = [
        ray_box_distance(origin, angle, boxes[k, :2], float(boxes[k, 2]), config.vehicle_length, config.vehicle_width)
        for k in range(len(vehicles))
        if k != j
    ]
    return min(1.0, min(hits, default=np.inf) / config.lidar_range)


def shadow_episode(
    config: ScenarioConfig, policy: Any, seed: int, steps: int, native_overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Run one MetaDrive episode of ``config`` (its native twin: the same config on the native backend) driven by
    ``policy`` (observations (n, obs_dim) -> actions (n, 2)), and take every step natively too from MetaDrive's state
    before it (:func:`transplant`), with the same actions. Returns per-step and per-vehicle-step comparisons (lists):
    ``pos_err`` (m), ``heading_err`` (rad), ``speed_err`` (km/h) of vehicles active before and after the step in both;
    ``<flag>_md`` / ``<flag>_native`` per acting vehicle for each of :data:`FLAGS`, and ``events`` where they differ;
    ``spawned_md`` / ``spawned_native`` per step and ``spawn_events`` where the counts differ; ``ego_err``, ``lidar_err``
    (per step), ``lidar_flips`` (beams off by more than 0.2, per step) and ``flip_exact`` (per such beam: whether the native
    and whether MetaDrive's value equals exact ray-rectangle geometry from MetaDrive's pose against the chassis the
    transplant gave the others), ``action_err`` (per vehicle step: the policy on
    the native observation against its action on MetaDrive's); ``steps``: steps taken. ``native_overrides``: settings
    of the native twin that differ (e.g. a rule as it was before a fix)."""
    env = MetaDriveDrivingEnv(replace(config, backend="metadrive"))
    sim = DrivingSimulator(replace(config, backend="native", **(native_overrides or {})), 1)
    ego = sim.cfg.obs_dim - sim.cfg.lidar_beams
    out: dict[str, Any] = collections.defaultdict(list)
    last: dict[str, tuple[np.ndarray, float]] = {}
    try:
        obs, _ = env.reset(seed=seed)
        for t in range(steps):
            if env.episode_over:
                break
            ids = transplant(env, sim, last)
            md_obs = np.stack([obs[a] for a in ids])
            act = policy(md_obs)
            nat_obs = sim.observe(np.arange(len(ids)))[0]
            ego_err = np.abs(nat_obs[:, :ego] - md_obs[:, :ego])
            out["ego_err"].append(ego_err.max())
            if ego_err.max() > 0.01:
                j, c = np.unravel_index(np.argmax(ego_err), ego_err.shape)
                out["ego_events"].append((t, ids[j], int(c), float(nat_obs[j, c]), float(md_obs[j, c])))
            lidar_err = np.abs(nat_obs[:, ego:] - md_obs[:, ego:])
            out["lidar_err"].append(lidar_err.mean())
            out["lidar_flips"].append(int((lidar_err > 0.2).sum()))
            vehicles = [env.md.agents[a] for a in ids] + [v for v, _ in env.md.agent_manager._dying_objects.values()]
            for j, b in zip(*np.nonzero(lidar_err > 0.2)):
                exact = _exact_beam(vehicles, sim._chassis_poses(), int(j), int(b), sim.cfg)
                out["flip_exact"].append((abs(exact - nat_obs[j, ego + b]) < 0.02, abs(exact - md_obs[j, ego + b]) < 0.02))
            out["action_err"].extend(np.abs(policy(nat_obs) - act).max(1))
            full = np.zeros((sim.num_slots, 2))
            full[: len(ids)] = act
            speed_before = sim.speed[: len(ids)].copy()
            sim_heading = sim.heading[: len(ids)].copy()
            res = sim.step(full)
            new_obs, _, _, _, infos = env.step(dict(zip(ids, act)))
            final = env.md.coin_final
            last = {aid: (act[j], float(sim_heading[j])) for j, aid in enumerate(ids)}
            for j, aid in enumerate(ids):
                info = infos[aid]
                for flag in FLAGS:
                    a, b = bool(info[flag]), bool(getattr(res, flag)[j])
                    out[f"{flag}_md"].append(a)
                    out[f"{flag}_native"].append(b)
                    if a != b:
                        out["events"].append((t, aid, flag, a, b, float(speed_before[j]) * 3.6))
                done_md = bool(info["arrive_dest"] or info["crash_vehicle"] or info["out_of_road"] or info["max_step"])
                done_nat = bool(res.terminated[j] or res.truncated[j])
                if not done_md and not done_nat:
                    x = _state(env.md.agents[aid]) if aid in env.md.agents else final[aid]
                    out["pos_err"].append(float(np.hypot(*(x[:2] - sim.pos[j]))))
                    out["heading_err"].append(float(abs((x[2] - sim.heading[j] + np.pi) % (2 * np.pi) - np.pi)))
                    out["speed_err"].append(float(abs(x[3] - sim.speed[j]) * 3.6))
            md_new = [tuple(np.round(np.asarray(env.md.agents[a].position)[:2], 1)) for a in new_obs if a not in ids]
            nat_new = [tuple(np.round(sim.pos[k], 1)) for k in np.nonzero(res.spawned)[0]]
            out["spawned_md"].append(len(md_new))
            out["spawned_native"].append(len(nat_new))
            if len(md_new) != len(nat_new):
                live = int((env.md.agent_manager._active_objects.__len__()) + len(env.md.agent_manager._dying_objects))
                out["spawn_events"].append((t, md_new, nat_new, live))
            out["wrecks"].append(int((sim.status == DYING).sum()))
            obs.update(new_obs)
    finally:
        env.close()
    out["steps"] = t
    return out
