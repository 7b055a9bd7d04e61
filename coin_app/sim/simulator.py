"""The vectorized multi-vehicle simulator core: ``num_envs`` copies of one scenario.

State lives in flat per-slot numpy arrays; env ``e`` owns slots ``e*S .. e*S+S-1``. A slot
is EMPTY, ACTIVE (an agent that acts) or DYING (a crashed / off-road / timed-out vehicle
left as a static obstacle for ``delay_done`` steps). Every per-vehicle computation in
:meth:`DrivingSimulator.step` is one numpy call or one compiled kernel (``docs/decisions.md`` §3.6)
over all slots of all envs; pairwise tests only pair vehicles of the same env. The only
Python loops run over respawn *events*. Each env has its own random generator, so env
``e`` of a batch reproduces a single env seeded the same way.

Step order (as MetaDrive): clip actions -> dynamics -> lane localisation and reference
road update -> arrival / out-of-road / crash tests -> rewards (the rules: ``rules.py``) ->
observations of every agent that acted -> retire done vehicles -> respawn -> observations of the new agents. So, as in
MetaDrive (whose ``step`` observes before its ``_after_vehicle_done`` and respawn), the observation after a step sees the
vehicles that arrived in it at their final poses and not the ones spawned by it; a new agent's first observation sees
the traffic after both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from coin_app.sim import rules, schema
from coin_app.sim.collision import footprint_in_polygons, places_blocked, same_env_overlaps, touches_boxes
from coin_app.sim.config import PHYSICS_DT, ScenarioConfig
from coin_app.sim.dynamics import bicycle_step, wrap_angle
from coin_app.sim.road_map import GridIndex, load_map, localize
from coin_app.sim.scenes import scene
from coin_app.sim.sensors import ego_features, lidar_same_env, line_detector, local_state
from coin_app.sim.vehicle import RaycastVehicles

EMPTY, ACTIVE, DYING = 0, 1, 2
CKPT_UPDATE_RANGE = 5.0  # m: the reference road switches within this s on the next road
MAX_RESPAWN_PER_STEP = 8  # one per respawn place


def _f64(a: np.ndarray) -> np.ndarray:
    """``a`` as a contiguous float64 array (what the kernels take)."""
    return np.ascontiguousarray(a, dtype=np.float64)


def agent_name(num: int) -> str:
    """The string id of the ``num``-th vehicle of an episode."""
    return f"agent{num}"


@dataclass
class StepResult:
    """Per-slot outcome of one step (flat over envs); rows of slots that did not act are zero."""

    acted: np.ndarray  # bool (N,): the slot's agent acted this step
    spawned: np.ndarray  # bool (N,): a new agent appeared in the slot this step
    agent_num: np.ndarray  # int (N,): agent number that acted (or spawned) in the slot
    obs: np.ndarray  # (N, obs_dim) float32
    state: np.ndarray  # (N, 10) float32 local world-frame state
    reward: np.ndarray  # (N,)
    arrive_dest: np.ndarray
    crash_vehicle: np.ndarray
    out_of_road: np.ndarray
    max_step: np.ndarray
    terminated: np.ndarray
    truncated: np.ndarray
    episode_length: np.ndarray  # the agent's own steps so far
    global_reward: np.ndarray  # (E,) mean reward over the agents that acted in each env
    episode_over: np.ndarray  # bool (E,): no active agent is left after respawn (docs/reference/deviations.md)
    env_step: np.ndarray  # (E,) env steps taken in the current episode


class DrivingSimulator:
    """All vehicles of ``num_envs`` independent instances of one scenario, stepped together."""

    def __init__(self, config: ScenarioConfig, num_envs: int = 1):
        if not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"bad num_envs {num_envs!r}; allowed: an integer >= 1")
        if config.backend != "native":
            raise ValueError(
                f"the native simulator cannot run backend {config.backend!r}; "
                "use coin_app.sim.driving_env.make_driving_env(config) (or backend='native')"
            )
        self.cfg = config
        self.map = load_map(config.scenario, config.solid_center_line)
        m = self.map
        self.num_envs = num_envs
        # spare slots so that a slot vacated in a step is never refilled in the same step
        self.slots_per_env = config.num_agents + MAX_RESPAWN_PER_STEP
        self.num_slots = self.slots_per_env * num_envs
        self.env_of = np.repeat(np.arange(num_envs), self.slots_per_env)
        self.half = np.array([config.vehicle_length / 2, config.vehicle_width / 2])
        self.half_diag = float(np.hypot(*self.half))
        self.scene = scene(config.scenario)
        seg = m.solid_p2 - m.solid_p1
        self.seg_center = 0.5 * (m.solid_p1 + m.solid_p2)
        self.seg_heading = np.arctan2(seg[:, 1], seg[:, 0])
        self.seg_half = np.stack([0.5 * np.hypot(seg[:, 0], seg[:, 1]), np.full(len(seg), m.solid_half_width)], 1)
        seg_bbox = np.concatenate([np.minimum(m.solid_p1, m.solid_p2), np.maximum(m.solid_p1, m.solid_p2)], 1)
        self.seg_grid = GridIndex(seg_bbox, reach=self.half_diag + m.solid_half_width + 0.01) if len(seg) else None
        self.tri_centroid = m.sidewalk_quads.mean(1)
        self.tri_radius = (
            np.linalg.norm(m.sidewalk_quads - self.tri_centroid[:, None], axis=2).max(1) if len(m.sidewalk_quads) else np.zeros(0)
        )
        self.sidewalk_grid = GridIndex(m.sidewalk_quad_bbox, reach=self.half_diag + 0.01) if len(m.sidewalk_quads) else None
        rl, rs = m.respawn_lane, m.respawn_s
        self.place_pos = m.position(rl, rs, np.zeros(len(rl)))
        self.place_heading = m.heading_at(rl, rs)
        self.place_half = np.array([m.respawn_region[0] / 2, m.respawn_region[1] / 2])
        self._route_choices = {
            ln: [r for r in rs if config.own_arm_destinations or not m.route_returns[r]] or rs for ln, rs in m.routes_by_spawn_lane.items()
        }
        self.max_agent_ids = config.num_agents + min(MAX_RESPAWN_PER_STEP, config.num_agents) * config.horizon
        # until an env is reset with a seed it draws from a fixed stream (env e: seed e)
        self.rngs = [np.random.default_rng(e) for e in range(num_envs)]
        # vehicles at reset and the respawn cap, per env: the config's num_agents unless a curriculum lowered it
        self.agent_cap = np.full(num_envs, config.num_agents, np.int64)
        self._next_cap = config.num_agents  # the cap of episodes started from now on (set_num_agents)
        g = m.hull_grid
        self._map_arrays = (  # what road_map.localize reads of the map
            (g.table, g.origin, float(g.cell), g.shape),
            (m.hull_normals, m.hull_offsets, m.hull_bbox),
            (m.lane_rows, m.is_circ, m.unit, m.start_phase, m.direction, m.radius, m.length, m.lane_road),
            (m.route_roads, m.route_nroads, m.route_road_pos),
        )
        self._alloc()

    # ------------------------------------------------------------------ state
    def _alloc(self) -> None:
        n, e = self.num_slots, self.num_envs
        self.status = np.zeros(n, dtype=np.int8)
        self.agent_num = np.full(n, -1, dtype=np.int64)
        self.pos = np.zeros((n, 2))
        self.prev_pos = np.zeros((n, 2))
        self.vel = np.zeros((n, 2))
        self.heading = np.zeros(n)
        self.heading_prev = np.zeros(n)
        self.speed = np.zeros(n)
        self.yaw_rate = np.zeros(n)
        # the chassis states of MetaDrive's car (dynamics model "raycast"); None for the bicycle models
        self.bodies = RaycastVehicles(n) if self.cfg.dynamics.model == "raycast" else None
        self.action = np.zeros((n, schema.ACT_DIM))
        self.route = np.zeros(n, dtype=np.int64)
        self.ref_idx = np.zeros(n, dtype=np.int64)
        self.lane = np.zeros(n, dtype=np.int64)
        self.ep_len = np.zeros(n, dtype=np.int64)
        self.dying_left = np.zeros(n, dtype=np.int64)
        self.env_step = np.zeros(e, dtype=np.int64)
        self.next_agent = np.zeros(e, dtype=np.int64)

    @property
    def episode_step(self) -> int:
        """Env steps of env 0's current episode (the single-env view)."""
        return int(self.env_step[0])

    def env_slots(self, env: int) -> np.ndarray:
        """Slot indices owned by ``env``."""
        return np.arange(env * self.slots_per_env, (env + 1) * self.slots_per_env)

    def reset(self, seed: int | list[int] | None = None) -> StepResult:
        """Start new episodes in every env; env ``e`` is seeded with ``seed + e`` (or ``seed[e]``).

        ``seed=None`` continues each env's random stream, so a run seeded once at its first
        reset is reproducible over all its episodes.
        """
        if seed is None or isinstance(seed, (int, np.integer)):
            seeds = [None if seed is None else int(seed) + e for e in range(self.num_envs)]
        else:
            seeds = list(seed)
        return self.reset_envs(np.arange(self.num_envs), seeds)

    def set_num_agents(self, n: int) -> None:
        """Vehicles at reset (and the respawn cap) of every episode started from now on: 1 to the config's num_agents.

        Episodes in progress keep their cap; slots, the id pool and the spaces stay the config's (a curriculum's phase).
        """
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= self.cfg.num_agents:
            raise ValueError(f"num_agents={n!r}; allowed: an integer from 1 to the scenario's num_agents ({self.cfg.num_agents})")
        self._next_cap = int(n)

    def reset_envs(self, envs: np.ndarray, seeds: list[int | None]) -> StepResult:
        """Start new episodes in ``envs`` (others are untouched; their rows in the result are zero)."""
        m, cfg = self.map, self.cfg
        envs = np.asarray(envs, dtype=np.int64)
        if len(seeds) != len(envs):
            raise ValueError(f"need one seed per env: {len(envs)} envs, {len(seeds)} seeds")
        spawned = np.zeros(self.num_slots, bool)
        n = self._next_cap
        for e, sd in zip(envs, seeds):
            self.agent_cap[e] = n
            rows = self.env_slots(int(e))
            self.status[rows] = EMPTY
            self.agent_num[rows] = -1
            self.env_step[e] = 0
            self.next_agent[e] = 0
            if sd is not None:  # None continues the env's random stream (gymnasium convention)
                self.rngs[e] = np.random.default_rng(sd)
            rng = self.rngs[e]
            slots = rng.choice(len(m.spawn_slot_lane), size=n, replace=False)
            lane = m.spawn_slot_lane[slots]
            s = m.spawn_slot_s[slots] + rng.uniform(-cfg.spawn_jitter_long, cfg.spawn_jitter_long, n)
            r = rng.uniform(-cfg.spawn_jitter_lat, cfg.spawn_jitter_lat, n)
            self._spawn(rows[:n], lane, s, r)
            spawned[rows[:n]] = True
        z = np.zeros(self.num_slots, bool)
        return self._result(z, spawned, z, z, z, z, np.zeros(self.num_slots), np.zeros(self.num_envs))

    def _spawn(self, slots: np.ndarray, lane: np.ndarray, s: np.ndarray, r: np.ndarray) -> None:
        """Place new agents of one env at rest in ``slots``, each with a fresh number and route."""
        m = self.map
        k = len(slots)
        e = int(self.env_of[slots[0]])
        self.status[slots] = ACTIVE
        self.agent_num[slots] = self.next_agent[e] + np.arange(k)
        self.next_agent[e] += k
        self.pos[slots] = m.position(lane, s, r)
        self.prev_pos[slots] = self.pos[slots]
        self.heading[slots] = m.heading_at(lane, s)
        self.heading_prev[slots] = self.heading[slots]
        self.vel[slots] = 0.0
        self.speed[slots] = 0.0
        self.yaw_rate[slots] = 0.0
        if self.bodies is not None:  # at rest at MetaDrive's spawn height, settling onto its suspension
            self.bodies.place(slots, self.pos[slots], self.heading[slots])
        self.action[slots] = 0.0
        self.lane[slots] = lane
        self.ref_idx[slots] = 0
        self.ep_len[slots] = 0
        self.dying_left[slots] = 0
        # destination uniform over the map's choices for this spawn lane
        rng = self.rngs[e]
        for sl, ln in zip(slots, lane):
            choices = self._route_choices[int(ln)]
            self.route[sl] = choices[int(rng.integers(len(choices)))]

    def place(self, slot: int, pos: tuple[float, float], heading: float, speed: float = 0.0, route: int | None = None) -> None:
        """Put a new active vehicle at a pose (scripted scenarios and tests); its lane is localised."""
        m = self.map
        route = int(self.route[slot]) if route is None else int(route)
        if not 0 <= route < len(m.routes):
            raise ValueError(f"bad route {route}; allowed: 0 .. {len(m.routes) - 1}")
        lane = np.array([m.routes[route].spawn_lane])
        sl = np.array([slot])
        self._spawn(sl, lane, np.zeros(1), np.zeros(1))
        self.route[slot] = route
        self.pos[slot] = self.prev_pos[slot] = pos
        self.heading[slot] = self.heading_prev[slot] = heading
        self.speed[slot] = speed
        self.vel[slot] = speed * np.array([np.cos(heading), np.sin(heading)])
        if self.bodies is not None:  # on its suspension, driving straight at ``speed``
            self.bodies.place(sl, self.pos[sl], self.heading[sl], speed, settled=True)
        self._localize(sl)

    def remove(self, slot: int) -> None:
        """Take the vehicle in ``slot`` off the map."""
        self.status[slot] = EMPTY

    # ------------------------------------------------------------------ step
    def step(self, actions: np.ndarray) -> StepResult:
        """Advance every env one step; ``actions`` (N, 2) holds a row per slot (non-active rows ignored)."""
        cfg, m = self.cfg, self.map
        actions = np.asarray(actions, dtype=float)
        if actions.shape != (self.num_slots, 2):
            raise ValueError(f"actions must have shape ({self.num_slots}, 2), got {actions.shape}")
        idx = np.nonzero(self.status == ACTIVE)[0]
        a = actions[idx]
        bad = ~np.isfinite(a).all(1)
        if bad.any():
            names = [agent_name(int(self.agent_num[i])) for i in idx[bad]]
            raise ValueError(f"non-finite action for agent(s) {names}: {a[bad].tolist()}; actions must be finite numbers in [-1, 1]")
        a = np.clip(a, -1.0, 1.0)
        self.env_step += 1
        # wrecks count down before the physics, as MetaDrive's agent manager does (its ``before_step``): one that
        # became dying at step t is an obstacle to the crash test at steps t+1 .. t+delay_done-1, seen by the
        # observations up to step t+delay_done-1, and its slot is free for the respawn at step t+delay_done
        dying = self.status == DYING
        self.dying_left[dying] -= 1
        self.status[dying & (self.dying_left <= 0)] = EMPTY

        # dynamics
        self.prev_pos[idx] = self.pos[idx]
        self.heading_prev[idx] = self.heading[idx]
        self.action[idx] = a
        dyn = cfg.dynamics
        if self.bodies is not None:  # MetaDrive's car: poses as Bullet reports them, the body's own velocities
            pos, hd = self.bodies.step(idx, a, round(dyn.dt / PHYSICS_DT), dyn.max_speed_kmh, dyn.max_steer_deg)
            hd = wrap_angle(hd)
            self.vel[idx] = self.bodies.vel[idx, :2]
            v = np.sqrt((self.vel[idx] ** 2).sum(1))
            r = self.bodies.ang[idx, 2]
        else:
            pos, hd, v, r = bicycle_step(dyn, self.pos[idx], self.heading[idx], self.speed[idx], self.yaw_rate[idx], a)
            self.vel[idx] = (pos - self.pos[idx]) / dyn.dt
        self.pos[idx], self.heading[idx], self.speed[idx], self.yaw_rate[idx] = pos, hd, v, r

        on_lane = self._localize(idx)
        ref_road = m.route_roads[self.route[idx], self.ref_idx[idx]]

        # the rules (coin_app/sim/rules.py) on this step's geometry: lane coordinates on the final lane (arrival) and on
        # the reward lane now and before (progress), in one call
        fl = m.route_final_lane[self.route[idx]]
        rw_lane, on_ref = rules.reward_lane(self.lane[idx], m.lane_road, ref_road, m.road_first_lane)
        s_all, r_all = m.local_coordinates(np.concatenate([fl, rw_lane, rw_lane]), np.concatenate([pos, pos, self.prev_pos[idx]]))
        n_idx = len(idx)
        arrive = rules.arrived(s_all[:n_idx], r_all[:n_idx], m.length[fl], m.width[fl], m.road_nlanes[ref_road])
        poses = self._crash_poses(idx)
        line_pose = poses[idx, -1]  # Bullet's contact test after the physics steps: the chassis, one step past the shown pose
        oor = rules.off_road(on_lane, self._touches_solid_line(line_pose[:, :2], line_pose[:, 2]), self._on_sidewalk(pos, hd))
        crash = self._crashes(poses)[idx]
        self.ep_len[idx] += 1
        max_step = rules.step_limit_reached(self.ep_len[idx], cfg)
        force_env = rules.force_stopped(self.env_step, cfg)
        force = force_env[self.env_of[idx]]
        sign = rules.progress_sign(on_ref, m.road_negative[ref_road], self.scene.progress_sign_flip)
        r_step = rules.step_reward(cfg, s_all[n_idx : 2 * n_idx], s_all[2 * n_idx :], v, sign)
        reward = rules.reward(cfg, r_step, arrive, oor, crash)
        terminated, truncated = rules.done(arrive, oor, crash, max_step, force)
        acted_obs = self.observe(idx)  # before the retirement and the respawn (module doc)

        # retire: arrived vehicles vanish, other done ones linger as obstacles
        done_idx = idx[terminated | truncated]
        linger = ~arrive[terminated | truncated] & (cfg.delay_done > 0)
        self.status[done_idx[linger]] = DYING
        self.dying_left[done_idx[linger]] = cfg.delay_done
        self.speed[done_idx] = 0.0
        self.vel[done_idx] = 0.0
        self.yaw_rate[done_idx] = 0.0
        self.status[done_idx[~linger]] = EMPTY

        vacated = np.zeros(self.num_slots, bool)
        vacated[done_idx[~linger]] = True
        spawned = self._respawn(vacated, ~force_env)

        acted = np.zeros(self.num_slots, bool)
        acted[idx] = True
        spawned_mask = np.zeros(self.num_slots, bool)
        spawned_mask[spawned] = True

        def scatter(vals: np.ndarray) -> np.ndarray:
            out = np.zeros(self.num_slots, dtype=vals.dtype)
            out[idx] = vals
            return out

        result = self._result(
            acted,
            spawned_mask,
            scatter(arrive),
            scatter(crash),
            scatter(oor),
            scatter(max_step),
            scatter(reward),
            rules.global_reward(reward, self.env_of[idx], self.num_envs),
            terminated=scatter(terminated),
            truncated=scatter(truncated),
            observed=(idx, *acted_obs),
        )
        if force_env.any():  # after the observations, so that final observations see the traffic
            self.status[force_env[self.env_of]] = EMPTY
            result.episode_over |= force_env
        return result

    # ------------------------------------------------------------------ pieces
    def _localize(self, idx: np.ndarray) -> np.ndarray:
        """Update each vehicle's lane and reference road; return whether it is on a lane (``road_map.localize``)."""
        return localize(
            self.pos,
            self.heading,
            np.asarray(idx, dtype=np.int64),
            self.route,
            self.ref_idx,
            self.lane,
            *self._map_arrays,
            CKPT_UPDATE_RANGE,
        )

    def _touches_solid_line(self, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Whether each footprint overlaps a physical solid line (or road edge) box."""
        if self.seg_grid is None or len(pos) == 0:
            return np.zeros(len(pos), bool)
        g = self.seg_grid
        return touches_boxes(
            _f64(pos), _f64(heading), self.half, g.table, g.origin, g.cell, g.shape, self.seg_center, self.seg_heading, self.seg_half
        )

    def _on_sidewalk(self, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
        """Whether a footprint sample point lies on a sidewalk (triangulated strips)."""
        m = self.map
        if self.sidewalk_grid is None or len(pos) == 0:
            return np.zeros(len(pos), bool)
        g = self.sidewalk_grid
        return footprint_in_polygons(
            _f64(pos), _f64(heading), self.half, g.table, g.origin, g.cell, g.shape, self.tri_centroid, self.tri_radius,
            m.sidewalk_normals, m.sidewalk_offsets,
        )  # fmt: skip

    def _same_env_pairs(self, max_dist: float, observers: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Slot pairs of vehicles of one env closer than ``max_dist``.

        Without ``observers``: unordered pairs (i < j) of non-empty slots. With a per-slot
        ``observers`` mask: ordered pairs (observer i, other non-empty vehicle j != i).
        """
        e, s = self.num_envs, self.slots_per_env
        p = self.pos.reshape(e, s, 2)
        live = (self.status != EMPTY).reshape(e, s)
        dx = p[:, :, None, 0] - p[:, None, :, 0]
        dy = p[:, :, None, 1] - p[:, None, :, 1]
        close = (dx * dx + dy * dy < max_dist**2) & live[:, None, :]
        if observers is None:
            ee, i, j = np.nonzero(np.triu(close & live[:, :, None], 1))
        else:
            close &= observers.reshape(e, s)[:, :, None] & ~np.eye(s, dtype=bool)[None]
            ee, i, j = np.nonzero(close)
        return ee * s + i, ee * s + j

    def _chassis_poses(self) -> np.ndarray:
        """(N, 3) every slot's chassis pose (x, y, heading): with MetaDrive's car where Bullet has the body, one physics
        step ahead of the pose MetaDrive shows (``pos``, ``heading``) while it moves; without it the shown pose."""
        if self.bodies is None:
            return np.column_stack([self.pos, self.heading])
        b = self.bodies
        return np.column_stack([b.pos[:, :2], np.arctan2(b.rot[:, 1, 1], b.rot[:, 0, 1])])

    def _crash_poses(self, idx: np.ndarray) -> np.ndarray:
        """(N, K, 3) every slot's pose (x, y, heading) at the K instants the crash test sees.

        With MetaDrive's car, Bullet's: the chassis before each physics step of this env step (its contact callback, in
        the collision detection of every physics step) and after the last (its contact test after the step); the
        vehicles not stepped (``idx`` are) where their chassis stands. Without it, K = 1: the end-of-step pose.
        """
        chassis = self._chassis_poses()
        if self.bodies is None:
            return chassis[:, None, :]
        poses = np.repeat(chassis[:, None, :], self.bodies.path.shape[1], axis=1)
        poses[idx] = self.bodies.path
        return poses

    def _crashes(self, poses: np.ndarray) -> np.ndarray:
        """Per slot: whether its box overlaps another active or dying vehicle's box at one of the instants of ``poses``."""
        return same_env_overlaps(poses, self.status != EMPTY, self.slots_per_env, self.half, 2 * self.half_diag)

    def _respawn(self, vacated: np.ndarray, env_ok: np.ndarray) -> np.ndarray:
        """Spawn new agents on free respawn places while under each env's cap, at most ``respawns_per_step`` per env
        (MetaDrive's spawn manager marks every place it finds free as used at its first query of a step, so its respawn
        loop spawns one vehicle per step); new slots."""
        cfg, m = self.cfg, self.map
        if not cfg.allow_respawn:
            return np.zeros(0, dtype=np.int64)
        e_n, s_n = self.num_envs, self.slots_per_env
        live = (self.status != EMPTY).reshape(e_n, s_n)
        allowed = np.where(env_ok & (self.env_step < cfg.horizon), self.agent_cap - live.sum(1), 0)
        if not (allowed > 0).any():
            return np.zeros(0, dtype=np.int64)
        # which places are blocked by a vehicle of the same env (8 x 3 m box at the place)
        blocked = places_blocked(
            self.place_pos, self.place_heading, self.place_half, self.pos, self.heading, self.half, live.reshape(-1), allowed > 0, s_n
        )
        free = (self.status == EMPTY) & ~vacated
        new_slots = []
        for e in np.nonzero(allowed > 0)[0]:
            avail = np.nonzero(~blocked[e])[0]
            rows = self.env_slots(int(e))
            slots = rows[free[rows]]
            k = min(int(allowed[e]), len(avail), len(slots), cfg.respawns_per_step or len(slots))
            if k == 0:
                continue
            places = self.rngs[e].choice(avail, size=k, replace=False)
            self._spawn(slots[:k], m.respawn_lane[places], m.respawn_s[places], np.zeros(k))
            new_slots.append(slots[:k])
        return np.concatenate(new_slots) if new_slots else np.zeros(0, dtype=np.int64)

    # ------------------------------------------------------------------ output
    def observe(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Observations (n, obs_dim) and local states (n, 10) of the vehicles in ``slots``."""
        cfg, m = self.cfg, self.map
        pos, hd = self.pos[slots], self.heading[slots]
        route, ref = self.route[slots], self.ref_idx[slots]
        ref_road = m.route_roads[route, ref]
        next_road = m.route_roads[route, np.minimum(ref + 1, m.route_nroads[route] - 1)]
        ego, ck1, ck2 = ego_features(
            m, pos, hd, self.heading_prev[slots], self.speed[slots], self.action[slots], self.lane[slots], ref_road, next_road,
            cfg.dynamics.max_speed_kmh, cfg.navi_point_dist, cfg.dynamics.dt,
        )  # fmt: skip
        boxes = self._chassis_poses()  # MetaDrive's lidar: rays from the shown pose, against the others' chassis
        lidar = lidar_same_env(
            np.asarray(slots, dtype=np.int64), self.pos, self.heading, boxes[:, :2], boxes[:, 2], self.status != EMPTY,
            self.slots_per_env, self.half, cfg.lidar_beams, cfg.lidar_range,
        )  # fmt: skip
        if cfg.obs_layout == "bottleneck96":  # MetaDrive's bottleneck observation
            hw = m.solid_half_width
            side = line_detector(pos, hd, m.line_p1[m.line_solid], m.line_p2[m.line_solid], hw, cfg.side_detector_range)
            lanes = line_detector(pos, hd, m.line_p1, m.line_p2, hw, cfg.lane_line_detector_range)
            ego = np.concatenate([side, ego[:, 2:8], lanes, ego[:, 9:19]], 1)
        obs = np.concatenate([ego, lidar / cfg.lidar_range], 1).astype(np.float32)
        state = local_state(pos, self.vel[slots], hd, ck1, ck2, m.centre, m.scale, cfg.max_speed, cfg.navi_point_dist)
        return obs, state

    def _result(
        self,
        acted: np.ndarray,
        spawned: np.ndarray,
        arrive: np.ndarray,
        crash: np.ndarray,
        oor: np.ndarray,
        max_step: np.ndarray,
        reward: np.ndarray,
        global_reward: np.ndarray,
        terminated: np.ndarray | None = None,
        truncated: np.ndarray | None = None,
        observed: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
    ) -> StepResult:
        """The step's result; ``observed``: (slots, observations, local states) already taken (the acting vehicles'),
        the others of ``acted | spawned`` are observed now."""
        n = self.num_slots
        obs = np.zeros((n, self.cfg.obs_dim), np.float32)
        state = np.zeros((n, schema.STATE_DIM), np.float32)
        out = acted | spawned
        if observed is not None:
            obs[observed[0]], state[observed[0]] = observed[1], observed[2]
            out[observed[0]] = False
        out_slots = np.nonzero(out)[0]
        if len(out_slots):
            obs[out_slots], state[out_slots] = self.observe(out_slots)
        zeros = np.zeros(n, bool)
        active_per_env = np.bincount(self.env_of[self.status == ACTIVE], minlength=self.num_envs)
        return StepResult(
            acted=acted,
            spawned=spawned,
            agent_num=self.agent_num.copy(),
            obs=obs,
            state=state,
            reward=reward,
            arrive_dest=arrive,
            crash_vehicle=crash,
            out_of_road=oor,
            max_step=max_step,
            terminated=zeros if terminated is None else terminated,
            truncated=zeros if truncated is None else truncated,
            episode_length=self.ep_len.copy(),
            global_reward=global_reward,
            episode_over=active_per_env == 0,
            env_step=self.env_step.copy(),
        )
