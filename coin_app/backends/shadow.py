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
from coin_app.sim import collision
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


def _ray(angle: float) -> np.ndarray:
    return np.array([[np.cos(angle), np.sin(angle)]])


def ray_box_distance(origin: np.ndarray, angle: float, center: np.ndarray, heading: float, length: float, width: float) -> float:
    """Distance along the ray from ``origin`` at ``angle`` to the rectangle (``center``, ``heading``, ``length`` x
    ``width``) (:func:`coin_app.sim.collision.ray_box_distance`); ``inf`` when the ray misses it."""
    half = np.array([[length / 2, width / 2]])
    o, c = np.asarray(origin, float)[None, :2], np.asarray(center, float)[None, :2]
    return float(collision.ray_box_distance(o, _ray(angle), c, np.array([float(heading)]), half)[0])


def ray_box_clearance(origin: np.ndarray, angle: float, center: np.ndarray, heading: float, length: float, width: float) -> float:
    """How squarely the ray meets the rectangle: its chord through it (m) when it hits, minus its distance from it when it
    misses (the nearest of a corner to the ray and the ray's origin to an edge). A grazing ray gives a value near 0."""
    d = _ray(angle)[0]
    o = np.asarray(origin, float)[:2]
    t_in = ray_box_distance(o, angle, center, heading, length, width)
    if np.isfinite(t_in):  # the exit: where the reversed ray from far beyond meets the box
        far = o + d * (t_in + length + width)
        return float(length + width - ray_box_distance(far, angle + np.pi, center, heading, length, width))
    corners = collision.box_corners(np.asarray(center, float)[None, :2], np.array([float(heading)]), length / 2, width / 2)[0]
    t = np.maximum((corners - o) @ d, 0.0)
    miss = np.hypot(*(corners - o - t[:, None] * d).T).min()
    edges = [(corners[k], corners[(k + 1) % 4]) for k in range(4)]
    for p, q in edges:
        u = np.clip((o - p) @ (q - p) / ((q - p) @ (q - p)), 0.0, 1.0)
        miss = min(miss, float(np.hypot(*(o - p - u * (q - p)))))
    return -float(miss)


def outline_distance(point: np.ndarray, boxes: np.ndarray, length: float, width: float) -> np.ndarray:
    """Distance (m) from ``point`` to the outline of each rectangle ``boxes`` (x, y, heading per row); negative inside."""
    c, s = np.cos(boxes[:, 2]), np.sin(boxes[:, 2])
    rel = np.asarray(point, float)[:2] - boxes[:, :2]
    q = np.abs(np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], 1)) - np.array([length, width]) / 2
    return np.where((q > 0).any(1), np.hypot(*np.maximum(q, 0.0).T), q.max(1))


def _flip(
    vehicles: list[Any], boxes: np.ndarray, j: int, beam: int, config: ScenarioConfig, near: float
) -> tuple[float, float, float, int]:
    """Beam ``beam`` of vehicle ``j``'s lidar by exact ray-rectangle geometry (range-normalised), from MetaDrive's shown
    pose of ``j`` against the other vehicles' chassis poses ``boxes`` (x, y, heading per vehicle, in ``vehicles``
    order); and, for the box whose outline lies nearest the point at range-normalised distance ``near`` along the
    beam, that point's distance from its outline (m) and the beam's :func:`ray_box_clearance` with it (m)."""
    v = vehicles[j]
    origin, angle = np.asarray(v.position)[:2], float(v.heading_theta) + 2 * np.pi * beam / config.lidar_beams
    size = (config.vehicle_length, config.vehicle_width)
    others = [k for k in range(len(vehicles)) if k != j]
    hits = [ray_box_distance(origin, angle, boxes[k, :2], float(boxes[k, 2]), *size) for k in others]
    point = origin + _ray(angle)[0] * near * config.lidar_range
    best, outline = -1, np.inf
    if others:
        dist = np.abs(outline_distance(point, boxes[others], *size))
        best, outline = others[int(np.argmin(dist))], float(dist.min())
    clearance = ray_box_clearance(origin, angle, boxes[best, :2], float(boxes[best, 2]), *size) if best >= 0 else np.nan
    return min(1.0, min(hits, default=np.inf) / config.lidar_range), outline, clearance, best


