"""Record MetaDrive vehicle traces for open-loop replay in the native simulator (issue 21).

Usage (needs the MetaDrive extra)::

    python -m coin_app.backends.vehicle_traces --out coin_app/sim/maps/metadrive_traces.npz

Two kinds of trace, each a sequence of actions with MetaDrive's state before and after every
env step (``decision_repeat`` 5 physics steps of 0.02 s = 0.1 s):

* **Scripted manoeuvres** on open ground (the car is put at (300, 300), away from every road,
  sidewalk and vehicle, with ``out_of_road_done`` off): full and half steering lock at 20, 30 and
  40 km/h while coasting and at part throttle, both directions; braking in a turn; a lane change
  at speed; straight acceleration and braking; seeded smooth random actions. Each starts from
  straight driving at its speed (MetaDrive's own ``set_velocity``), so its initial state is
  exactly what the native simulator can represent (no yaw rate, no sideslip): the car first rests
  ``SETTLE_STEPS`` on its suspension, then gets its speed from MetaDrive's own ``set_velocity``.
* **The heuristic driver's routes** through each map, one vehicle alone: a native shadow vehicle
  is put on MetaDrive's pose every step (the same route and route progress), and
  :class:`~coin_app.sim.heuristic.HeuristicDriver` acts for it. These traces are closed loop in
  MetaDrive; their replay is open loop from windows along the route.

The output is one ``.npz``: ``names`` (k,), ``kinds`` (k,), ``lengths`` (k,), and per trace
``actions`` (k, T, 2) and ``states`` (k, T + 1, 14) padded with NaN, a state being
``STATE_COLUMNS``: ``[x, y, heading, speed m/s, yaw rate rad/s, lateral velocity m/s]`` (the
lateral velocity to the car's left), then the rest of Bullet's chassis state: height, the world
velocity (3), the roll and pitch rates (world x, y) and the z components of the chassis' forward
and right axes. :mod:`coin_app.sim.vehicle_replay` reads and replays it.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from coin_app.backends.metadrive import _env_class
from coin_app.sim.config import make_config
from coin_app.sim.heuristic import HeuristicDriver
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.simulator import DrivingSimulator

OPEN_GROUND = (300.0, 300.0)  # far from every road of the three maps (their extents are within +-150 m)
# the first six are what the native simulator represents; the rest complete the chassis state of Bullet's vehicle
STATE_COLUMNS = (
    "x", "y", "heading", "speed", "yaw_rate", "lateral_velocity",
    "z", "vx", "vy", "vz", "wx", "wy", "forward_z", "right_z",
)  # fmt: skip
SETTLE_STEPS = 30  # steps at rest on open ground before a scripted manoeuvre: the suspension settles (3 s)
SCRIPT_STEPS = 40  # 4 s of every scripted manoeuvre


@dataclass(frozen=True)
class Manoeuvre:
    """A scripted manoeuvre: initial speed (km/h) and the actions of each of its steps."""

    name: str
    speed_kmh: float
    actions: np.ndarray  # (T, 2): [steering, throttle_brake]


def scripted_manoeuvres(steps: int = SCRIPT_STEPS, seed: int = 0) -> list[Manoeuvre]:
    """The scripted manoeuvres (module doc), in a fixed order."""
    out: list[Manoeuvre] = []

    def const(steer: float, pedal: float) -> np.ndarray:
        return np.tile([steer, pedal], (steps, 1)).astype(float)

    for speed in (20.0, 30.0, 40.0):
        for steer, side in ((1.0, "left"), (-1.0, "right"), (0.5, "left"), (-0.5, "right")):
            lock = "full" if abs(steer) == 1.0 else "half"
            for pedal, what in ((0.0, "coast"), (0.3, "throttle0.3")):
                out.append(Manoeuvre(f"{lock}_lock_{side}_{int(speed)}kmh_{what}", speed, const(steer, pedal)))
        out.append(Manoeuvre(f"brake_in_turn_{int(speed)}kmh", speed, const(0.5, -0.5)))
        t = np.arange(steps) * 0.1
        change = np.where(t < 2.0, 0.25 * np.sin(np.pi * t), 0.0)  # one full sine period of steering: a lane change
        out.append(Manoeuvre(f"lane_change_{int(speed)}kmh", speed, np.stack([change, np.full(steps, 0.2)], 1)))
    out.append(Manoeuvre("accelerate_from_rest", 0.0, const(0.0, 1.0)))
    out.append(Manoeuvre("brake_from_40kmh", 40.0, const(0.0, -1.0)))
    out.append(Manoeuvre("half_brake_from_40kmh", 40.0, const(0.0, -0.5)))
    rng = np.random.default_rng(seed)
    for k in range(4):
        raw = rng.uniform(-1.0, 1.0, size=(steps + 4, 2))
        smooth = np.stack([np.convolve(raw[:, j], np.ones(5) / 5, mode="valid") for j in range(2)], 1)[:steps]
        smooth[:, 0] *= 1.5  # steering up to about full lock
        out.append(Manoeuvre(f"random_{k}_30kmh", 30.0, np.clip(smooth, -1.0, 1.0)))
    return out


def _state(vehicle: Any) -> np.ndarray:
    """``STATE_COLUMNS`` of one MetaDrive vehicle (velocities in the world frame; ``forward_z``, ``right_z``: the chassis tilt)."""
    lin = np.asarray(vehicle.body.getLinearVelocity(), float)
    ang = np.asarray(vehicle.body.getAngularVelocity(), float)
    h = float(vehicle.heading_theta)
    lateral = -math.sin(h) * lin[0] + math.cos(h) * lin[1]
    x, y = np.asarray(vehicle.position, float)[:2]
    quat = vehicle.origin.getQuat()
    tilt = [float(quat.getForward()[2]), float(quat.getRight()[2])]
    return np.array([x, y, h, float(vehicle.speed), ang[2], lateral, float(vehicle.origin.getZ()), *lin, ang[0], ang[1], *tilt])


def _open_env(scenario: str) -> Any:
    """A one-vehicle MetaDrive env of ``scenario`` that does not end an episode off the road or in a crash."""
    env_class = _env_class(scenario, "skip")  # the backend's class: spawns seeded by coin_seed
    env = env_class(
        {
            "num_agents": 1,
            "use_render": False,
            "log_level": logging.CRITICAL,
            "out_of_road_done": False,
            "crash_done": False,
            "horizon": 5000,
            "delay_done": 0,
            "allow_respawn": False,
            "start_seed": 0,
            "num_scenarios": 1,
        }
    )
    env.coin_state_fn = lambda vehicle: None  # the backend's hook records final states; not needed here
    return env


def record_scripted(env: Any, manoeuvre: Manoeuvre) -> tuple[np.ndarray, np.ndarray]:
    """(actions (T, 2), states (T + 1, 6)) of one scripted manoeuvre on open ground."""
    env.reset(seed=0)
    aid = next(iter(env.agents))
    vehicle = env.agents[aid]
    vehicle.set_position(OPEN_GROUND)
    vehicle.set_heading_theta(0.0)
    vehicle.set_velocity((1.0, 0.0), 0.0)
    vehicle.set_angular_velocity(0.0)
    for _ in range(SETTLE_STEPS):  # at rest on its suspension, as a car driving straight at a steady speed would be
        env.step({aid: [0.0, 0.0]})
    vehicle.set_velocity((1.0, 0.0), manoeuvre.speed_kmh / 3.6)
    states = [_state(vehicle)]
    for action in manoeuvre.actions:
        env.step({aid: [float(action[0]), float(action[1])]})
        states.append(_state(vehicle))
    return manoeuvre.actions.copy(), np.stack(states)


def record_route(env: Any, scenario: str, seed: int, max_steps: int = 600) -> tuple[np.ndarray, np.ndarray]:
    """(actions, states) of the heuristic driver alone on ``scenario`` from MetaDrive's spawn for ``seed``, until it arrives."""
    env.coin_seed = seed
    env.reset(seed=0)
    aid = next(iter(env.agents))
    vehicle = env.agents[aid]
    sim = DrivingSimulator(make_config(scenario, num_agents=1, allow_respawn=False))
    sim.reset(0)
    m = sim.map
    route_of = {(r.spawn_lane, r.destination): k for k, r in enumerate(m.routes)}
    nav = vehicle.navigation
    lane = m.lane_index[tuple(vehicle.config["spawn_lane_index"][:2]) + (int(vehicle.config["spawn_lane_index"][2]),)]
    route = route_of[(lane, nav.checkpoints[-1])]
    driver = HeuristicDriver(sim)
    states, actions = [_state(vehicle)], []
    for _ in range(max_steps):
        x, y, h, v = states[-1][:4]
        sim.place(0, (x, y), h, speed=v, route=route)
        sim.yaw_rate[0] = states[-1][4]
        road = m.road_index[(nav.current_road.start_node, nav.current_road.end_node)]
        sim.ref_idx[0] = list(m.route_roads[route]).index(road)
        action = np.asarray(driver.act_slots(np.array([0]))[0], float)
        _, _, terminated, truncated, info = env.step({aid: [float(action[0]), float(action[1])]})
        actions.append(action)
        states.append(_state(vehicle))
        if info.get(aid, {}).get("arrive_dest") or terminated.get(aid) or truncated.get(aid):
            break
    return np.stack(actions), np.stack(states)


