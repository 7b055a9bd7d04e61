"""Arena configuration: every constant of the navigation-and-parking scenario in one dataclass.

Defaults are the seed-2 paper's where it gives numbers (Δt 0.1 s, success 1.25 m / 0.2 rad /
0.05 m/s) and our choices elsewhere (``docs/decisions.md`` §8.1, after the A-GNN simulator):
wheelbase 2.0 m, friction 0.99, pedal ±1 m/s², steering ±0.8 rad, 1.0 × 2.5 m vehicles,
obstacles of radius 1–3 m, a ±25 m map, the semi-implicit update order (``update_order``; the
A-GNN baseline runs in its own simulator's, ``"position_first"`` with ``dt`` 0.2 s). The reward
coefficients (Eqs. 2–6) are left symbolic by the paper; ours keep one step's shaping near 1 (the distance
reward is at most 0.7, the angle reward half of it, the proximity penalty 0.2 per entity at 1 m
clearance) and make the time penalty (2 per step at the 400-step limit) outgrow it, as the
paper intends: hovering near the target until the limit, collecting distance and angle rewards,
must earn less than parking at any step (tested). A time penalty of 0.01 with a success reward
of 50 fails that test: the first trained pair learnt to hover.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any

OWN_WIDTH = 6  # observation.py: target (4 numbers), own speed and steering
ENTITY_WIDTH = 7  # observation.py: one observed entity's block
# observation.py: the optional candidate features, a capped clearance and an admissibility flag for each of the planning
# filter's 22 candidate actions (heuristic.CANDIDATES and the plain driver's own); 44 = 2 (mod 7), so an observation's
# width tells whether they are there (observation.layout_of)
CANDIDATE_WIDTH = 44


@dataclass(frozen=True)
class RewardConfig:
    """Coefficients of the reward, Eqs. 2–6 of the paper (symbols in brackets)."""

    min_distance_reward: float = 0.05  # [gamma] floor of the distance reward's magnitude
    distance_scale: float = 0.01  # [alpha_dis] per metre
    distance_offset: float = 70.0  # [c_dis] m, about the map diagonal
    sign_free_radius: float = 5.0  # [d_c] m: inside it the distance reward is positive even when moving away
    angle_scale: float = 1.0  # [alpha_angle]
    angle_radius: float = 5.0  # [d_a_min] m: angle reward only inside this distance
    collision_reward: float = -10.0  # [r_coll] per entity whose footprint overlaps the vehicle's
    proximity_scale: float = 0.02  # [alpha_obs]: penalty alpha_obs * r_coll / d inside the band
    proximity_radius: float = 3.0  # [d_min] m of clearance: no proximity penalty beyond it
    collision_clearance: float = 0.25  # [d_coll] m: the band's 1/d is capped at 1/d_coll
    time_scale: float = 0.05  # [alpha_time]: r_time = -alpha_time * dt * t (t = the vehicle's step)
    success_reward: float = 100.0  # [r_succ]
    truncation_reward: float = -20.0  # [r_trunc] at the step limit without success


@dataclass(frozen=True)
class ArenaConfig:
    """All constants of the arena; build with :func:`make_arena_config`."""

    num_vehicles: int = 4
    num_obstacles: int = 3
    # per-episode counts uniform in [num_vehicles, max_vehicles] / [num_obstacles, max_obstacles] when set
    max_vehicles: int | None = None
    max_obstacles: int | None = None
    # probability that a generated (training) episode is one vehicle without obstacles instead of the counts above; not in
    # the paper: a lone vehicle's observation (no entity, flag 0) is otherwise rare in the short stage's mix (1 of 72 draws)
    # and absent from the long stage's, though the suite's 1x0 case is exactly it (docs/arena/README.md)
    lone_fraction: float = 0.0
    max_steps: int = 400  # per vehicle (40 s at dt 0.1: the A-GNN evaluation's 200 steps of 0.2 s)
    # kinematics (Eq. 1)
    dt: float = 0.1
    wheelbase: float = 2.0
    friction: float = 0.99  # beta: v' = beta v + p dt
    # "semi_implicit" (the paper's text): v, then heading with the new v, then position with both new;
    # "position_first" (the A-GNN simulator, Ma et al. 2023): position with the old v and heading, then
    # heading with the old v (wrapped), then v; run the A-GNN baseline with it and dt 0.2
    update_order: str = "semi_implicit"
    max_pedal: float = 1.0  # m/s^2
    max_steer: float = 0.8  # rad
    # geometry
    vehicle_length: float = 2.5
    vehicle_width: float = 1.0
    obstacle_radius: tuple[float, float] = (1.0, 3.0)
    map_half_size: float = 25.0
    # success test (paper §IV): position, heading and speed tolerances
    success_distance: float = 1.25
    success_angle: float = 0.2
    success_speed: float = 0.05
    # the switching policy uses the short-range module inside this distance to the target
    switch_radius: float = 7.5
    # scenario generator (generator.py): "agnn" (A-GNN test procedure) or "short" (starts near targets)
    generator: str = "agnn"
    obstacle_side: str = "both"  # "left": the A-GNN test sets' one-sided placement; "both": either side
    short_start_radius: tuple[float, float] = (1.0, 7.5)  # "short" generator: start distance to target (m)
    # "short" generator's spread d in (0, 1]: start distance U(a, a + d (hi - a)) with a moving from lo out to twice the
    # success distance as d falls (generator._short_starts), start heading within d * pi of the target's; 1 = the full
    # spread (uniform heading); nav_ppo's curriculum raises it during training (curriculum_steps)
    start_difficulty: float = 1.0
    # entities each vehicle observes, the closest first (observation.py): 1 is the paper's (the closest entity only); more
    # is our option, not the paper's (docs/arena/README.md)
    observed_entities: int = 1
    # each vehicle also observes the clearance of the planning filter's candidate rollouts (observation.py; our option, not
    # the paper's: False is the paper's observation)
    candidate_features: bool = False
    reward: RewardConfig = field(default_factory=RewardConfig)

    @property
    def obs_dim(self) -> int:
        """Observation length (see ``observation.py``): 6 own numbers, 7 per observed entity (13 in the paper), and 44 with
        the candidate features."""
        return OWN_WIDTH + ENTITY_WIDTH * self.observed_entities + (CANDIDATE_WIDTH if self.candidate_features else 0)

    @property
    def vehicle_pool(self) -> int:
        """Most vehicles an episode of this config can have."""
        return self.num_vehicles if self.max_vehicles is None else self.max_vehicles

    @property
    def vehicle_radius(self) -> float:
        """Radius of the circle around a vehicle's footprint."""
        return 0.5 * math.hypot(self.vehicle_length, self.vehicle_width)