def shadow_episode(
    config: ScenarioConfig, policy: Any, seed: int, steps: int, native_overrides: dict[str, Any] | None = None
) -> dict[str, Any]:
    """Run one MetaDrive episode of ``config`` (its native twin: the same config on the native backend) driven by
    ``policy`` (observations (n, obs_dim) -> actions (n, 2)), and take every step natively too from MetaDrive's state
    before it (:func:`transplant`), with the same actions. Returns per-step and per-vehicle-step comparisons (lists):

    * ``pos_err`` (m), ``heading_err`` (rad), ``speed_err`` (km/h) of vehicles active before and after the step in both;
    * ``<flag>_md`` / ``<flag>_native`` per acting vehicle for each of :data:`FLAGS`, and ``events`` where they differ;
      ``spawned_md`` / ``spawned_native`` per step and ``spawn_events`` where the counts differ;
    * at MetaDrive's poses before the step: ``ego_err``, ``lidar_err`` (per step), ``ego_columns_off`` (per step and
      ego column, the vehicles off by more than 0.01), ``lidar_flips`` (beams off by more than 0.2, per step);
      per such beam ``flip_exact`` (whether the native and whether MetaDrive's value equals exact ray-rectangle
      geometry against the chassis the transplant gave the others) and ``flip_detail`` (the native and MetaDrive
      values; for the box whose outline lies nearest the nearer hit, that distance and :func:`ray_box_clearance`, m;
      whether that box is a vehicle spawned by the previous step; the distance of MetaDrive's hit from the outline of
      a vehicle the previous step retired; whether the observer was spawned by the previous step);
    * ``action_err`` (per vehicle step: the policy on the native observation against its action on MetaDrive's);
    * ``step_lidar_flips`` / ``step_lidar_beams`` (per step, in each simulator's own observations after the step of
      the vehicles that acted: the lidar beams off by more than 0.2, and all);
    * ``steps``: steps taken.

    ``native_overrides``: settings of the native twin that differ (e.g. a rule as it was before a fix)."""
    env = MetaDriveDrivingEnv(replace(config, backend="metadrive"))
    sim = DrivingSimulator(replace(config, backend="native", **(native_overrides or {})), 1)
    ego = sim.cfg.obs_dim - sim.cfg.lidar_beams
    out: dict[str, Any] = collections.defaultdict(list)
    last: dict[str, tuple[np.ndarray, float]] = {}
    prev_ids: set[str] = set()
    gone = np.zeros((0, 3))  # the final poses of the vehicles the last step retired (not left as wrecks)
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
            out["ego_columns_off"].append((ego_err > 0.01).sum(0))
            if ego_err.max() > 0.01:
                j, c = np.unravel_index(np.argmax(ego_err), ego_err.shape)
                out["ego_events"].append((t, ids[j], int(c), float(nat_obs[j, c]), float(md_obs[j, c])))
            lidar_err = np.abs(nat_obs[:, ego:] - md_obs[:, ego:])
            out["lidar_err"].append(lidar_err.mean())
            out["lidar_flips"].append(int((lidar_err > 0.2).sum()))
            vehicles = [env.md.agents[a] for a in ids] + [v for v, _ in env.md.agent_manager._dying_objects.values()]
            for j, b in zip(*np.nonzero(lidar_err > 0.2)):
                nat, mdv = float(nat_obs[j, ego + b]), float(md_obs[j, ego + b])
                exact, outline, clearance, k = _flip(vehicles, sim._chassis_poses(), int(j), int(b), sim.cfg, min(nat, mdv))
                out["flip_exact"].append((abs(exact - nat) < 0.02, abs(exact - mdv) < 0.02))
                v = vehicles[int(j)]
                md_point = (
                    np.asarray(v.position)[:2]
                    + _ray(float(v.heading_theta) + 2 * np.pi * int(b) / sim.cfg.lidar_beams)[0] * mdv * sim.cfg.lidar_range
                )
                to_gone = (
                    np.abs(outline_distance(md_point, gone, sim.cfg.vehicle_length, sim.cfg.vehicle_width)).min() if len(gone) else np.inf
                )
                new_box = 0 <= k < len(ids) and ids[k] not in prev_ids and bool(prev_ids)
                new_eye = ids[int(j)] not in prev_ids
                out["flip_detail"].append((nat, mdv, outline, clearance, float(new_box), float(to_gone), float(new_eye)))
            out["action_err"].extend(np.abs(policy(nat_obs) - act).max(1))
            full = np.zeros((sim.num_slots, 2))
            full[: len(ids)] = act
            speed_before = sim.speed[: len(ids)].copy()
            sim_heading = sim.heading[: len(ids)].copy()
            res = sim.step(full)
            new_obs, _, _, _, infos = env.step(dict(zip(ids, act)))
            final = env.md.coin_final
            both = [j for j, aid in enumerate(ids) if aid in new_obs]  # the step's own observations of the acting vehicles
            if both:
                after = np.stack([new_obs[ids[j]] for j in both])[:, ego:]
                out["step_lidar_flips"].append(int((np.abs(res.obs[both, ego:] - after) > 0.2).sum()))
                out["step_lidar_beams"].append(after.size)
            prev_ids = set(ids)
            retired = [j for j, aid in enumerate(ids) if aid not in env.md.agents]  # their native final poses: ~MetaDrive's
            gone = np.column_stack([sim.pos[retired], sim.heading[retired]]).reshape(-1, 3)
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
