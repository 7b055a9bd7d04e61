"""Heuristic driver: pure pursuit along the route's lane centre lines plus gap keeping.

Every route gets a reference path: the shortest chain of physically connected lanes from
the spawn lane to the final road, with lane changes across broken lines allowed and
lanes tighter than the car can turn (radius < ``min_radius``) left out -- so a U-turn
from the inner lane first changes to the outer lane. The controller is vectorized over
all acting vehicles: steering from pure pursuit, throttle / brake from a target speed
limited by the path's curvature ahead and by the nearest vehicle in the lane ahead.
"""

from __future__ import annotations

import heapq
from functools import cache

import numpy as np

from coin_app.sim import schema
from coin_app.sim.config import make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.road_map import RoadMap, load_map
from coin_app.sim.rollout import BatchedEnvs, rollout
from coin_app.sim.simulator import ACTIVE, DrivingSimulator

LANE_CHANGE_COST = 15.0  # metres of detour charged per lane change
EXTENSION = 40.0  # metres of straight path appended past the final lane's end
PROGRESS_WINDOW = 20  # path points searched ahead of the last progress each step
CURVE_LOOKAHEAD = 40.0  # metres of path scanned for curvature when choosing the speed
GAP_RANGE = 40.0  # metres within which a vehicle ahead limits the speed
OUTCOME_PRIORITY = (schema.ARRIVE_DEST, schema.OUT_OF_ROAD, schema.CRASH_VEHICLE, schema.MAX_STEP)  # MetaDrive's terminal priority


def _lane_graph(m: RoadMap, min_radius: float) -> dict[int, list[tuple[int, float, bool]]]:
    """Edges lane -> (next lane, cost, is_lane_change) of the drivable lane graph."""
    succ = m.successors()
    ok = ~m.is_circ | (m.radius >= min_radius)
    edges: dict[int, list[tuple[int, float, bool]]] = {i: [] for i in range(m.num_lanes)}
    for i in range(m.num_lanes):
        if not ok[i]:
            continue
        edges[i] += [(j, float(m.length[i]), False) for j in succ[i] if ok[j]]
        road, k = m.lane_road[i], m.lane_keys[i][2]
        for dk in (-1, 1):
            kk = k + dk
            if 0 <= kk < m.road_nlanes[road] and not m.is_circ[i]:
                j = int(m.road_lanes[road, kk])
                if ok[j]:
                    edges[i].append((j, LANE_CHANGE_COST, True))
    return edges


def _lane_points(m: RoadMap, lane: int, s0: float, s1: float) -> np.ndarray:
    """Centre-line points of ``lane`` every metre for s in [s0, s1]."""
    s = np.arange(s0, s1 + 1e-9, 1.0)
    if len(s) == 0:
        return np.zeros((0, schema.ACT_DIM))
    return m.position(np.full(len(s), lane), s, np.zeros(len(s)))


@cache
def route_paths(name: str, min_radius: float = 4.0) -> tuple[np.ndarray, ...]:
    """Reference polylines of every route of map ``name`` (cached)."""
    m = load_map(name)
    return tuple(route_path(m, i, min_radius) for i in range(len(m.routes)))


def route_path(m: RoadMap, route: int, min_radius: float = 4.0) -> np.ndarray:
    """Reference polyline (K, 2), 1 m spacing, from the route's spawn lane to past its end."""
    r = m.routes[route]
    final_road = r.roads[-1]
    edges = _lane_graph(m, min_radius)
    dist = {r.spawn_lane: 0.0}
    prev: dict[int, tuple[int, bool]] = {}
    heap = [(0.0, r.spawn_lane)]
    goal = -1
    while heap:
        d, lane = heapq.heappop(heap)
        if d > dist.get(lane, np.inf):
            continue
        if m.lane_road[lane] == final_road:
            goal = lane
            break
        for nxt, cost, change in edges[lane]:
            nd = d + cost
            if nd < dist.get(nxt, np.inf):
                dist[nxt] = nd
                prev[nxt] = (lane, change)
                heapq.heappush(heap, (nd, nxt))
    if goal < 0:
        raise RuntimeError(f"no drivable lane path for route {route} on {m.name}")
    chain = []  # (lane, entered by a lane change), goal first
    lane = goal
    while lane != r.spawn_lane:
        pred, change = prev[lane]
        chain.append((lane, change))
        lane = pred
    chain.append((r.spawn_lane, False))
    chain.reverse()
    pieces = []
    for n, (lane, _) in enumerate(chain):
        length = float(m.length[lane])
        s0 = 0.0
        s1 = length
        if n > 0 and chain[n][1]:  # reached by a lane change: start mid-lane
            s0 = min(length, length / 2 + 6.0)
        if n + 1 < len(chain) and chain[n + 1][1]:  # leaving by a lane change
            s1 = max(0.0, length / 2 - 6.0)
        pieces.append(_lane_points(m, lane, s0, s1))
    pts = np.concatenate([p for p in pieces if len(p)])
    # resample by arc length at 1 m: lane changes become straight 12 m diagonals
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
    grid = np.arange(0.0, arc[-1] + 1e-9, 1.0)
    pts = np.stack([np.interp(grid, arc, pts[:, 0]), np.interp(grid, arc, pts[:, 1])], 1)
    end_h = m.heading_at(np.array([goal]), np.array([m.length[goal]]))[0]
    ext = pts[-1] + np.arange(1, EXTENSION + 1)[:, None] * np.array([np.cos(end_h), np.sin(end_h)])
    return np.concatenate([pts, ext])


