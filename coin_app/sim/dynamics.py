"""Vehicle dynamics: one vectorized bicycle-model step for every moving vehicle.

Order (semi-implicit, as the seed-2 paper describes Eq. 1): speed first, then yaw rate
and heading, then position with the *new* speed and heading.

    delta   = a0 * max_steer
    v'      = clip(v + accel(a0, a1, v, r) * dt, 0, v_max)
    kappa   = k * a0                (or tan(delta) / L), |kappa| <= grip(a0) / v'^2
    r'      = r + alpha * (v' * kappa - r)
    psi'    = psi + dt * (r + r') / 2        (trapezoid; psi + dt * r' if not trapezoid)
    beta    = beta_gain * atan(lr / L * tan(delta)) * kappa / kappa_cmd
    x', y'  = x, y + v' * dt * (cos, sin)(psi' + beta)

accel: a1 > 0 -> throttle * a1 (0 above max speed, then coasting); a1 = 0 -> -coast;
a1 < 0 -> -min(brake_linear * b, c + k * b) * (1 - brake_steer * |a0|), b = -a1; when
a1 >= 0 a scrub loss scrub * (1 + scrub_throttle * a1) * |v r tan(delta)| is subtracted.
"""

from __future__ import annotations

import numba
import numpy as np

from coin_app.sim.config import DynamicsConfig