GENERATORS = ("agnn", "short")
# success tests of the arena suite: the seed paper's (vehicles park) or the A-GNN paper's (coin_app.evaluation.arena_suite)
PROTOCOLS = ("arena", "agnn")
MAX_OBSERVED_ENTITIES = 16
UPDATE_ORDERS = ("semi_implicit", "position_first")
OBSTACLE_SIDES = ("both", "left")


def _bad(name: str, value: Any, allowed: str) -> ValueError:
    return ValueError(f"bad arena value {name}={value!r}; allowed: {allowed}")


def make_arena_config(**overrides: Any) -> ArenaConfig:
    """An :class:`ArenaConfig` with ``overrides`` (``reward`` may be a dict of RewardConfig fields); bad values are refused."""
    allowed = {f.name for f in dataclasses.fields(ArenaConfig)}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise ValueError(f"unknown arena key(s) {unknown}; allowed: {', '.join(sorted(allowed))}")
    reward = overrides.pop("reward", RewardConfig())
    if isinstance(reward, dict):
        known = {f.name for f in dataclasses.fields(RewardConfig)}
        if set(reward) - known:
            raise ValueError(f"unknown reward key(s) {sorted(set(reward) - known)}; allowed: {', '.join(sorted(known))}")
        reward = RewardConfig(**reward)
    for key in ("obstacle_radius", "short_start_radius"):
        if key in overrides:
            overrides[key] = tuple(overrides[key])
    cfg = ArenaConfig(reward=reward, **overrides)
    k = cfg.observed_entities
    if not (isinstance(k, int) and not isinstance(k, bool) and 1 <= k <= MAX_OBSERVED_ENTITIES):
        raise _bad("observed_entities", k, f"an integer in [1, {MAX_OBSERVED_ENTITIES}] (1: the paper's closest entity only)")
    if not isinstance(cfg.candidate_features, bool):
        raise _bad("candidate_features", cfg.candidate_features, "True or False (False: the paper's observation)")
    for name in ("num_vehicles", "max_steps"):
        v = getattr(cfg, name)
        if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
            raise _bad(name, v, "an integer >= 1")
    if not (isinstance(cfg.num_obstacles, int) and not isinstance(cfg.num_obstacles, bool) and cfg.num_obstacles >= 0):
        raise _bad("num_obstacles", cfg.num_obstacles, "an integer >= 0")
    for name in ("dt", "wheelbase", "max_pedal", "max_steer", "vehicle_length", "vehicle_width", "map_half_size", "switch_radius"):
        if not getattr(cfg, name) > 0:
            raise _bad(name, getattr(cfg, name), "a number > 0")
    if not 0 < cfg.friction <= 1:
        raise _bad("friction", cfg.friction, "a number in (0, 1]")
    if not (isinstance(cfg.lone_fraction, int | float) and not isinstance(cfg.lone_fraction, bool) and 0 <= cfg.lone_fraction <= 1):
        raise _bad("lone_fraction", cfg.lone_fraction, "a number in [0, 1]")
    if not 0 < cfg.start_difficulty <= 1:
        raise _bad("start_difficulty", cfg.start_difficulty, "a number in (0, 1]")
    for name in ("obstacle_radius", "short_start_radius"):
        lo, hi = getattr(cfg, name)
        if not 0 < lo <= hi:
            raise _bad(name, getattr(cfg, name), "(low, high) with 0 < low <= high")
    for name, low in (("max_vehicles", cfg.num_vehicles), ("max_obstacles", cfg.num_obstacles)):
        v = getattr(cfg, name)
        if v is not None and not (isinstance(v, int) and not isinstance(v, bool) and v >= low):
            raise _bad(name, v, f"None or an integer >= {low}")
    if cfg.generator not in GENERATORS:
        raise _bad("generator", cfg.generator, ", ".join(GENERATORS))
    if cfg.obstacle_side not in OBSTACLE_SIDES:
        raise _bad("obstacle_side", cfg.obstacle_side, ", ".join(OBSTACLE_SIDES))
    if cfg.update_order not in UPDATE_ORDERS:
        raise _bad("update_order", cfg.update_order, ", ".join(UPDATE_ORDERS))
    return cfg
