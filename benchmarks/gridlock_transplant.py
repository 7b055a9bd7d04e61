"""A native junction gridlock, carried into MetaDrive: does MetaDrive's closed loop break a jam the native one keeps?

Usage (needs the MetaDrive extra and the COIN authors' actors, see ``python -m coin_app evaluate-reference --help``)::

    python benchmarks/gridlock_transplant.py --actors DIR [--actor-seed 1000] [--env 1] [--at 600] [--steps 400]

1. Runs the authors' intersection actor natively on the reference protocol's batch of episodes (seeds 1000 + 100 i,
   one BLAS thread, as ``evaluate-reference`` runs them) up to env step ``--at`` and prints how many of env
   ``--env``'s vehicles stand still (below 0.5 m/s).
2. Open loop: the actions of the vehicles that stand still over the next 300 steps are applied to one MetaDrive car
   and to the native car from the same start (open ground, as ``coin_app.backends.vehicle_traces`` records its
   manoeuvres): how far apart the two cars end, and how far each drove.
3. Closed loop: every vehicle of that env at step ``--at`` (pose, speed, route and route progress) is put into a fresh
   native simulator and into MetaDrive, and the same actor drives both for ``--steps`` steps; every 50 steps it prints
   how many of those vehicles are still on the road and how many of them stand still, and at the end their outcomes.
   After MetaDrive's first step, its observations are compared with the native simulator's at MetaDrive's poses.
"""

from __future__ import annotations

import argparse
import collections
import time
from typing import Any

import numpy as np
from threadpoolctl import threadpool_limits

from coin_app.backends.metadrive import MetaDriveDrivingEnv
from coin_app.backends.vehicle_traces import Manoeuvre, _open_env, record_scripted
from coin_app.evaluation.reference import episode_seeds, reference_config
from coin_app.inference.coin_actors import actors_root, find_coin_actors, load_coin_actor
from coin_app.sim.config import DynamicsConfig
from coin_app.sim.rollout import BatchedEnvs, rollout
from coin_app.sim.simulator import ACTIVE, DrivingSimulator
from coin_app.sim.vehicle_replay import Traces, replay_windows

STOPPED = 0.5  # m/s
OUTCOMES = ("arrive_dest", "crash_vehicle", "out_of_road")
FIELDS = ("pos", "heading", "speed", "route", "ref_idx", "agent_num")


def native_state(policy: Any, env: int, at: int, episodes: int, open_loop: int) -> tuple[dict[str, np.ndarray], dict[int, list]]:
    """Env ``env``'s vehicles at env step ``at`` of the batched native run, and every vehicle's actions over the next steps."""
    sim = DrivingSimulator(reference_config("intersection", "native"), num_envs=episodes)
    state: dict[str, np.ndarray] = {}
    actions: dict[int, list] = collections.defaultdict(list)
    for step in rollout(BatchedEnvs(sim), policy, episode_seeds(episodes), at + open_loop):
        rows = sim.env_slots(env)
        live = rows[sim.status[rows] == ACTIVE]
        if step.t == at:
            state = {k: getattr(sim, k)[live].copy() for k in FIELDS}
        elif step.t > at:
            for s in live:
                actions[int(sim.agent_num[s])].append(sim.action[s].copy())
    return state, actions


def open_loop(state: dict[str, np.ndarray], actions: dict[int, list], steps: int) -> None:
    """The stopped vehicles' next actions on one MetaDrive car and on the native car, from the same start."""
    stopped = [j for j in range(len(state["speed"])) if state["speed"][j] < STOPPED and len(actions[int(state["agent_num"][j])]) >= steps]
    manoeuvres = [
        Manoeuvre(
            f"agent{int(state['agent_num'][j])}", float(state["speed"][j]) * 3.6, np.array(actions[int(state["agent_num"][j])][:steps])
        )
        for j in stopped[:6]
    ]
    env = _open_env("intersection")
    try:
        recorded = [record_scripted(env, m) for m in manoeuvres]
    finally:
        env.close()
    names, kinds = np.array([m.name for m in manoeuvres]), np.array(["scripted"] * len(manoeuvres))
    acts, states = np.stack([a for a, _ in recorded]), np.stack([s for _, s in recorded])
    traces = Traces(names, kinds, np.full(len(manoeuvres), steps), acts, states)
    windows = replay_windows(DynamicsConfig(), traces, steps)
    for k, m in enumerate(manoeuvres):
        md, nat = windows.recorded[k], windows.native[k]
        path_md = np.linalg.norm(np.diff(md[:, :2], axis=0), axis=1).sum()
        path_nat = np.linalg.norm(np.diff(nat[:, :2], axis=0), axis=1).sum()
        gap = np.linalg.norm(md[-1, :2] - nat[-1, :2])
        drove = f"drove {path_md:5.2f} m in MetaDrive, {path_nat:5.2f} m natively"
        print(f"  {m.name:<8} from {m.speed_kmh:4.1f} km/h: {drove}; {gap:.3f} m apart")


