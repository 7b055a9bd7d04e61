"""A scripted arena driver (no learning): reach the target's centre line from behind, then track it and stop.

From the observation only (``observation.py``), in the target's frame (``a`` along the
target heading, ``e`` to its left, ``psi`` the vehicle heading relative to the target's):

* **line phase** when the vehicle is behind the target or just past it (a < 1), inside a cone around the
  line (|e| < 0.6 max(-a, 0) + 0.8) and roughly aligned (|psi| < 1.4): Stanley steering
  ``-psi - atan(k e / (|v| + 0.5))`` and a speed that lets the 1 m/s² pedal stop the car on the
  target;
* otherwise **approach**: pure pursuit of the point 10 m behind the target on its line (circling
  there until aligned).

It ignores obstacles and the other vehicles: the arena's reference for tests and a floor for
learned policies.
"""

from __future__ import annotations

import numpy as np

from coin_app.sim.arena.observation import POSITION_SCALE, SPEED_SCALE


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
