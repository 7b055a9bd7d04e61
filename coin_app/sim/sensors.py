"""Sensors: 2-D lidar against vehicle boxes, and MetaDrive's 19 ego/navigation features.

Feature formulas and their quirks are MetaDrive 0.4.3's ``LidarStateObservation``
(``docs/decisions.md`` §3.2), reproduced on purpose so that a policy
trained on one simulator can be evaluated on the other.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from coin_app.sim.collision import box_axes, ray_box_distance
from coin_app.sim.road_map import RoadMap, _lane_position, _lane_right_normal, _lane_sr

MAX_LANE_SPAN = 18.0  # (MAX_LANE_NUM 3 + 1) * MAX_LANE_WIDTH 4.5
LANE_OFFSET_NORM = 4.5  # MAX_LANE_WIDTH
STEERING_QUIRK = 60.0  # MetaDrive divides the normalised steering by MAX_STEERING = 60
CURVE_RADIUS_MAX = 60.0
CURVE_ANGLE_MAX_DEG = 135.0


@numba.njit(cache=True)
def _beam_table(n_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of every beam's angle offset ``2 pi k / n_beams``."""
    ck, sk = np.empty(n_beams), np.empty(n_beams)
    for k in range(n_beams):
        ang = 2 * np.pi * k / n_beams
        ck[k], sk[k] = np.cos(ang), np.sin(ang)
    return ck, sk


WINDOW_PAD = 1e-4  # rad added on either side of a box's angular window: 30 times _atan2_bound's largest error


@numba.njit(cache=True, error_model="numpy")
def _atan2_bound(y: float, x: float) -> float:
    """arctan2(y, x) within 3.5e-6 rad (a degree-11 polynomial of the octant's ratio; measured against np.arctan2 on
    millions of points): cheap, for bounds that are padded by ``WINDOW_PAD``."""
    ax, ay = abs(x), abs(y)
    big, small = max(ax, ay), min(ax, ay)
    a = small / big if big > 0.0 else 0.0
    q = a * a
    r = (((((-0.013480470 * q + 0.057477314) * q - 0.121239071) * q + 0.195635925) * q - 0.332994597) * q + 0.999995630) * a
    if ay > ax:
        r = np.pi / 2 - r
    if x < 0.0:
        r = np.pi - r
    return -r if math.copysign(1.0, y) < 0.0 else r


@numba.njit(cache=True, error_model="numpy")
def _scan_box(
    out: np.ndarray, beams: tuple, ox0: float, oy0: float, own_h: float, cx: float, cy: float, box_h: float, box_cs: tuple,
    hl: float, hw: float, rad_b: float, max_range: float,
) -> None:  # fmt: skip
    """Lower the beams ``out`` (n_beams,) of an observer at (ox0, oy0) heading ``own_h`` to the box at (cx, cy), ``box_h``
    (its cos and sin ``box_cs``), half extents (hl, hw) where they hit it, ray-casting only the beams inside the box's
    angular extent (boxes beyond the range plus the box's bounding radius ``rad_b`` = hypot(hl, hw) are skipped);
    ``beams``: ``_beam_table``. The extent is an upper bound: its half-angle atan(p / (d - q)) bounds the box's
    across the line of sight (p, its half-width across; q, its half-depth along), so beams outside it cannot hit."""
    ck, sk = beams
    n_beams = len(out)
    rx, ry = cx - ox0, cy - oy0
    d = np.hypot(rx, ry)
    if not d < max_range + rad_b:  # bounding-circle radius: the range cut
        return
    step = 2 * np.pi / n_beams
    bearing = _atan2_bound(ry, rx) - own_h
    # observer position in the box's frame
    c, s = box_cs
    ox = -(rx * c + ry * s)
    oy = rx * s - ry * c
    # angular half-width of the box seen from the observer, bounded by its extent across
    # the line of sight (p) over its nearest depth along it (d - q)
    inv_d = 1.0 / max(d, 1e-9)
    p = (hl * abs(oy) + hw * abs(ox)) * inv_d
    depth = d - (hl * abs(ox) + hw * abs(oy)) * inv_d
    full = depth <= 1e-6
    # a bound: the beams of a window widened by WINDOW_PAD miss the box outside the exact window (cast for nothing),
    # so the scan is the same as with the exact arctan2s
    half_ang = _atan2_bound(p, max(depth, 1e-6)) + WINDOW_PAD
    k0 = 0 if full else int(np.ceil((bearing - half_ang) / step))
    k1 = int(np.floor((bearing + half_ang) / step))
    count = min(max(n_beams if full else k1 - k0 + 1, 0), n_beams)
    rel_h = own_h - box_h
    cr, sr = np.cos(rel_h), np.sin(rel_h)
    for k in range(k0, k0 + count):
        kk = k % n_beams
        # beam direction in the box frame: angle rel_h + k * step, by angle addition
        dx = cr * ck[kk] - sr * sk[kk]
        dy = sr * ck[kk] + cr * sk[kk]
        tx1, tx2 = (-hl - ox) / dx, (hl - ox) / dx
        ty1, ty2 = (-hw - oy) / dy, (hw - oy) / dy
        t_in = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
        t_out = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
        if t_out >= np.maximum(t_in, 0.0) and t_out < np.inf:
            out[kk] = min(out[kk], max(t_in, 0.0))