def closed_loop_native(policy: Any, state: dict[str, np.ndarray], steps: int) -> tuple[collections.Counter, list]:
    """The vehicles of ``state`` in a fresh native simulator, driven by ``policy``: outcomes, (on road, stopped) per step."""
    sim = DrivingSimulator(reference_config("intersection", "native"), 1)
    sim.reset(0)
    for s in range(sim.num_slots):
        sim.remove(s)
    for j in range(len(state["pos"])):
        sim.place(j, tuple(state["pos"][j]), float(state["heading"][j]), speed=float(state["speed"][j]), route=int(state["route"][j]))
        sim.ref_idx[j] = state["ref_idx"][j]
    ours = {int(sim.agent_num[j]) for j in range(len(state["pos"]))}
    obs = np.zeros((sim.num_slots, sim.cfg.obs_dim), np.float32)
    outcomes: collections.Counter = collections.Counter()
    history = []
    res = sim.step(np.zeros((sim.num_slots, 2)))  # one coasting step, as in MetaDrive below: every vehicle observes
    for _ in range(steps):
        fresh = res.acted | res.spawned
        obs[fresh] = res.obs[fresh]
        idx = np.nonzero(sim.status == ACTIVE)[0]
        full = np.zeros((sim.num_slots, 2))
        full[idx] = policy(obs[idx])
        res = sim.step(full)
        for s in np.nonzero(res.acted)[0]:
            if int(res.agent_num[s]) in ours:
                outcomes.update(k for k in OUTCOMES if getattr(res, k)[s])
        live = [s for s in np.nonzero(sim.status == ACTIVE)[0] if int(sim.agent_num[s]) in ours]
        history.append((len(live), sum(int(sim.speed[s] < STOPPED) for s in live)))
    return outcomes, history


def closed_loop_metadrive(policy: Any, state: dict[str, np.ndarray], steps: int) -> tuple[collections.Counter, list]:
    """The vehicles of ``state`` put into MetaDrive (pose, speed, route, route progress), driven by ``policy``."""
    from metadrive.component.road_network import Road  # optional: the MetaDrive extra

    env = MetaDriveDrivingEnv(reference_config("intersection", "metadrive"))
    outcomes: collections.Counter = collections.Counter()
    history = []
    try:
        lanes = {v: k for k, v in env.map.lane_index.items()}
        env.reset(seed=0)
        ours = list(env.md.agents)[: len(state["pos"])]
        for j, aid in enumerate(ours):
            vehicle, route = env.md.agents[aid], env.map.routes[int(state["route"][j])]
            heading = float(state["heading"][j])
            vehicle.config["spawn_lane_index"], vehicle.config["destination"] = lanes[route.spawn_lane], route.destination
            vehicle.set_position(tuple(state["pos"][j]))
            vehicle.set_heading_theta(heading)
            vehicle.set_velocity([np.cos(heading), np.sin(heading)], float(state["speed"][j]))
            vehicle.set_angular_velocity(0.0)
            nav = vehicle.navigation
            nav.set_route(lanes[route.spawn_lane], route.destination)
            ck, graph = nav.checkpoints, nav.map.road_network.graph
            i0 = int(state["ref_idx"][j])
            i1 = min(i0 + 1, len(ck) - 2)
            nav._target_checkpoints_index = [i0, i1]
            nav.current_ref_lanes, nav.current_road = graph[ck[i0]][ck[i0 + 1]], Road(ck[i0], ck[i0 + 1])
            nav.next_ref_lanes = graph[ck[i1]][ck[i1 + 1]] if i1 != i0 else None
            nav.next_road = Road(ck[i1], ck[i1 + 1]) if i1 != i0 else None
            nav._last_long_in_ref_lane = nav.current_ref_lanes[0].local_coordinates(vehicle.position)[0]
        obs = env.step({a: np.zeros(2) for a in env.agents})[0]  # one coasting step: every vehicle observes
        observation_parity(env, obs)
        for _ in range(steps):
            acting = list(env.agents)
            actions = policy(np.stack([obs[a] for a in acting])) if acting else np.zeros((0, 2))
            new_obs, _, _, _, infos = env.step(dict(zip(acting, actions)))
            obs.update(new_obs)
            for a in acting:
                if a in ours:
                    outcomes.update(k for k in OUTCOMES if infos[a][k])
            live = [a for a in env.agents if a in ours]
            history.append((len(live), sum(int(env.md.agents[a].speed < STOPPED) for a in live)))
            if env.episode_over:
                break
    finally:
        env.close()
    return outcomes, history