class HeuristicDriver:
    """Route-following driver for every agent of a :class:`DrivingEnv` or simulator (privileged state).

    Called on a batch of observations it is a :data:`~coin_app.sim.rollout.Policy` for
    :func:`~coin_app.sim.rollout.rollout`: it ignores the observations and drives the acting
    vehicles of its own simulator. Its actions are float32 (the env's action space) when it
    drives a :class:`DrivingEnv`, float64 on a bare simulator.
    """

    def __init__(
        self,
        env: DrivingEnv | DrivingSimulator,
        cruise_speed: float = 10.0,
        lateral_accel: float = 1.5,
        time_gap: float = 1.2,
        min_gap: float = 3.0,
        look_gain: float = 0.4,
        look_min: float = 3.0,
    ):
        self.env = env if isinstance(env, DrivingEnv) else None
        self.sim = env.sim if isinstance(env, DrivingEnv) else env
        self.dtype = env.action_space.dtype if isinstance(env, DrivingEnv) else np.dtype(np.float64)
        m = self.sim.map
        paths = route_paths(m.name)
        k = max(len(p) for p in paths)
        self.paths = np.stack([np.concatenate([p, np.repeat(p[-1:], k - len(p), 0)]) for p in paths])
        self.path_len = np.array([len(p) for p in paths])
        head = np.arctan2(np.diff(self.paths[..., 1], axis=1), np.diff(self.paths[..., 0], axis=1))
        curv = np.abs(np.angle(np.exp(1j * np.diff(head, axis=1))))  # rad per metre
        self.curvature = np.pad(curv, ((0, 0), (1, 1)))
        self.cruise_speed = cruise_speed
        self.lateral_accel = lateral_accel
        self.time_gap = time_gap
        self.min_gap = min_gap
        self.look_gain = look_gain
        self.look_min = look_min
        self.progress = np.zeros(self.sim.num_slots, dtype=np.int64)
        self._owner = np.full(self.sim.num_slots, -1, dtype=np.int64)

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, 2) of the N acting vehicles in slot order (the rows of a rollout's observation batch)."""
        active = np.nonzero(self.sim.status == ACTIVE)[0]
        if len(obs) != len(active):
            raise ValueError(f"the heuristic driver drives the {len(active)} acting vehicles of its simulator; got {len(obs)} observations")
        return self.act_slots(active).astype(self.dtype)

    def actions(self) -> dict[str, np.ndarray]:
        """Actions for every agent that acts next in the wrapped :class:`DrivingEnv`."""
        if self.env is None:
            raise TypeError("actions() needs a DrivingEnv; use act_slots() with a bare simulator")
        slots = np.array([self.env.agent_slot(a) for a in self.env.agents], dtype=np.int64)
        if len(slots) == 0:
            return {}
        acts = self.act_slots(slots).astype(np.float32)
        return {a: acts[i] for i, a in enumerate(self.env.agents)}

    def act_all(self) -> np.ndarray:
        """Actions (num_slots, 2) for every slot of the simulator (zeros where nobody acts)."""
        out = np.zeros((self.sim.num_slots, schema.ACT_DIM))
        active = np.nonzero(self.sim.status == ACTIVE)[0]
        if len(active):
            out[active] = self.act_slots(active)
        return out

    def act_slots(self, slots: np.ndarray) -> np.ndarray:
        """Actions (n, 2) of the vehicles in ``slots``."""
        sim = self.sim
        dyn = sim.cfg.dynamics
        new = self._owner[slots] != sim.agent_num[slots]
        self._owner[slots] = sim.agent_num[slots]
        route = sim.route[slots]
        paths = self.paths[route]  # (n, K, 2)
        pos, hd, v = sim.pos[slots], sim.heading[slots], sim.speed[slots]
        n, k = len(slots), paths.shape[1]
        rows = np.arange(n)
        # progress along the path: global nearest point for new agents, else a window ahead
        prog = self.progress[slots].copy()
        if new.any():
            d_new = np.linalg.norm(paths[new] - pos[new][:, None, :], axis=2)
            d_new[np.arange(k)[None, :] >= self.path_len[route[new]][:, None]] = np.inf
            prog[new] = d_new.argmin(1)
        win = np.minimum(prog[:, None] + np.arange(PROGRESS_WINDOW)[None, :], k - 1)
        pts = paths[rows[:, None], win]
        prog = win[rows, np.hypot(pts[..., 0] - pos[:, 0:1], pts[..., 1] - pos[:, 1:2]).argmin(1)]
        self.progress[slots] = prog
        # pure pursuit steering
        look = np.clip(self.look_gain * v + self.look_min, self.look_min, 15.0)
        tgt_i = np.minimum(prog + np.round(look).astype(np.int64), k - 1)
        tgt = paths[rows, tgt_i]
        d = tgt - pos
        c, s = np.cos(hd), np.sin(hd)
        x_l = d[:, 0] * c + d[:, 1] * s
        y_l = -d[:, 0] * s + d[:, 1] * c
        dist = np.maximum(np.hypot(x_l, y_l), 1e-6)
        kappa = 2.0 * y_l / dist**2
        if dyn.curvature_per_steer is None:
            steer = np.arctan(kappa * dyn.wheelbase) / np.deg2rad(dyn.max_steer_deg)
        else:
            steer = kappa / dyn.curvature_per_steer
        # target speed: curvature ahead, then gap to the nearest body in the corridor ahead
        horizon = np.clip(v**2 / 4.0 + 12.0, 12.0, CURVE_LOOKAHEAD)
        ahead = np.arange(int(CURVE_LOOKAHEAD) + 1)[None, :]
        idx_ahead = np.minimum(prog[:, None] + ahead, k - 1)
        curv = np.where(ahead <= horizon[:, None], self.curvature[route[:, None], idx_ahead], 0.0).max(1)
        v_target = np.minimum(self.cruise_speed, np.sqrt(self.lateral_accel / np.maximum(curv, 1e-6)))
        observer = np.zeros(sim.num_slots, bool)
        observer[slots] = True
        row_of = np.full(sim.num_slots, -1)
        row_of[slots] = rows
        po, pb = sim._same_env_pairs(GAP_RANGE, observers=observer)
        i = row_of[po]
        rel = sim.pos[pb] - pos[i]
        fx = rel[:, 0] * c[i] + rel[:, 1] * s[i]
        fy = -rel[:, 0] * s[i] + rel[:, 1] * c[i]
        corridor = (fx > 0.5) & (np.abs(fy) < 2.4)
        gap = np.full(n, np.inf)
        np.minimum.at(gap, i[corridor], fx[corridor] - 2 * sim.half[0])
        v_gap = np.maximum(gap - self.min_gap, 0.0) / self.time_gap
        v_target = np.minimum(v_target, v_gap)
        throttle = np.clip(0.5 * (v_target - v), -1.0, 1.0)
        throttle = np.where((v_target < 0.1) & (v < 0.5), -0.3, throttle)
        return np.clip(np.stack([steer, throttle], 1), -1.0, 1.0)


def single_vehicle_outcomes(scenario: str, seeds: list[int], max_steps: int = 800) -> list[str]:
    """Outcome of one heuristic vehicle alone on the map for each seeded spawn.

    The spawns run as a batch of independent one-vehicle envs (env ``e`` is exactly a
    single env reset with ``seeds[e]``); outcomes are ``arrive_dest``, ``crash_vehicle``,
    ``out_of_road``, ``max_step`` or ``running``.
    """
    envs = BatchedEnvs(DrivingSimulator(make_config(scenario, num_agents=1, allow_respawn=False), num_envs=len(seeds)))
    outcome = ["running"] * len(seeds)
    for step in rollout(envs, HeuristicDriver(envs.sim), seeds, max_steps):
        for e, result in step.results.items():
            for aid, terminated in result.terminateds.items():
                if terminated or result.truncateds[aid]:
                    outcome[e] = next((key for key in OUTCOME_PRIORITY if result.infos[aid][key]), outcome[e])
    return outcome


__all__ = ["HeuristicDriver", "route_path", "single_vehicle_outcomes"]