@numba.njit(cache=True)
def _lidar_pairs(
    obs_pos: np.ndarray, obs_heading: np.ndarray, pair_obs: np.ndarray, pair_center: np.ndarray, pair_heading: np.ndarray,
    hl: float, hw: float, n_beams: int, max_range: float,
) -> np.ndarray:  # fmt: skip
    out = np.full((len(obs_heading), n_beams), max_range)
    beams, rad_b = _beam_table(n_beams), np.hypot(hl, hw)
    for q in range(len(pair_obs)):
        i, h = pair_obs[q], pair_heading[q]
        box = pair_center[q, 0], pair_center[q, 1], h, (np.cos(h), np.sin(h))
        _scan_box(out[i], beams, obs_pos[i, 0], obs_pos[i, 1], obs_heading[i], *box, hl, hw, rad_b, max_range)
    return out


def lidar_scan(
    obs_pos: np.ndarray,
    obs_heading: np.ndarray,
    pair_obs: np.ndarray,
    pair_center: np.ndarray,
    pair_heading: np.ndarray,
    half: tuple[float, float],
    n_beams: int,
    max_range: float,
) -> np.ndarray:
    """Distances (A, n_beams) from each observer to the nearest box along each beam.

    Beam k points at ``heading + 2 pi k / n_beams`` (CCW; 0 = ahead). The boxes an observer
    can see are given as pairs: observer ``pair_obs[p]`` and a box of half extents ``half``
    at ``pair_center[p]`` with ``pair_heading[p]`` (the caller lists nearby boxes only).
    Each pair is ray-cast only on the beams inside the box's angular extent (``_scan_box``).
    """
    f = np.float64
    return _lidar_pairs(
        np.ascontiguousarray(obs_pos, f).reshape(-1, 2), np.ascontiguousarray(obs_heading, f), np.ascontiguousarray(pair_obs, np.int64),
        np.ascontiguousarray(pair_center, f).reshape(-1, 2), np.ascontiguousarray(pair_heading, f), float(half[0]), float(half[1]),
        int(n_beams), float(max_range),
    )  # fmt: skip