def record_all(route_seeds: int = 3) -> dict[str, Any]:
    """Every scripted manoeuvre, and ``route_seeds`` heuristic routes per map, as the arrays of the ``.npz``."""
    names, kinds, traces = [], [], []
    env = _open_env("intersection")
    try:
        for man in scripted_manoeuvres():
            traces.append(record_scripted(env, man))
            names.append(man.name)
            kinds.append("scripted")
            print(f"  {man.name}: {len(man.actions)} steps", flush=True)
    finally:
        env.close()
    for scenario in DRIVING_SCENARIOS:
        env = _open_env(scenario)
        try:
            for seed in range(route_seeds):
                acts, sts = record_route(env, scenario, seed)
                traces.append((acts, sts))
                names.append(f"heuristic_{scenario}_seed{seed}")
                kinds.append("route")
                print(f"  heuristic on {scenario}, seed {seed}: {len(acts)} steps", flush=True)
        finally:
            env.close()
    horizon = max(len(a) for a, _ in traces)
    actions = np.full((len(traces), horizon, 2), np.nan)
    states = np.full((len(traces), horizon + 1, len(STATE_COLUMNS)), np.nan)
    for k, (a, s) in enumerate(traces):
        actions[k, : len(a)] = a
        states[k, : len(s)] = s
    return {
        "names": np.array(names),
        "kinds": np.array(kinds),
        "lengths": np.array([len(a) for a, _ in traces]),
        "actions": actions.astype(np.float32),
        "states": states,
        "state_columns": np.array(STATE_COLUMNS),
    }


def main(argv: list[str] | None = None) -> int:
    """Record the traces to ``--out`` and print a summary."""
    ap = argparse.ArgumentParser(description="Record MetaDrive vehicle traces for open-loop replay (coin_app.sim.vehicle_replay)")
    ap.add_argument("--out", default="coin_app/sim/maps/metadrive_traces.npz", help="output .npz")
    ap.add_argument("--route-seeds", type=int, default=3, help="heuristic routes recorded per map")
    args = ap.parse_args(argv)
    if args.route_seeds < 0:
        raise SystemExit(f"error: bad --route-seeds {args.route_seeds}; allowed: an integer >= 0")
    t0 = time.perf_counter()
    print("recording MetaDrive traces (metadrive-simulator, physics only)")
    data = record_all(args.route_seeds)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **data)
    summary = {"traces": len(data["names"]), "steps": int(data["lengths"].sum()), "file": str(out), "bytes": out.stat().st_size}
    print(f"summary: {json.dumps(summary)} in {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
