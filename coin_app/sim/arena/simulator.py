"""The arena core: N vehicles with target poses among M circular obstacles, vectorized over vehicles.

One ``step`` moves every vehicle still driving by the friction bicycle (``dynamics.py``, or
:func:`position_first_step`, the A-GNN simulator's order, with ``update_order="position_first"``),
finds contacts geometrically (1.0 × 2.5 m boxes against boxes and circles, ``collision.py``),
computes the reward of Eqs. 2–6 (``reward.py``) and the observations (``observation.py``; the optional candidate
features from ``heuristic.py``).
A vehicle's run ends when it reaches the success state (it then stays parked where it
stopped, an obstacle for the others) or when the step limit is reached. Collisions do not end
a run. Metrics follow the paper (§IV) and the A-GNN code: a collision *event* is a rising edge
of contact with one entity (counted for each vehicle involved); the collision rate is events
per metre driven; success-to-goal is reaching the success state without any collision before.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from coin_app.sim.arena.config import CANDIDATE_WIDTH, ArenaConfig
from coin_app.sim.arena.generator import Layout
from coin_app.sim.arena.heuristic import candidate_features
from coin_app.sim.arena.observation import observe
from coin_app.sim.arena.reward import step_reward
from coin_app.sim.collision import box_circle_overlap, boxes_overlap
from coin_app.sim.dynamics import friction_bicycle_step, position_first_step, wrap_angle


@dataclass
class ArenaStep:
    """Per-vehicle result of one step (vehicles that were driving before it have ``acted``)."""

    obs: np.ndarray  # (N, obs_dim)
    reward: np.ndarray  # (N,)
    acted: np.ndarray  # (N,) bool: drove in this step
    success: np.ndarray  # (N,) bool: reached the success state in this step
    truncated: np.ndarray  # (N,) bool: hit the step limit in this step without success
    new_collisions: np.ndarray  # (N,) collision events that started in this step


class ArenaSimulator:
    """State and step of one arena scenario (see module doc)."""

    def __init__(self, config: ArenaConfig):
        self.config = config
        self.half = np.array([config.vehicle_length / 2.0, config.vehicle_width / 2.0])
        self.layout: Layout | None = None
        self.feature_time = 0.0  # seconds the last observations' candidate features took (0 without them)

    @property
    def num_vehicles(self) -> int:
        """Vehicles of the current scenario."""
        return 0 if self.layout is None else len(self.layout.starts)

    def reset(self, layout: Layout) -> np.ndarray:
        """Place the vehicles of ``layout`` at rest on their starts; returns the observations (N, obs_dim)."""
        self.layout = layout
        n, m = len(layout.starts), len(layout.obstacles)
        self.pos = layout.starts[:, :2].astype(float).copy()
        self.heading = wrap_angle(layout.starts[:, 2].astype(float))
        self.speed = np.zeros(n)
        self.steer = np.zeros(n)
        self.t = 0
        self.driving = np.ones(n, bool)
        self.succeeded = np.zeros(n, bool)
        self.collided = np.zeros(n, bool)  # any collision so far
        self.collision_events = np.zeros(n, int)
        self.distance = np.zeros(n)
        self.steps = np.zeros(n, int)
        self.contact = np.zeros((n, n + m), bool)
        self.prev_dist = self.target_distance()
        self.clearance = self.entity_clearance()
        return self.observations()

    def observations(self, rows: np.ndarray | None = None) -> np.ndarray:
        """Observations (N, obs_dim) of every vehicle (``observation.py``), the candidate features appended where configured.

        The features are computed for the vehicles ``rows`` (bool (N,); all when None), the ones whose
        observation is read (those that drove in the step); the other rows' features are 0.
        """
        obs = observe(self)
        cfg = self.config
        if not cfg.candidate_features:
            return obs
        t0 = time.perf_counter()
        physics = {"wheelbase": cfg.wheelbase, "max_steer": cfg.max_steer, "max_pedal": cfg.max_pedal}
        features = np.zeros((len(obs), CANDIDATE_WIDTH), np.float32)
        read = np.ones(len(obs), bool) if rows is None else rows
        if read.any():
            features[read] = candidate_features(obs[read], cfg.dt, cfg.friction, **physics)
        self.feature_time = time.perf_counter() - t0  # part of a policy's time per step (evaluation.arena_suite)
        return np.concatenate([obs, features], 1)

    def target_distance(self) -> np.ndarray:
        """Distance (N,) of each vehicle's centre to its target position."""
        return np.linalg.norm(self.layout.targets[:, :2] - self.pos, axis=1)

    def heading_error(self) -> np.ndarray:
        """|heading - target heading| (N,) in [0, pi]."""
        return np.abs(wrap_angle(self.heading - self.layout.targets[:, 2]))

    def contacts(self) -> np.ndarray:
        """(N, N + M) bool: vehicle i's footprint overlaps vehicle j (j < N, never itself) or obstacle j - N."""
        n, m = self.num_vehicles, len(self.layout.obstacles)
        out = np.zeros((n, n + m), bool)
        i, j = np.triu_indices(n, 1)
        if len(i):
            half = np.broadcast_to(self.half, (len(i), 2))
            hit = boxes_overlap(self.pos[i], self.heading[i], half, self.pos[j], self.heading[j], half)
            out[i, j] = hit
            out[j, i] = hit
        if m:
            vi, oj = np.repeat(np.arange(n), m), np.tile(np.arange(m), n)
            obs = self.layout.obstacles
            hit = box_circle_overlap(self.pos[vi], self.heading[vi], np.broadcast_to(self.half, (len(vi), 2)), obs[oj, :2], obs[oj, 2])
            out[vi, n + oj] = hit
        return out

    def entity_clearance(self) -> np.ndarray:
        """(N, N + M) clearance between each vehicle's bounding circle and every other entity's (inf for itself)."""
        cfg = self.config
        centres = np.concatenate([self.pos, self.layout.obstacles[:, :2]])
        radii = np.concatenate([np.full(self.num_vehicles, cfg.vehicle_radius), self.layout.obstacles[:, 2]])
        d = np.linalg.norm(self.pos[:, None, :] - centres[None, :, :], axis=-1) - radii[None, :] - cfg.vehicle_radius
        d[np.arange(self.num_vehicles), np.arange(self.num_vehicles)] = np.inf
        return d

    def is_success(self) -> np.ndarray:
        """(N,) within the position, heading and speed tolerances of the target."""
        cfg = self.config
        return (
            (self.target_distance() < cfg.success_distance)
            & (self.heading_error() < cfg.success_angle)
            & (np.abs(self.speed) < cfg.success_speed)
        )

    def step(self, actions: np.ndarray) -> ArenaStep:
        """Advance one step; ``actions`` (N, 2) = (steering, pedal) in [-1, 1] (rows of parked vehicles are ignored)."""
        cfg = self.config
        acted = self.driving.copy()
        a = np.clip(np.asarray(actions, float).reshape(self.num_vehicles, 2), -1.0, 1.0)
        steer, pedal = a[:, 0] * cfg.max_steer, a[:, 1] * cfg.max_pedal
        step = position_first_step if cfg.update_order == "position_first" else friction_bicycle_step
        pos, heading, speed = step(self.pos, self.heading, self.speed, pedal, steer, cfg.dt, cfg.wheelbase, cfg.friction)
        self.distance += np.where(acted, np.linalg.norm(pos - self.pos, axis=1), 0.0)
        self.pos = np.where(acted[:, None], pos, self.pos)
        self.heading = np.where(acted, heading, self.heading)
        self.speed = np.where(acted, speed, 0.0)
        self.steer = np.where(acted, steer, self.steer)
        self.t += 1
        self.steps += acted
        contact = self.contacts()
        new = (contact & ~self.contact).sum(1) * acted
        self.contact = contact
        self.collision_events += new
        self.last_new_collisions = new
        self.collided |= contact.any(1) & acted
        dist = self.target_distance()
        success = self.is_success() & acted
        truncated = acted & ~success & (self.t >= cfg.max_steps)
        self.clearance = self.entity_clearance()
        reward = step_reward(
            cfg.reward, dist, self.prev_dist, self.heading_error(), contact, self.clearance, self.t, cfg.dt, success, truncated
        )
        self.prev_dist = dist
        self.succeeded |= success
        self.driving &= ~(success | truncated)
        return ArenaStep(self.observations(acted), np.where(acted, reward, 0.0), acted, success, truncated, new)