@numba.njit(cache=True)
def lidar_same_env(
    slots: np.ndarray,
    pos: np.ndarray,
    heading: np.ndarray,
    box_pos: np.ndarray,
    box_heading: np.ndarray,
    live: np.ndarray,
    slots_per_env: int,
    half: np.ndarray,
    n_beams: int,
    max_range: float,
) -> np.ndarray:
    """``lidar_scan`` of the vehicles ``slots`` from their poses ``pos``, ``heading`` (per-slot arrays) against the boxes
    (``box_pos``, ``box_heading``) of every other live vehicle of their env closer than the range plus the box's half
    diagonal (env e: slots ``e S .. e S + S - 1``); (len(slots), n_beams)."""
    out = np.full((len(slots), n_beams), max_range)
    rad_b = np.hypot(half[0], half[1])
    reach = max_range + rad_b
    beams = _beam_table(n_beams)
    cos_h, sin_h = np.cos(box_heading), np.sin(box_heading)  # each box's axes, once per slot
    for q in range(len(slots)):
        i = slots[q]
        base = i - i % slots_per_env
        for j in range(base, base + slots_per_env):
            if j == i or not live[j]:
                continue
            dx, dy = pos[i, 0] - box_pos[j, 0], pos[i, 1] - box_pos[j, 1]
            if dx * dx + dy * dy < reach**2:
                box = box_pos[j, 0], box_pos[j, 1], box_heading[j], (cos_h[j], sin_h[j])
                _scan_box(out[q], beams, pos[i, 0], pos[i, 1], heading[i], *box, half[0], half[1], rad_b, max_range)
    return out


def line_detector(
    pos: np.ndarray,
    heading: np.ndarray,
    p1: np.ndarray,
    p2: np.ndarray,
    half_width: float,
    max_range: float,
    n_beams: int = 4,
) -> np.ndarray:
    """MetaDrive's side / lane-line detector: distances (N, n_beams) / range to line segments.

    Beam k points at ``heading + pi/2 + k * 2 pi / n_beams`` ([left, back, right, front] for
    4 beams); the value is the distance along it to the nearest line box (the segment, ``half_width``
    to each side, as MetaDrive's Bullet body of the line), over ``max_range`` (1 = no line within range).
    Gaps between broken-line dashes let beams through; a beam along a line meets the end of a dash; a beam
    starting inside a line's box does not see that line (Bullet's ray test reports no hit from inside a convex body).
    """
    n = len(pos)
    out = np.full((n, n_beams), max_range)
    if n == 0 or len(p1) == 0:
        return out / max_range
    e = p2 - p1
    mid = 0.5 * (p1 + p2)
    seg_len = np.hypot(e[:, 0], e[:, 1])
    reach = max_range + 0.5 * seg_len + half_width
    vi, si = np.nonzero(((pos[:, None, :] - mid[None]) ** 2).sum(-1) < reach[None] ** 2)
    ang = (heading[vi][:, None] + np.pi / 2 + np.arange(n_beams)[None, :] * (2 * np.pi / n_beams)).ravel()
    rep = np.repeat(np.arange(len(vi)), n_beams)  # candidate (vehicle, segment) of each ray
    half = np.column_stack([0.5 * seg_len[si], np.full(len(si), half_width)])
    seg_heading = np.arctan2(e[si, 1], e[si, 0])
    dist = ray_box_distance(pos[vi][rep], np.column_stack([np.cos(ang), np.sin(ang)]), mid[si][rep], seg_heading[rep], half[rep])
    fwd, left = box_axes(seg_heading)
    rel = pos[vi] - mid[si]
    inside = (np.abs((rel * fwd).sum(1)) <= half[:, 0]) & (np.abs((rel * left).sum(1)) <= half[:, 1])
    dist[inside[rep]] = np.inf
    flat = out.reshape(-1)
    rows = vi[rep] * n_beams + np.tile(np.arange(n_beams), len(vi))
    np.minimum.at(flat, rows, dist)
    return np.minimum(out, max_range) / max_range