def observation_parity(env: MetaDriveDrivingEnv, obs: dict[str, np.ndarray]) -> None:
    """MetaDrive's observations in the jam against the native simulator's with its vehicles at MetaDrive's poses."""
    sim = DrivingSimulator(reference_config("intersection", "native"), 1)
    sim.reset(0)
    for s in range(sim.num_slots):
        sim.remove(s)
    m, ids = env.map, list(env.md.agents)
    route_of = {(r.spawn_lane, r.destination): k for k, r in enumerate(m.routes)}
    for j, aid in enumerate(ids):
        v = env.md.agents[aid]
        nav = v.navigation
        lane = m.lane_index[tuple(v.config["spawn_lane_index"][:2]) + (int(v.config["spawn_lane_index"][2]),)]
        route = route_of[(lane, nav.checkpoints[-1])]
        sim.place(j, tuple(np.asarray(v.position)[:2]), float(v.heading_theta), speed=float(v.speed), route=route)
        sim.vel[j] = np.asarray(v.velocity)[:2]
        sim.ref_idx[j] = list(m.route_roads[route]).index(m.road_index[(nav.current_road.start_node, nav.current_road.end_node)])
    native = sim.observe(np.arange(len(ids)))[0]
    md = np.stack([obs[a] for a in ids])
    ego = sim.cfg.obs_dim - sim.cfg.lidar_beams
    cols = [c for c in range(ego) if c != 7]  # the yaw rate needs the previous heading
    lidar = np.abs(native[:, ego:] - md[:, ego:])
    print(
        f"observations in the jam ({len(ids)} vehicles at MetaDrive's poses): ego and navigation within "
        f"{np.abs(native[:, cols] - md[:, cols]).max():.4f}; lidar beams off by > 0.01: {(lidar > 0.01).mean():.1%}, "
        f"by > 0.05: {(lidar > 0.05).mean():.1%}, mean |diff| {lidar.mean():.4f}"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--actors", default=None, help="the authors' actors (default: $COIN_OFFICIAL_ACTORS)")
    ap.add_argument("--actor-seed", type=int, default=1000, help="training seed of the intersection actor")
    ap.add_argument("--episodes", type=int, default=5, help="episodes of the batch (the reference protocol's 5)")
    ap.add_argument("--env", type=int, default=1, help="the batch's episode to take the gridlock from (1: seed 1100)")
    ap.add_argument("--at", type=int, default=600, help="env step of the state carried over")
    ap.add_argument("--steps", type=int, default=400, help="closed-loop steps in each simulator")
    ap.add_argument("--open-loop", type=int, default=300, help="steps of the open-loop replay of the stopped vehicles' actions")
    args = ap.parse_args()
    policy = load_coin_actor(find_coin_actors(actors_root(args.actors), "intersection")[args.actor_seed])
    start = time.perf_counter()
    with threadpool_limits(limits=1, user_api="blas"):
        state, actions = native_state(policy, args.env, args.at, args.episodes, args.open_loop)
        n, stopped = len(state["speed"]), int((state["speed"] < STOPPED).sum())
        where = f"actor {args.actor_seed}, episode seed {episode_seeds(args.episodes)[args.env]} at step {args.at}"
        print(f"native, {where}: {n} vehicles, {stopped} stopped")
        print(f"open loop, {args.open_loop} steps of the stopped vehicles' own actions:")
        open_loop(state, actions, args.open_loop)
        for name, run in (("native", closed_loop_native), ("MetaDrive", closed_loop_metadrive)):
            outcomes, history = run(policy, state, args.steps)
            shown = ", ".join(f"{a}/{b}" for a, b in history[49::50])
            print(f"closed loop, {name}: on the road / stopped every 50 steps: {shown}; outcomes {dict(outcomes)}")
    print(f"wall {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()
