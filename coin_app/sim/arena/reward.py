"""The arena reward, Eqs. 2–6 of the seed-2 paper, vectorized over vehicles (coefficients in ``RewardConfig``).

    r_hat   = max(gamma, alpha_dis (c_dis - d_t))
    r_dis   = +r_hat if d_t < d_{t-1} or d_t < d_c, else -r_hat                          (3)
    r_angle = alpha_angle (0.5 - zeta_diff / pi) |r_dis| if d_t < d_a_min, else 0            (4)
    r_obs   = sum over the other vehicles and the obstacles i of                            (5)
              r_coll                              if the footprints overlap,
              alpha_obs r_coll / max(d_i, d_coll) if the clearance d_i < d_min,
              0                                   otherwise
    r_time  = -alpha_time dt t                                                               (6)
    r_total = r_dis + r_obs + r_angle + r_time; r_succ on success; r_trunc at the limit      (2)

Our reading of Eq. 5: the paper tests centre distances against d_coll and d_min, which cannot
tell a 1 m obstacle from a 3 m one; here a collision is a geometric overlap (what the
evaluation counts) and d_i is the clearance between the two bounding circles.
"""

from __future__ import annotations

import numpy as np

from coin_app.sim.arena.config import RewardConfig


def distance_reward(cfg: RewardConfig, dist: np.ndarray, prev_dist: np.ndarray) -> np.ndarray:
    """Eq. 3: the signed linear distance reward."""
    magnitude = np.maximum(cfg.min_distance_reward, cfg.distance_scale * (cfg.distance_offset - dist))
    return np.where((dist < prev_dist) | (dist < cfg.sign_free_radius), magnitude, -magnitude)


def angle_reward(cfg: RewardConfig, dist: np.ndarray, heading_error: np.ndarray, r_dis: np.ndarray) -> np.ndarray:
    """Eq. 4: heading alignment reward near the target, scaled by |r_dis|."""
    return np.where(dist < cfg.angle_radius, cfg.angle_scale * (0.5 - heading_error / np.pi) * np.abs(r_dis), 0.0)


def obstacle_reward(cfg: RewardConfig, contact: np.ndarray, clearance: np.ndarray) -> np.ndarray:
    """Eq. 5: collision and proximity penalties summed over entities ((N, E) contact and clearance)."""
    band = cfg.proximity_scale * cfg.collision_reward / np.maximum(clearance, cfg.collision_clearance)
    per_entity = np.where(contact, cfg.collision_reward, np.where(clearance < cfg.proximity_radius, band, 0.0))
    return per_entity.sum(1)


def time_reward(cfg: RewardConfig, t: int, dt: float) -> float:
    """Eq. 6: a penalty growing linearly with the step index."""
    return -cfg.time_scale * dt * t


def step_reward(
    cfg: RewardConfig,
    dist: np.ndarray,
    prev_dist: np.ndarray,
    heading_error: np.ndarray,
    contact: np.ndarray,
    clearance: np.ndarray,
    t: int,
    dt: float,
    success: np.ndarray,
    truncated: np.ndarray,
) -> np.ndarray:
    """Eq. 2: the total reward of every vehicle for one step."""
    r_dis = distance_reward(cfg, dist, prev_dist)
    shaped = r_dis + angle_reward(cfg, dist, heading_error, r_dis) + obstacle_reward(cfg, contact, clearance) + time_reward(cfg, t, dt)
    return np.where(success, cfg.success_reward, np.where(truncated, cfg.truncation_reward, shaped))
