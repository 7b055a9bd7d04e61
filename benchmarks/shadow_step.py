"""Shadow steps: every step of a MetaDrive episode, repeated by the native simulator from MetaDrive's own state.

Usage (needs the MetaDrive extra and the COIN authors' actors, see ``python -m coin_app evaluate-reference --help``)::

    python benchmarks/shadow_step.py --actors DIR [--scene intersection] [--actor-seed 1000] [--seed 1000] [--steps 1000]

The authors' actor drives one MetaDrive episode of the reference protocol (``evaluate-reference``'s scenario and
episode seed). Before every step, every vehicle MetaDrive holds — active ones with their chassis state, route, route
progress and step count, wrecks with their countdown — is put into a native simulator; both simulators then take the
step with the same actions (the actor's, on MetaDrive's observations). Closed-loop episodes of the two simulators part
within seconds (the traffic is chaotic), so comparing whole episodes says little about where they differ; one step
from one state says it exactly. Printed at the end:

* poses after the step: position, heading and speed error over the vehicles active before and after it in both;
* outcomes: per flag (arrival, crash, off-road, step limit), how often MetaDrive and the native step disagree, and
  each disagreement (step, agent, speed, what each said);
* respawns: vehicles spawned by the step in each (the places are drawn by different generators, the count should agree);
* observations at MetaDrive's poses before the step: ego and navigation error, lidar error, and how far the actor's
  action on the native observation is from its action on MetaDrive's.
"""

from __future__ import annotations

import argparse
import collections
import time
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from coin_app.backends.metadrive import MetaDriveDrivingEnv
from coin_app.backends.vehicle_traces import _state
from coin_app.evaluation.reference import reference_config
from coin_app.inference.coin_actors import actors_root, find_coin_actors, load_coin_actor
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


def shadow_episode(scene: str, policy: Any, seed: int, steps: int) -> dict[str, Any]:
    """Run one MetaDrive episode and shadow every step natively; the collected comparisons."""
    env = MetaDriveDrivingEnv(reference_config(scene, "metadrive"))
    sim = DrivingSimulator(reference_config(scene, "native"), 1)
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


def summary(out: dict[str, Any]) -> None:
    """Print the comparisons (module doc)."""
    pos, hd, sp = (np.array(out[k]) for k in ("pos_err", "heading_err", "speed_err"))
    q = [50, 99, 100]
    print(f"{out['steps']} steps shadowed, {len(pos)} vehicle steps active in both before and after")
    print(f"  position error (m) median / p99 / max: {' / '.join(f'{v:.4f}' for v in np.percentile(pos, q))}")
    print(f"  heading error (deg): {' / '.join(f'{v:.4f}' for v in np.degrees(np.percentile(hd, q)))}")
    print(f"  speed error (km/h): {' / '.join(f'{v:.4f}' for v in np.percentile(sp, q))}")
    for flag in FLAGS:
        a, b = np.array(out[f"{flag}_md"]), np.array(out[f"{flag}_native"])
        print(f"  {flag:<13} MetaDrive {int(a.sum()):4d}, native {int(b.sum()):4d}, both {int((a & b).sum()):4d}")
    for t, aid, flag, a, b, v in out["events"]:
        print(f"    step {t:4d} {aid:<9} {flag:<13} MetaDrive {a!s:<5} native {b!s:<5} at {v:5.1f} km/h")
    smd, snat = np.array(out["spawned_md"]), np.array(out["spawned_native"])
    print(f"  respawns: MetaDrive {int(smd.sum())}, native {int(snat.sum())}, steps where the counts differ: {int((smd != snat).sum())}")
    for t, md_new, nat_new, live in out["spawn_events"]:
        print(f"    step {t:4d}: MetaDrive spawned at {md_new}, native at {nat_new} (MetaDrive active + dying after: {live})")
    ego, lid, act = (np.array(out[k]) for k in ("ego_err", "lidar_err", "action_err"))
    flips = np.array(out["lidar_flips"]).sum() / len(act)
    print(
        f"  observations: ego and navigation max error {ego.max():.4f}; lidar mean error per step median {np.median(lid):.4f}, "
        f"max {lid.max():.4f}; beams off by more than 0.2 (a grazed box seen by one simulator only): {flips:.3f} per vehicle step"
    )
    for t, aid, c, a, b in out["ego_events"][:20]:
        print(f"    step {t:4d} {aid:<9} column {c:2d}: native {a:.4f}, MetaDrive {b:.4f}")
    print(
        f"  the actor's action on the native observation against MetaDrive's, per vehicle step: median {np.median(act):.4f}, "
        f"p90 {np.percentile(act, 90):.4f}, p99 {np.percentile(act, 99):.4f}, max {act.max():.4f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actors", default=None, help="the authors' actors (default: $COIN_OFFICIAL_ACTORS)")
    ap.add_argument("--scene", default="intersection", choices=("intersection", "roundabout", "bottleneck"))
    ap.add_argument("--actor-seed", type=int, default=1000, help="training seed of the actor")
    ap.add_argument("--seed", type=int, default=1000, help="episode seed (the reference protocol's: 1000 + 100 i)")
    ap.add_argument("--steps", type=int, default=1000, help="steps to shadow (the episode's horizon: 1000)")
    args = ap.parse_args()
    policy = load_coin_actor(find_coin_actors(actors_root(args.actors), args.scene)[args.actor_seed])
    start = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        out = shadow_episode(args.scene, policy, args.seed, args.steps)
    summary(out)
    print(f"wall {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
