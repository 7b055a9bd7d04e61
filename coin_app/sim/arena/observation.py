"""The arena observation (paper §III-C): the vehicle's own frame, its target, and the closest entities.

6 numbers per vehicle and 7 per observed entity, in its own frame (x forward, y left; positions
/ 25 m, speeds / 10 m/s, the top steady-state speed at full pedal and friction 0.99); with the
paper's one entity (``observed_entities=1``) 13 numbers:

    0-1   target position (x, y)
    2-3   target heading relative to the vehicle's (sin, cos)
    4     own speed (negative when reversing)
    5     own steering angle / max steering
    6-7   closest other vehicle or obstacle: centre (x, y)
    8-9   its heading relative to the vehicle's (sin, cos); (0, 1) for an obstacle (a circle)
    10    its size: bounding radius / 3 m (obstacle: its radius; vehicle: half its diagonal)
    11    its speed (0 for an obstacle or a parked vehicle)
    12    1 if there is such an entity, else 0 (then 6-11 are 0, 0, 0, 1, 0, 0)

With ``observed_entities=k > 1`` (our option, not the paper's) blocks 13-19, 20-26, ... hold the
second, third, ... closest entities in the same layout, absent ones as (0, 0, 0, 1, 0, 0, 0).
With ``candidate_features=True`` (our option, not the paper's) 44 numbers follow the entity blocks:
for each of the planning driver's 22 candidate actions (the plain driver's action, then
``heuristic.CANDIDATES``), the least clearance of its 2.5 s constant-action rollout against the
observed entities moving at their observed velocities, capped at 3 m and divided by 3 (1 when no
entity can come within 3 m), then 22 flags, 1 where that clearance keeps the filter's 0.6 m margin
(``heuristic.candidate_features``; the arena simulator appends them). What the filter decides on
is then an input the policy can read rather than a computation it must learn.

"Closest" is by clearance between bounding circles, so a large obstacle counts as near
before its centre does (ties: vehicles first, by index). Parked (succeeded) vehicles are
entities like any other.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from coin_app.sim.arena.config import CANDIDATE_WIDTH, ENTITY_WIDTH, OWN_WIDTH

POSITION_SCALE = 25.0
SPEED_SCALE = 10.0
SIZE_SCALE = 3.0


def layout_of(width: int) -> tuple[int, bool]:
    """(observed entities k, whether the 44 candidate features follow) of observation rows ``width`` = 6 + 7 k (+ 44) wide.

    Unambiguous: 44 = 2 (mod 7). A ValueError for any other width.
    """
    for tail in (0, CANDIDATE_WIDTH):
        k, rest = divmod(width - OWN_WIDTH - tail, ENTITY_WIDTH)
        if k >= 1 and rest == 0:
            return k, tail > 0
    raise ValueError(
        f"arena observations must be 6 + 7 k numbers wide (k >= 1), plus {CANDIDATE_WIDTH} candidate features or not; got {width}"
    )


def to_frame(points: np.ndarray, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """World points (N, 2) in the frames of N poses (x forward, y left)."""
    c, s = np.cos(heading), np.sin(heading)
    d = points - pos
    return np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1]], axis=1)


def observe(sim: Any) -> np.ndarray:
    """Observations (N, 6 + 7 k) of every vehicle of an ``ArenaSimulator``: its own numbers and k observed entities' blocks.

    Without the candidate features (which the simulator appends) these are the whole observation.
    """
    cfg, layout = sim.config, sim.layout
    n, m = sim.num_vehicles, len(layout.obstacles)
    out = np.zeros((n, OWN_WIDTH + ENTITY_WIDTH * cfg.observed_entities), np.float32)
    out[:, 0:2] = to_frame(layout.targets[:, :2], sim.pos, sim.heading) / POSITION_SCALE
    rel = layout.targets[:, 2] - sim.heading
    out[:, 2], out[:, 3] = np.sin(rel), np.cos(rel)
    out[:, 4] = sim.speed / SPEED_SCALE
    out[:, 5] = sim.steer / cfg.max_steer
    blocks = out[:, OWN_WIDTH:].reshape(n, cfg.observed_entities, ENTITY_WIDTH)  # a view: writes land in out
    blocks[:, :, 3] = 1.0
    k = min(cfg.observed_entities, n + m - 1)
    if k <= 0:
        return out
    # the step's clearances (ArenaSimulator.entity_clearance), (N, N + M): index among vehicles, then obstacles
    order = np.argsort(sim.clearance, axis=1, kind="stable")[:, :k]  # stable: ties go to the lower index, as argmin's
    centres = np.concatenate([sim.pos, layout.obstacles[:, :2]])
    headings = np.concatenate([sim.heading, np.zeros(m)])
    radii = np.concatenate([np.full(n, cfg.vehicle_radius), layout.obstacles[:, 2]])
    speeds = np.concatenate([sim.speed, np.zeros(m)])
    for b in range(k):
        j = order[:, b]
        vehicle = j < n
        blocks[:, b, 0:2] = to_frame(centres[j], sim.pos, sim.heading) / POSITION_SCALE
        rel = np.where(vehicle, headings[j] - sim.heading, 0.0)
        blocks[:, b, 2], blocks[:, b, 3] = np.sin(rel), np.cos(rel)
        blocks[:, b, 4] = radii[j] / SIZE_SCALE
        blocks[:, b, 5] = speeds[j] / SPEED_SCALE
        blocks[:, b, 6] = 1.0
    return out