def bicycle_step(
    cfg: DynamicsConfig,
    pos: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    yaw_rate: np.ndarray,
    action: np.ndarray,
    trapezoid: bool | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Advance (pos, heading, speed, yaw_rate) of N vehicles by one step of ``cfg.dt``."""
    dt = cfg.dt
    a0 = action[:, 0]
    a1 = action[:, 1]
    delta = a0 * np.deg2rad(cfg.max_steer_deg)
    tan_d = np.tan(delta)
    v_max = cfg.max_speed_kmh / 3.6
    over = speed * 3.6 > cfg.max_speed_kmh
    brake = np.maximum(-a1, 0.0)
    brake_decel = np.minimum(cfg.brake_linear * brake, cfg.brake_sat_intercept + cfg.brake_sat_slope * brake)
    accel = np.where(
        a1 > 0,
        np.where(over, -cfg.coast_decel, cfg.throttle_accel * a1),
        np.where(a1 == 0, -cfg.coast_decel, -brake_decel * (1.0 - cfg.brake_steer * np.abs(a0))),
    )
    accel = accel - np.where(a1 >= 0, cfg.scrub * (1.0 + cfg.scrub_throttle * a1) * np.abs(speed * yaw_rate * tan_d), 0.0)
    v_new = np.clip(speed + accel * dt, 0.0, v_max)

    if cfg.curvature_per_steer is None:
        kappa_cmd = tan_d / cfg.wheelbase
    else:
        kappa_cmd = cfg.curvature_per_steer * a0
    grip = np.maximum(cfg.lateral_grip - cfg.lateral_grip_steer2 * a0**2, 0.0)
    with np.errstate(divide="ignore"):
        cap = np.where(v_new > 0, grip / np.maximum(v_new, 1e-12) ** 2, np.inf)
    kappa = np.clip(kappa_cmd, -cap, cap)
    r_new = yaw_rate + cfg.yaw_rate_alpha * (v_new * kappa - yaw_rate)
    if trapezoid is None:
        trapezoid = cfg.yaw_rate_alpha < 1.0
    heading_new = heading + dt * (0.5 * (yaw_rate + r_new) if trapezoid else r_new)
    ratio = np.where(np.abs(kappa_cmd) > 1e-12, kappa / np.where(np.abs(kappa_cmd) > 1e-12, kappa_cmd, 1.0), 1.0)
    beta = cfg.beta_gain * np.arctan(cfg.lr / cfg.wheelbase * tan_d) * ratio
    direction = heading_new + beta
    pos_new = pos + (v_new * dt)[:, None] * np.stack([np.cos(direction), np.sin(direction)], axis=1)
    return pos_new, heading_new, v_new, r_new


def wrap_angle(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


@numba.njit(cache=True)
def friction_bicycle(
    x: float, y: float, heading: float, speed: float, pedal: float, steer: float, dt: float, wheelbase: float, friction: float
) -> tuple[float, float, float, float]:
    """One vehicle's step of Eq. 1 (``friction_bicycle_step``): the new (x, y, heading, speed)."""
    return friction_bicycle_tan(x, y, heading, speed, pedal, np.tan(steer), dt, wheelbase, friction)[:4]


@numba.njit(cache=True)
def friction_bicycle_tan(
    x: float, y: float, heading: float, speed: float, pedal: float, tan_steer: float, dt: float, wheelbase: float, friction: float
) -> tuple[float, float, float, float, float, float]:
    """``friction_bicycle`` given the tangent of the steering angle (rollouts hold one); also the new heading's cos and sin."""
    v_new = friction * speed + pedal * dt
    shifted = heading + v_new * tan_steer * dt / wheelbase + np.pi
    # wrap_angle: (a % 2 pi) is a itself where 0 <= a < 2 pi (the usual case), so only the others pay for the remainder
    heading_new = (shifted if 0.0 <= shifted < 2.0 * np.pi else shifted % (2.0 * np.pi)) - np.pi
    step, c, s = v_new * dt, np.cos(heading_new), np.sin(heading_new)
    return x + step * c, y + step * s, heading_new, v_new, c, s


@numba.njit(cache=True)
def _friction_bicycle_all(
    pos: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    pedal: np.ndarray,
    steer: np.ndarray,
    dt: float,
    wheelbase: float,
    friction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    n = len(heading)
    pos_new, heading_new, v_new = np.empty((n, 2)), np.empty(n), np.empty(n)
    for i in range(n):
        pos_new[i, 0], pos_new[i, 1], heading_new[i], v_new[i] = friction_bicycle(
            pos[i, 0], pos[i, 1], heading[i], speed[i], pedal[i], steer[i], dt, wheelbase, friction
        )
    return pos_new, heading_new, v_new


def friction_bicycle_step(
    pos: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    pedal: np.ndarray,
    steer: np.ndarray,
    dt: float,
    wheelbase: float,
    friction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of the seed-2 paper's kinematic bicycle with friction (Eq. 1) for N vehicles.

    Semi-implicit order, as the paper's text describes (the action acts on the very next
    position): ``v' = friction * v + pedal * dt``; ``psi' = psi + v' * tan(steer) * dt / L``
    (wrapped to [-pi, pi)); ``(x, y)' = (x, y) + v' * dt * (cos psi', sin psi')``. The speed
    may be negative (reversing).
    """
    heading = np.asarray(heading, dtype=np.float64)
    n = heading.shape

    def arr(a: np.ndarray, shape: tuple) -> np.ndarray:
        return np.ascontiguousarray(np.broadcast_to(np.asarray(a, dtype=np.float64), shape))

    return _friction_bicycle_all(
        arr(pos, (*n, 2)), arr(heading, n), arr(speed, n), arr(pedal, n), arr(steer, n), float(dt), float(wheelbase), float(friction)
    )


def position_first_step(
    pos: np.ndarray,
    heading: np.ndarray,
    speed: np.ndarray,
    pedal: np.ndarray,
    steer: np.ndarray,
    dt: float,
    wheelbase: float,
    friction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One step of the friction bicycle in the A-GNN simulator's order (Ma et al. 2023; the seed paper's "old order").

    ``(x, y)' = (x, y) + v * dt * (cos psi, sin psi)`` with the old speed and heading;
    ``psi' = psi + v * dt * tan(steer) / L`` with the old speed, wrapped to [-pi, pi);
    ``v' = friction * v + pedal * dt``. The action reaches the position one step later than in
    :func:`~coin_app.sim.dynamics.friction_bicycle_step`.
    """
    pos_new = pos + (speed * dt)[:, None] * np.stack([np.cos(heading), np.sin(heading)], axis=1)
    heading_new = wrap_angle(heading + speed * dt * np.tan(steer) / wheelbase)
    return pos_new, heading_new, friction * speed + pedal * dt
