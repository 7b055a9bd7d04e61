"""A scripted arena driver (no learning): reach the target's centre line from behind, then track it and stop.

From the observation only (``observation.py``), in the target's frame (``a`` along the
target heading, ``e`` to its left, ``psi`` the vehicle heading relative to the target's):

* **line phase** when the vehicle is behind the target or just past it (a < 1), inside a cone around the
  line (|e| < 0.6 max(-a, 0) + 0.8) and roughly aligned (|psi| < 1.4): Stanley steering
  ``-psi - atan(k e / (|v| + 0.5))`` and a speed that lets the 1 m/s² pedal stop the car on the
  target;
* otherwise **approach**: pure pursuit of the point 10 m behind the target on its line (circling
  there until aligned).

``heuristic_actions`` ignores obstacles and the other vehicles: the arena's reference for tests
and a floor for learned policies. ``avoiding_actions`` is the same driver with one reflex for the
closest entity of the observation (nav_ppo's optional teacher): when it lies ahead, in a
corridor about its own width, closer to the vehicle than the target and within a look-ahead that
grows with speed, steer at full lock away from it and slow to a crawl (brake when nearly touching).

``DRIVERS`` names both.
"""

from __future__ import annotations

import numpy as np

from coin_app.sim.arena.observation import POSITION_SCALE, SIZE_SCALE, SPEED_SCALE

OWN_RADIUS = 0.5 * float(np.hypot(2.5, 1.0))  # the bounding radius of the arena's 2.5 x 1.0 m vehicles


def heuristic_actions(obs: np.ndarray, cruise: float = 4.0, dt: float = 0.1, friction: float = 0.99, max_steer: float = 0.8) -> np.ndarray:
    """(steering, pedal) in [-1, 1] for observations (N, 13)."""
    obs = np.asarray(obs, float).reshape(-1, 13)
    target = obs[:, 0:2] * POSITION_SCALE  # in the vehicle frame
    rel = np.arctan2(obs[:, 2], obs[:, 3])  # target heading in the vehicle frame
    speed = obs[:, 4] * SPEED_SCALE
    c, s = np.cos(rel), np.sin(rel)
    # the vehicle (origin) in the target frame
    a = -(c * target[:, 0] + s * target[:, 1])
    e = -(-s * target[:, 0] + c * target[:, 1])
    psi = -rel
    line = (a < 1.0) & (np.abs(e) < 0.6 * np.maximum(-a, 0.0) + 0.8) & (np.abs(psi) < 1.4)
    stanley = -psi - np.arctan(1.5 * e / (np.abs(speed) + 0.5))
    behind = target - 10.0 * np.stack([c, s], 1)
    pursuit = np.arctan2(behind[:, 1], behind[:, 0])
    steer = np.clip(np.where(line, stanley, 1.5 * pursuit) / max_steer, -1.0, 1.0)
    stop_dist = np.maximum(-a - 0.3, 0.0)
    v_line = np.minimum(cruise, 0.8 * np.sqrt(2.0 * 0.8 * stop_dist))
    v_approach = np.where(np.abs(pursuit) > 1.0, 1.5, np.minimum(cruise, 0.5 + 0.4 * np.linalg.norm(behind, axis=1)))
    v_des = np.where(line, v_line, v_approach)
    pedal = np.clip((v_des - friction * speed) / dt, -1.0, 1.0)
    return np.stack([steer, pedal], 1)


def avoiding_actions(
    obs: np.ndarray, look: float = 4.0, lateral: float = 1.8, crawl: float = 2.5, dt: float = 0.1, friction: float = 0.99
) -> np.ndarray:
    """``heuristic_actions`` with a reflex away from the closest entity ahead (see module doc) for observations (N, 13)."""
    obs = np.asarray(obs, float).reshape(-1, 13)
    actions = heuristic_actions(obs, dt=dt, friction=friction)
    near = obs[:, 6:8] * POSITION_SCALE  # the entity's centre in the vehicle frame
    speed = obs[:, 4] * SPEED_SCALE
    distance = np.linalg.norm(near, axis=1)
    clearance = distance - obs[:, 10] * SIZE_SCALE - OWN_RADIUS
    ahead = (
        (obs[:, 12] > 0.5)
        & (near[:, 0] > 0.0)
        & (np.abs(near[:, 1]) < obs[:, 10] * SIZE_SCALE + lateral)
        & (clearance < look + np.abs(speed))
        & (distance < np.linalg.norm(obs[:, 0:2] * POSITION_SCALE, axis=1))  # not beyond the target
    )
    away = np.where(near[:, 1] >= 0.0, -1.0, 1.0)  # full lock to the side the entity is not on
    crawl_pedal = np.clip((crawl - friction * speed) / dt, -1.0, 1.0)
    pedal = np.where(ahead, np.minimum(actions[:, 1], crawl_pedal), actions[:, 1])
    pedal = np.where(ahead & (clearance < 0.5), -1.0, pedal)
    return np.stack([np.where(ahead, away, actions[:, 0]), pedal], 1)


DRIVERS = {"heuristic": heuristic_actions, "avoiding": avoiding_actions}  # the scripted drivers by name
