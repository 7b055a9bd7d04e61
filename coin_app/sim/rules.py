"""The driving rules: reward, arrival, crash, off-road and time-outs, vectorized over vehicles (constants in ``ScenarioConfig``).

The individual reward of COIN App. A.3, as MetaDrive 0.4.3's ``MetaDriveEnv.reward_function`` computes it::

    lane    = the localised lane if its road is the reference road, else the reference road's lane 0
    sign    = -1 if the vehicle is off the reference lanes and the reference road is negative, else +1
              (MetaDrive's bottleneck has its own reward without this flip: Scene.progress_sign_flip)
    r_step  = c_1 (s_t - s_{t-1}) sign + c_2 (v_kmh / v_max_kmh) sign                      c_1 = 1, c_2 = 0.1
    r       = +success_reward        if arrived,
              -out_of_road_penalty   elif off the road,
              -crash_penalty         elif crashed,
              r_step                 otherwise            (a terminal reward replaces the step reward)
    r^G_t   = mean of r over the vehicles that acted in step t                             (global reward)

with s_t, s_{t-1} the longitudinal positions of this and the last step on the same ``lane``.
The outcomes (MetaDrive's ``done_function``):

    arrived     <=> len_f - 5 < s_f < len_f + 5  and  (0.5 - n) w <= r_f <= w / 2
                    ((s_f, r_f) on the route's final lane, the right-most; n lanes of the reference road; w the lane width)
    off_road    <=> not on any lane's region  or  the footprint touches a solid line / road edge  or  a sidewalk
    crashed     <=> the footprint overlaps another (active or dying) vehicle's; both are flagged
    terminated  =   arrived or off_road or crashed
    max_step    <=> the vehicle's own steps >= max_agent_steps
    force_stop  <=> the env step >= force_stop_factor x horizon
    truncated   =   (max_step or force_stop) and not terminated

The geometric tests (lane regions, line and sidewalk contact, the crash's box overlap) are the
simulator's geometry; these functions combine their results.
"""

from __future__ import annotations

import numpy as np

from coin_app.sim.config import ScenarioConfig

ARRIVE_LONG_TOLERANCE = 5.0  # m around the end of the final lane


def reward_lane(
    lane: np.ndarray, lane_road: np.ndarray, ref_road: np.ndarray, road_first_lane: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The lane progress is measured on, and whether the localised ``lane`` is on the reference road.

    ``lane_road`` maps each lane of the map to its road, ``road_first_lane`` each road to its lane 0.
    """
    on_ref = lane_road[lane] == ref_road
    return np.where(on_ref, lane, road_first_lane[ref_road]), on_ref


def progress_sign(on_ref: np.ndarray, negative_road: np.ndarray, flip: bool) -> np.ndarray:
    """+1, or -1 for a vehicle off the reference lanes of a negative reference road when the scene's reward ``flip``s."""
    neg = negative_road & flip
    return np.where(on_ref | ~neg, 1.0, -1.0)


def step_reward(cfg: ScenarioConfig, s_now: np.ndarray, s_last: np.ndarray, speed: np.ndarray, sign: np.ndarray) -> np.ndarray:
    """r_step: progress (m) along the reward lane and speed (m/s) as a fraction of the top speed, both times ``sign``."""
    return cfg.driving_reward * (s_now - s_last) * sign + cfg.speed_reward * (speed * 3.6 / cfg.dynamics.max_speed_kmh) * sign


def arrived(s_f: np.ndarray, r_f: np.ndarray, length: np.ndarray, width: np.ndarray, n_ref: np.ndarray) -> np.ndarray:
    """Whether the centre, at (s_f, r_f) on the final lane of ``length`` and ``width``, is at the end of the route's road."""
    near_end = (s_f > length - ARRIVE_LONG_TOLERANCE) & (s_f < length + ARRIVE_LONG_TOLERANCE)
    return near_end & (r_f >= (0.5 - n_ref) * width) & (r_f <= width / 2)


def off_road(on_lane: np.ndarray, on_solid_line: np.ndarray, on_sidewalk: np.ndarray) -> np.ndarray:
    """Whether each vehicle left the road: off every lane region, or touching a solid line or a sidewalk."""
    return ~on_lane | on_solid_line | on_sidewalk


def step_limit_reached(episode_length: np.ndarray, cfg: ScenarioConfig) -> np.ndarray:
    """Whether each vehicle has taken ``max_agent_steps`` steps of its own."""
    return episode_length >= cfg.max_agent_steps


def force_stopped(env_step: np.ndarray, cfg: ScenarioConfig) -> np.ndarray:
    """Whether each env has reached the force stop at ``force_stop_factor`` x ``horizon`` steps."""
    return env_step >= cfg.force_stop_factor * cfg.horizon


def reward(cfg: ScenarioConfig, r_step: np.ndarray, arrive: np.ndarray, oor: np.ndarray, crash: np.ndarray) -> np.ndarray:
    """r: the terminal reward (arrival, then off-road, then crash) in place of the step reward."""
    return np.where(arrive, cfg.success_reward, np.where(oor, -cfg.out_of_road_penalty, np.where(crash, -cfg.crash_penalty, r_step)))


def done(
    arrive: np.ndarray, oor: np.ndarray, crash: np.ndarray, max_step: np.ndarray, force_stop: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """(terminated, truncated): an outcome ends a vehicle; a time-out truncates one that no outcome ended."""
    terminated = arrive | oor | crash
    return terminated, (max_step | force_stop) & ~terminated


def global_reward(r: np.ndarray, env: np.ndarray, num_envs: int) -> np.ndarray:
    """r^G per env: the mean reward of the vehicles that acted (``env`` holds each one's env; 0 for an env with none)."""
    count = np.bincount(env, minlength=num_envs)
    return np.bincount(env, weights=r, minlength=num_envs) / np.maximum(count, 1)
