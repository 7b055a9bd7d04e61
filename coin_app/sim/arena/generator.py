"""Seeded arena scenarios: start poses, target poses and circular obstacles (the A-GNN test procedure).

A clean re-implementation of the A-GNN's documented test-scenario generator (Ma, Khan, Cremers
2023; summarised in ``docs/decisions.md`` §8.2):

* **1 vehicle**: start and target each uniform in [-25, 25]² × [-π, π].
* **≥ 2 vehicles** ("collision mode", paths cross near the centroid):
  1. starts uniform in [-15, 15]², every pair ≥ 5 m apart;
  2. with c the centroid of the starts, v_i the unit vector from start i to c and h_i = v_i
     turned +90°: target_i = c + U(0, 20) v_i + N(0, 3) h_i, every pair ≥ 5 m apart;
  3. the whole scene shifted by U(-10, 10)²; 4. headings U(-π, π); 5. speeds 0.
* **Obstacles**: for every vehicle and obstacle slot a candidate at
  start + U(-7, d + 7) v̂ + U(0, 7) ĥ (v̂ start→target, d their distance, ĥ = v̂ turned +90°:
  the left side only, as in the A-GNN test sets, with ``obstacle_side="left"``; either side
  with ``"both"``, our training default), radius U(1, 3) m, redrawn while it lies within
  r + 5 m of any start or target; then ``n_obstacles`` of the candidates at random.

Where the A-GNN code re-draws a whole set, this generator re-draws one point at a time (the
same guarantees, and it terminates for 20 vehicles); after every 100 failed draws the ranges
widen by 3 m, as in the A-GNN code. Obstacles may overlap each other (as there).

The ``"short"`` generator (short-range training) keeps the targets but starts each vehicle
U(1, 7.5) m from its target in a random direction (starts ≥ 5 m apart) with a random heading;
obstacles are then placed along these short paths by the same rule. With ``start_difficulty``
d < 1 (nav_ppo's curriculum) the same draws are narrowed: the distance to U(a, a + d (7.5 - a)) m
with a = 1 + (1 - d)(2.5 - 1) (the near end moves toward twice the 1.25 m success distance as d
falls; for d ≤ 5/6 no start is within the success distance) and the start heading to within d·π of the
target heading; d = 1 gives the draws above unchanged.

Seeds: training scenarios draw from ``training_rng(seed)`` and the fixed test sets from
``heldout_rng(vehicles, obstacles, index)``; the two streams can never coincide (different
first entropy word), so no test scenario is ever used for training.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.dynamics import wrap_angle

MIN_SEPARATION = 5.0  # m between starts, and between targets
OBSTACLE_CLEARANCE = 5.0  # m between an obstacle's surface and any start or target
WIDEN_EVERY, WIDEN_BY = 100, 3.0
CURRICULUM_NEAR_FACTOR = 2.0  # the curriculum's nearest start, in success distances, at the lowest spread
TRAIN_STREAM, TEST_STREAM = 0x5EED_7A1, 0x7E57_5E7
# the 24 (vehicles, obstacles) cases of the paper's Table I
PAPER_CASES: tuple[tuple[int, int], ...] = (
    *((n, m) for n in (1, 2, 4) for m in (0, 4, 8, 12)),
    *((n, m) for n in (6, 10, 15, 20) for m in (0, 4, 8)),
)


@dataclass(frozen=True)
class Layout:
    """One scenario: starts (N, 3) and targets (N, 3) as (x, y, heading), obstacles (M, 3) as (x, y, radius)."""

    starts: np.ndarray
    targets: np.ndarray
    obstacles: np.ndarray


def training_rng(seed: int) -> np.random.Generator:
    """The generator of training scenario ``seed``."""
    return np.random.default_rng([TRAIN_STREAM, int(seed)])


def heldout_rng(num_vehicles: int, num_obstacles: int, index: int) -> np.random.Generator:
    """The generator of test scenario ``index`` of the case (vehicles, obstacles); fixed forever."""
    return np.random.default_rng([TEST_STREAM, int(num_vehicles), int(num_obstacles), int(index)])


def _spaced_points(
    rng: np.random.Generator, n: int, draw: Callable[[np.random.Generator, int, float], np.ndarray], min_sep: float
) -> np.ndarray:
    """``n`` points from ``draw(rng, i, widen)``, each ≥ ``min_sep`` from the earlier ones; widens after failures."""
    points = np.zeros((n, 2))
    failures = 0
    for i in range(n):
        while True:
            p = draw(rng, i, WIDEN_BY * (failures // WIDEN_EVERY))
            if i == 0 or np.min(np.linalg.norm(points[:i] - p, axis=1)) >= min_sep:
                points[i] = p
                break
            failures += 1
    return points


def _unit(v: np.ndarray) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 1e-9, v / np.maximum(n, 1e-9), np.array([1.0, 0.0]))


def _left(v: np.ndarray) -> np.ndarray:
    return np.stack([-v[..., 1], v[..., 0]], -1)


def _vehicles(rng: np.random.Generator, n: int, cfg: ArenaConfig) -> tuple[np.ndarray, np.ndarray]:
    """Start and target positions (N, 2) of the A-GNN procedure."""
    half = cfg.map_half_size
    if n == 1:
        return rng.uniform(-half, half, (1, 2)), rng.uniform(-half, half, (1, 2))
    starts = _spaced_points(rng, n, lambda r, i, w: r.uniform(-15.0 - w, 15.0 + w, 2), MIN_SEPARATION)
    centre = starts.mean(0)
    toward = _unit(centre - starts)
    side = _left(toward)
    targets = _spaced_points(
        rng, n, lambda r, i, w: centre + r.uniform(0.0, 20.0 + w) * toward[i] + r.normal(0.0, 3.0 + w) * side[i], MIN_SEPARATION
    )
    shift = rng.uniform(-10.0, 10.0, 2)
    return starts + shift, targets + shift


def _short_starts(rng: np.random.Generator, targets: np.ndarray, cfg: ArenaConfig) -> np.ndarray:
    """Starts U(a, a + d (hi - a)) m from each target in a random direction, ≥ 5 m apart (d: ``start_difficulty``).

    a = lo + (1 - d) (max(lo, 2 success_distance) - lo): at d = 1 the generator's (lo, hi); below, the
    nearest starts move out of the success region.
    """
    lo, hi = cfg.short_start_radius
    d = cfg.start_difficulty
    lo = lo + (1.0 - d) * (max(lo, CURRICULUM_NEAR_FACTOR * cfg.success_distance) - lo)
    hi = lo + d * (hi - lo)

    def draw(r: np.random.Generator, i: int, w: float) -> np.ndarray:
        angle = r.uniform(-np.pi, np.pi)
        return targets[i] + r.uniform(lo, hi + w) * np.array([np.cos(angle), np.sin(angle)])

    return _spaced_points(rng, len(targets), draw, MIN_SEPARATION)


def _obstacles(rng: np.random.Generator, m: int, starts: np.ndarray, targets: np.ndarray, cfg: ArenaConfig) -> np.ndarray:
    """``m`` obstacles (x, y, r) along the vehicles' straight paths, clear of every start and target."""
    if m == 0:
        return np.zeros((0, 3))
    points = np.concatenate([starts, targets])
    lo, hi = cfg.obstacle_radius
    candidates = []
    for s, t in zip(starts, targets):
        d = float(np.linalg.norm(t - s))
        along = _unit(t - s)
        side = _left(along)
        for _ in range(m):
            failures = 0
            while True:
                w = WIDEN_BY * (failures // WIDEN_EVERY)
                lateral = rng.uniform(0.0, 7.0 + w)
                if cfg.obstacle_side == "both" and rng.random() < 0.5:
                    lateral = -lateral
                c = s + rng.uniform(-7.0 - w, d + 7.0 + w) * along + lateral * side
                r = rng.uniform(lo, hi)
                if np.min(np.linalg.norm(points - c, axis=1)) >= r + OBSTACLE_CLEARANCE:
                    candidates.append((c[0], c[1], r))
                    break
                failures += 1
    picked = rng.choice(len(candidates), size=m, replace=False)
    return np.array([candidates[i] for i in picked])


def generate(rng: np.random.Generator, cfg: ArenaConfig, num_vehicles: int | None = None, num_obstacles: int | None = None) -> Layout:
    """One scenario of ``cfg``'s generator (vehicle and obstacle counts default to the config's)."""
    n = cfg.num_vehicles if num_vehicles is None else int(num_vehicles)
    m = cfg.num_obstacles if num_obstacles is None else int(num_obstacles)
    if n < 1 or m < 0:
        raise ValueError(f"bad scenario size: {n} vehicles, {m} obstacles; allowed: >= 1 vehicle, >= 0 obstacles")
    starts, targets = _vehicles(rng, n, cfg)
    if cfg.generator == "short":
        starts = _short_starts(rng, targets, cfg)
    start_heading = rng.uniform(-np.pi, np.pi, n)
    target_heading = rng.uniform(-np.pi, np.pi, n)
    if cfg.generator == "short" and cfg.start_difficulty < 1.0:  # the same draws, the start turned toward the target heading
        start_heading = wrap_angle(target_heading + cfg.start_difficulty * wrap_angle(start_heading - target_heading))
    obstacles = _obstacles(rng, m, starts, targets, cfg)
    return Layout(
        starts=np.column_stack([starts, start_heading]),
        targets=np.column_stack([targets, target_heading]),
        obstacles=obstacles,
    )