@numba.njit(cache=True, error_model="numpy")
def _checkpoint(
    lanes: tuple, length: np.ndarray, angle: np.ndarray, lane: int, mid: float, span: float, x: float, y: float, c: float, s: float,
    navi_dist: float, out: np.ndarray,
) -> tuple[float, float]:  # fmt: skip
    """MetaDrive's 5 navigation features of the checkpoint at the end of ``lane`` shifted ``mid`` to the right, seen from
    (x, y) with heading (cos, sin) = (c, s), into ``out`` (5,): [forward, left, radius, dir, angle]; its world position."""
    _, _, _, _, direction, radius, is_circ = lanes
    ck_x, ck_y = _lane_position(lanes, lane, length[lane], mid)
    dx, dy = ck_x - x, ck_y - y
    norm = np.hypot(dx, dy)
    scale = navi_dist / max(norm, 1e-9) if norm > navi_dist else 1.0
    dx, dy = dx * scale, dy * scale
    out[0] = ((dx * c + dy * s) / navi_dist + 1) / 2
    out[1] = ((-dx * s + dy * c) / navi_dist + 1) / 2
    circ = is_circ[lane]
    out[2] = radius[lane] / (CURVE_RADIUS_MAX + span) if circ else 0.0
    out[3] = (-direction[lane] + 1) / 2 if circ else 0.5
    out[4] = (np.rad2deg(angle[lane]) / CURVE_ANGLE_MAX_DEG + 1) / 2 if circ else 0.5
    return ck_x, ck_y


@numba.njit(cache=True, error_model="numpy")
def _ego_features(
    lanes: tuple, rows: np.ndarray, is_circ: np.ndarray, roads: tuple, lane_data: tuple, pos: np.ndarray, heading: np.ndarray,
    heading_prev: np.ndarray, speed: np.ndarray, action: np.ndarray, lane: np.ndarray, ref_road: np.ndarray, next_road: np.ndarray,
    max_speed_kmh: float, navi_dist: float, dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    road_first_lane, road_last_lane, road_nlanes = roads
    width, length, angle = lane_data
    n = len(pos)
    out = np.empty((n, 19))
    ck1, ck2 = np.empty((n, 2)), np.empty((n, 2))
    for i in range(n):
        x, y, h = pos[i, 0], pos[i, 1], heading[i]
        ref0, ref_last = road_first_lane[ref_road[i]], road_last_lane[ref_road[i]]
        n_lanes = float(road_nlanes[ref_road[i]])
        w = width[ref0]
        r_ref0 = _lane_sr(rows, is_circ, ref0, x, y)[1]
        r_cur = _lane_sr(rows, is_circ, lane[i], x, y)[1]
        dl = r_ref0 + w / 2
        c, s = np.cos(h), np.sin(h)
        nx, ny = _lane_right_normal(lanes, ref_last, x, y)
        yaw = np.arccos(min(max(c * np.cos(heading_prev[i]) + s * np.sin(heading_prev[i]), 0.0), 1.0)) / dt
        mid = (n_lanes / 2 - 0.5) * w
        span = n_lanes * w
        f = out[i]
        f[0] = dl / MAX_LANE_SPAN
        f[1] = (span - dl) / MAX_LANE_SPAN
        f[2] = 0.5 + 0.5 * (c * nx + s * ny)
        f[3] = (3.6 * speed[i] + 1) / (max_speed_kmh + 1)
        f[4] = (action[i, 0] / STEERING_QUIRK + 1) / 2
        f[5] = (action[i, 0] + 1) / 2
        f[6] = (action[i, 1] + 1) / 2
        f[7] = min(yaw, 1.0)
        f[8] = 0.5 + r_cur / LANE_OFFSET_NORM
        # the checkpoints: the end of the reference road and of the next one, at the reference road's lateral middle
        ck1[i, 0], ck1[i, 1] = _checkpoint(lanes, length, angle, ref0, mid, span, x, y, c, s, navi_dist, f[9:14])
        next0 = road_first_lane[next_road[i]]
        ck2[i, 0], ck2[i, 1] = _checkpoint(lanes, length, angle, next0, mid, span, x, y, c, s, navi_dist, f[14:19])
        for k in range(19):
            f[k] = min(max(f[k], 0.0), 1.0)
    return out, ck1, ck2


def ego_features(
    road_map: RoadMap,
    pos: np.ndarray,
    heading: np.ndarray,
    heading_prev: np.ndarray,
    speed: np.ndarray,
    action: np.ndarray,
    lane: np.ndarray,
    ref_road: np.ndarray,
    next_road: np.ndarray,
    max_speed_kmh: float,
    navi_dist: float,
    dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The 19 ego + navigation features (N, 19) in [0, 1], and both checkpoints (N, 2) each.

    MetaDrive's 9 ego numbers (distances to the reference road's edges, heading error, speed, steering with
    MetaDrive's 1/60 quirk, the action, yaw rate, offset from the lane centre), then the 5 navigation numbers of
    the end of the reference road and of the next road (``_checkpoint``).
    """
    m = road_map
    f = np.float64
    return _ego_features(
        m.lane_arrays, m.lane_rows, m.is_circ, (m.road_first_lane, m.road_last_lane, m.road_nlanes), (m.width, m.length, m.angle),
        np.ascontiguousarray(pos, f), np.ascontiguousarray(heading, f), np.ascontiguousarray(heading_prev, f),
        np.ascontiguousarray(speed, f), np.ascontiguousarray(action, f), np.ascontiguousarray(lane, np.int64),
        np.ascontiguousarray(ref_road, np.int64), np.ascontiguousarray(next_road, np.int64),
        float(max_speed_kmh), float(navi_dist), float(dt),
    )  # fmt: skip


@numba.njit(cache=True)
def _local_state(
    pos: np.ndarray, vel: np.ndarray, heading: np.ndarray, ck1: np.ndarray, ck2: np.ndarray, centre: np.ndarray, scale: float,
    max_speed: float, navi_dist: float,
) -> np.ndarray:  # fmt: skip
    out = np.empty((len(heading), 10), np.float32)
    for i in range(len(heading)):
        x, y = pos[i, 0], pos[i, 1]
        out[i, 0], out[i, 1] = (x - centre[0]) / scale, (y - centre[1]) / scale
        out[i, 2], out[i, 3] = vel[i, 0] / max_speed, vel[i, 1] / max_speed
        out[i, 4], out[i, 5] = np.cos(heading[i]), np.sin(heading[i])
        for k, ck in ((6, ck1), (8, ck2)):  # each checkpoint vector clipped to navi_dist metres, over navi_dist
            dx, dy = ck[i, 0] - x, ck[i, 1] - y
            shrink = min(1.0, navi_dist / max(np.hypot(dx, dy), 1e-9))
            out[i, k], out[i, k + 1] = dx * shrink / navi_dist, dy * shrink / navi_dist
    return out


def local_state(
    pos: np.ndarray,
    vel: np.ndarray,
    heading: np.ndarray,
    ck1: np.ndarray,
    ck2: np.ndarray,
    centre: np.ndarray,
    scale: float,
    max_speed: float,
    navi_dist: float,
) -> np.ndarray:
    """The 10-dim world-frame local state s_i of n vehicles (float32, (n, 10)).

    ``[(p - centre) / scale, v / max_speed, cos h, sin h, (ck1 - p), (ck2 - p)]`` where each
    checkpoint vector is clipped to ``navi_dist`` metres and divided by it.
    """
    f = np.float64
    heading = np.ascontiguousarray(heading, f).reshape(-1)
    n = len(heading)
    pos, vel, ck1, ck2 = (np.ascontiguousarray(a, f).reshape(n, 2) for a in (pos, vel, ck1, ck2))
    centre = np.ascontiguousarray(centre, f).reshape(2)
    return _local_state(pos, vel, heading, ck1, ck2, centre, float(scale), float(max_speed), float(navi_dist))
