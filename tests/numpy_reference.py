"""The simulator's numpy implementations as they were before the compiled kernels (issue 59): the references of the parity tests.

Each function is the former numpy body of the piece named in its docstring, kept verbatim (``self`` is the
object whose method it was), so that the tests can run the old step beside the compiled one.
"""

from __future__ import annotations

import functools

import numpy as np

from coin_app.sim.arena.heuristic import (
    CANDIDATES,
    FILTER_HORIZON,
    FILTER_MARGIN,
    FOOTPRINT_OFFSET,
    FOOTPRINT_RADIUS,
    as_rows,
    entity_views,
    may_come_near,
)
from coin_app.sim.arena.observation import POSITION_SCALE, SIZE_SCALE, SPEED_SCALE
from coin_app.sim.collision import box_axes
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.dynamics import wrap_angle
from coin_app.sim.road_map import RoadMap
from coin_app.sim.sensors import (
    CURVE_ANGLE_MAX_DEG,
    CURVE_RADIUS_MAX,
    LANE_OFFSET_NORM,
    MAX_LANE_SPAN,
    STEERING_QUIRK,
    line_detector,
)
from coin_app.sim.simulator import CKPT_UPDATE_RANGE, EMPTY, DrivingSimulator
from coin_app.sim.vehicle import RaycastVehicles

_ROLL12, _ROLL21, _ROLL121 = np.array([1, 2, 0, 2, 0, 1]), np.array([2, 0, 1, 1, 2, 0]), np.array([1, 2, 0, 2, 0, 1, 1, 2, 0])
_W_ROLL12 = 3 + _ROLL12  # the same rows of the angular part of a stacked (v, w)
# turn_matrices: the product pairs of its off-diagonal entries, and its entries' rows in row-major matrix order
_PAIR_A, _PAIR_B = np.array([0, 1, 0]), np.array([1, 2, 2])
_MATRIX_ORDER = np.array([6, 0, 5, 3, 7, 1, 2, 4, 8])


def turn_matrices(w: np.ndarray, dt: float) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of turning at world angular velocities ``w`` (n, 3) for ``dt`` (the exponential map).

    Rodrigues' formula ``I + sin(a) [k] + (1 - cos(a)) [k]^2`` about the unit axis ``k``: off the diagonal
    ``c1 k_i k_j -+ s k_m``, on it ``1 - c1 (k_j^2 + k_m^2)`` (s = sin(a), c1 = 1 - cos(a)).
    """
    sq = w.T * w.T
    norm = np.sqrt(sq[0] + sq[1] + sq[2])
    angle = norm * dt
    k = w.T / np.maximum(norm, 1e-12)  # rows x, y, z
    s, c1 = np.sin(angle), 1.0 - np.cos(angle)
    kk = k * k
    entries = np.empty((9, len(angle)))  # rows: (0,1), (1,2), (2,0), (1,0), (2,1), (0,2), (0,0), (1,1), (2,2)
    np.add(kk[1], kk[2], out=entries[6])
    np.add(kk[0], kk[2], out=entries[7])
    np.add(kk[0], kk[1], out=entries[8])
    np.subtract(1, c1 * entries[6:], out=entries[6:])
    pairs = (c1 * k)[_PAIR_A] * k[_PAIR_B]  # c1 kx ky, c1 ky kz, c1 kx kz
    skew = s * k[_ROLL21[:3]]  # s kz, s kx, s ky
    np.subtract(pairs, skew, out=entries[:3])
    np.add(pairs, skew, out=entries[3:6])
    return entries.T[:, _MATRIX_ORDER].reshape(-1, 3, 3)


def vehicle_step(
    self, slots: np.ndarray, action: np.ndarray, substeps: int = 5, max_speed_kmh: float = 80.0, max_steer_deg: float = 40.0
) -> tuple[np.ndarray, np.ndarray]:
    """``RaycastVehicles.step`` before the kernel: ``substeps`` physics steps of ``slots`` with ``action`` (n, 2).

    Returns the reported pose of each: position (n, 2) and heading (n,), as MetaDrive reads them.
    The physics runs in the chassis frame (constant connection points, diagonal inertia); the
    state is kept in the world frame. Vectors are stacked on a leading axis (x, y, z) over
    (wheel, vehicle), so that each line below is one array operation for every component,
    wheel and vehicle.
    """
    p = self.p
    connection = np.ascontiguousarray(p.connection.T[:, :, None])  # (3, 4, 1): right, forward, up
    inv_m = 1.0 / p.mass
    inv_inertia_v = 1.0 / np.asarray(p.inertia)
    inv_inertia = inv_inertia_v[:, None, None]
    inv_mass = np.concatenate([np.full(3, inv_m), inv_inertia_v])[:, None]  # (6, 1): of (v, w)
    length_min, length_max = p.suspension_rest - p.suspension_travel, p.suspension_rest + p.suspension_travel
    dt, gdt, ray = p.physics_dt, p.gravity * p.physics_dt, p.suspension_rest + p.wheel_radius
    pos, rot = self.pos[slots], self.rot[slots]
    world_v = self.vel[slots]
    n = len(pos)
    # MetaDrive's _apply_throttle_brake, once per env step: engine off above the speed limit, brake 2.0 unless braking
    fast = np.sqrt(world_v[:, 0] ** 2 + world_v[:, 1] ** 2) * 3.6 > max_speed_kmh
    pedal = action[:, 1]
    engine = np.where(pedal >= 0.0, np.where(fast, 0.0, p.engine_force * pedal), 0.0)
    brake = np.where(pedal >= 0.0, p.coast_brake, -pedal * p.brake_force)
    engine_on, engine_impulse = engine != 0.0, engine * dt
    delta = np.where(p.front[:, None], np.deg2rad(max_steer_deg) * action[:, 0], 0.0)  # (4, n)
    # the wheels' heading in the chassis plane; z = -0.0 so that -0.0 - x is -x to the bit
    wheel_dir = np.stack([np.cos(delta), np.sin(delta), np.full((4, n), -0.0)])
    vw = np.empty((6, n))  # chassis-frame linear and angular velocity
    vw[:3] = np.einsum("nji,nj->ni", rot, world_v).T
    vw[3:] = np.einsum("nji,nj->ni", rot, self.ang[slots]).T
    up = np.empty((3, 4, n))  # world up in the chassis frame, at every wheel
    points = np.empty((2, 3, 4, n))  # contact points and the side impulses' points, relative to the centre of mass
    points[0, :2] = connection[:2]
    r = points[0]
    dirs = np.empty((2, 3, 4, n))  # each wheel's forward direction and axle on the ground
    lift_sums = np.empty((6, 4, n))  # the suspension impulses and their torques, per wheel
    friction_sums = np.empty((2, 6, 4, n))  # the forward and side impulses and their torques, per wheel
    friction = np.empty((2, 4, n))  # the forward and side impulse sizes
    shown_pos, shown_fwd = pos[:, :2], rot[:, :2, 1]
    self.path = np.empty((n, substeps + 1, 3))
    for k in range(substeps):
        self.path[:, k, :2], self.path[:, k, 2] = pos[:, :2], np.arctan2(rot[:, 1, 1], rot[:, 0, 1])
        if k == substeps - 1:  # Bullet's motion state shows the pose before the last integration
            shown_pos, shown_fwd = pos[:, :2].copy(), rot[:, :2, 1].copy()
        vw[:3] -= gdt * rot[:, 2, :].T  # gravity
        v = np.ascontiguousarray(vw[:3].T)
        pos = pos + np.einsum("nij,nj->ni", rot, v) * dt
        turn = turn_matrices(vw[3:].T, dt)  # a body-frame turn: R exp([w] dt)
        rot = rot @ turn
        vw[:3] = np.einsum("nji,nj->ni", turn, v).T  # the same world velocity in the turned frame
        up[:] = rot[:, None, 2, :].T
        nz = up[2]
        # rays straight down the chassis' -z from the connection points to the ground z = 0
        arm = up * connection
        height = pos[:, 2] + arm[0] + arm[1] + arm[2]  # connection points above the ground (4, n)
        steep = nz > 0.1
        upright = steep.all()  # the usual case, and then np.where(steep, x, y) is x
        safe_nz = nz if upright else np.where(steep, nz, 1.0)
        dist = height / safe_nz if upright else np.where(steep, height / safe_nz, np.inf)
        contact = (dist >= 0.0) & (dist <= ray)
        grounded = contact.all()  # the usual case, and then np.where(contact, x, y) is x
        length = np.minimum(np.maximum(dist - p.wheel_radius, length_min), length_max)  # np.clip to the bit
        np.subtract(connection[2], dist if grounded else np.where(contact, dist, ray), out=r[2])  # contact heights
        rr = r[_ROLL121]
        r12, r21 = rr[:6], rr[3:]
        # suspension: spring and damper along the ray, impulse along world up at the contact
        cross = vw[_W_ROLL12, None] * r21
        cv = vw[:3, None] + cross[:3] - cross[3:]  # v + w x r
        inv_cos = 1.0 / safe_nz if upright else np.where(steep, 1.0 / safe_nz, 10.0)
        along = up * cv
        rel_vel = (along[0] + along[1] + along[2]) * inv_cos
        if not upright:
            rel_vel = np.where(steep, rel_vel, 0.0)
        damping = np.where(rel_vel < 0.0, p.damping_compression, p.damping_relaxation)
        force = np.maximum((p.suspension_stiffness * (p.suspension_rest - length) * inv_cos - damping * rel_vel) * p.mass, 0.0)
        if not grounded:
            force = np.where(contact, force, 0.0)
        lift = np.minimum(force, p.max_suspension_force) * dt
        np.multiply(lift, up, out=lift_sums[:3])
        cross = r12 * lift_sums[_ROLL21]
        np.subtract(cross[:3], cross[3:], out=lift_sums[3:])
        vw += lift_sums.sum(1) * inv_mass
        # friction: each wheel's axle and forward direction on the ground
        tilt = wheel_dir[0] * up[0] + wheel_dir[1] * up[1]
        axle = wheel_dir - up * tilt
        sq = axle * axle
        axle = np.divide(axle, np.sqrt(sq[0] + sq[1] + sq[2]), out=dirs[1])
        cross = up[_ROLL12] * axle[_ROLL21]
        np.subtract(cross[:3], cross[3:], out=dirs[0])  # forward: up x axle
        cross = vw[_W_ROLL12, None] * r21
        cv = vw[:3, None] + cross[:3] - cross[3:]
        # Bullet's impulse denominators 1/m + (r x d)^T I^-1 (r x d) (forward, side)
        cross = r12 * dirs[:, _ROLL21]
        moment = cross[:, :3] - cross[:, 3:]
        q = moment * moment * inv_inertia
        den = inv_m + q[:, 0] + q[:, 1] + q[:, 2]
        along = cv * dirs
        slip = along[:, 0] + along[:, 1] + along[:, 2]  # contact point velocity (forward, side)
        side = -p.side_damping * slip[1] / den[1]
        stop = -slip[0] / den[0]  # the impulse that stops the contact point (not shared out)
        rolling = np.where(engine_on, engine_impulse, np.minimum(np.maximum(stop, -brake), brake))  # np.clip to the bit
        if not grounded:
            side, rolling = np.where(contact, side, 0.0), np.where(contact, rolling, 0.0)
        limit = force * dt * p.friction_slip
        demand = (rolling * p.forward_skid_factor) ** 2 + side * side
        skidding = contact & (demand > limit * limit)
        if skidding.any():
            skid = np.where(skidding, limit / np.sqrt(np.where(skidding, demand, 1.0)), 1.0)
            scale = np.where(skidding.any(0) & (side != 0.0) & (skid < 1.0), skid, 1.0)
            rolling, side = rolling * scale, side * scale
        # the forward impulse acts at the contact point; the side one with its height over the ground scaled (roll influence)
        across = up * r
        up_part = (1.0 - p.roll_influence) * (across[0] + across[1] + across[2])
        np.subtract(r, up_part * up, out=points[1])
        friction[0], friction[1] = rolling, side
        impulse = np.multiply(friction[:, None], dirs, out=friction_sums[:, :3])
        cross = points[:, _ROLL12] * impulse[:, _ROLL21]
        np.subtract(cross[:, :3], cross[:, 3:], out=friction_sums[:, 3:])
        total = friction_sums.sum(2) * inv_mass
        vw += total[0]
        vw += total[1]
    self.path[:, substeps, :2], self.path[:, substeps, 2] = pos[:, :2], np.arctan2(rot[:, 1, 1], rot[:, 0, 1])
    self.pos[slots], self.rot[slots] = pos, rot
    self.vel[slots] = np.einsum("nij,nj->ni", rot, np.ascontiguousarray(vw[:3].T))
    self.ang[slots] = np.einsum("nij,nj->ni", rot, np.ascontiguousarray(vw[3:].T))
    return shown_pos, np.arctan2(shown_fwd[:, 1], shown_fwd[:, 0])


def local_coordinates(self, lane: np.ndarray, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``RoadMap.local_coordinates`` before the kernel."""
    row = self.lane_rows[lane]
    rel = pos - row[:, 0:2]
    u = row[:, 2:4]
    s_straight = np.einsum("nd,nd->n", rel, u)
    r_straight = rel[:, 0] * u[:, 1] - rel[:, 1] * u[:, 0]
    delta = pos - row[:, 4:6]
    sp, direc, mid, rad = row[:, 6], row[:, 7], row[:, 8], row[:, 9]
    # wrap around the arc's middle (mid), not its start: MetaDrive wraps around the start,
    # which flips s to negative near the end of its 180-degree U-turn lanes
    dphi = mid + wrap_to_pi(np.arctan2(delta[:, 1], delta[:, 0]) - sp - mid)
    s_circ = direc * dphi * rad
    r_circ = direc * (np.hypot(delta[:, 0], delta[:, 1]) - rad)
    circ = self.is_circ[lane]
    return np.where(circ, s_circ, s_straight), np.where(circ, r_circ, r_straight)


def heading_at(self, lane: np.ndarray, s: np.ndarray) -> np.ndarray:
    """``RoadMap.heading_at`` before the kernel: lane heading (rad) at longitudinal positions ``s``."""
    straight = np.arctan2(self.unit[lane, 1], self.unit[lane, 0])
    direc = self.direction[lane]
    phi = self.start_phase[lane] + direc * s / self.radius[lane]
    return np.where(self.is_circ[lane], phi + direc * np.pi / 2, straight)


def hull_contains(self, pos: np.ndarray, margin: float = 0.05) -> np.ndarray:
    """``RoadMap.hull_contains`` before the kernel: (N, L) bool: point n lies in the on-lane region (convex hull) of lane l."""
    out = np.zeros((len(pos), self.num_lanes), bool)
    vi, li = candidates(self.hull_grid, pos)
    bb, p = self.hull_bbox[li], pos[vi]
    inside_bb = (
        (p[:, 0] >= bb[:, 0] - margin) & (p[:, 0] <= bb[:, 2] + margin) & (p[:, 1] >= bb[:, 1] - margin) & (p[:, 1] <= bb[:, 3] + margin)
    )
    vi, li = vi[inside_bb], li[inside_bb]
    if len(vi):
        proj = np.einsum("ckd,cd->ck", self.hull_normals[li], pos[vi]) - self.hull_offsets[li]
        out[vi, li] = np.all(proj <= margin, axis=1)
    return out


def wrap_to_pi(angle: np.ndarray) -> np.ndarray:
    """Wrap angles to [-pi, pi) (``road_map.wrap_to_pi``)."""
    return (angle + np.pi) % (2 * np.pi) - np.pi


@functools.cache
def _beam_table(n_beams: int) -> tuple[np.ndarray, np.ndarray]:
    """cos and sin of every beam's angle offset."""
    ang = 2 * np.pi * np.arange(n_beams) / n_beams
    return np.cos(ang), np.sin(ang)


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
    """``sensors.lidar_scan`` before the kernel: distances (A, n_beams) from each observer to the nearest box along each beam.

    Beam k points at ``heading + 2 pi k / n_beams`` (CCW; 0 = ahead). The boxes an observer
    can see are given as pairs: observer ``pair_obs[p]`` and a box of half extents ``half``
    at ``pair_center[p]`` with ``pair_heading[p]`` (the caller lists nearby boxes only).
    Each pair is ray-cast only on the beams inside the box's angular extent, so the cost
    grows with the number of nearby pairs, not with beams x vehicles.
    """
    a_n = len(obs_pos)
    out = np.full(a_n * n_beams, max_range)
    if a_n == 0 or len(pair_obs) == 0:
        return out.reshape(a_n, n_beams)
    hl, hw = half
    rad_b = float(np.hypot(hl, hw))  # bounding-circle radius: the range cut
    rel = pair_center - obs_pos[pair_obs]
    d = np.hypot(rel[:, 0], rel[:, 1])
    keep = d < max_range + rad_b
    pair_obs, rel, d, pair_heading = pair_obs[keep], rel[keep], d[keep], pair_heading[keep]
    step = 2 * np.pi / n_beams
    own_h = obs_heading[pair_obs]
    bearing = np.arctan2(rel[:, 1], rel[:, 0]) - own_h
    # observer position in each box's frame, once per pair
    c, s = np.cos(pair_heading), np.sin(pair_heading)
    ox = -(rel[:, 0] * c + rel[:, 1] * s)
    oy = rel[:, 0] * s - rel[:, 1] * c
    # angular half-width of the box seen from the observer, bounded by its extent across
    # the line of sight (p) over its nearest depth along it (d - q)
    inv_d = 1.0 / np.maximum(d, 1e-9)
    p = (hl * np.abs(oy) + hw * np.abs(ox)) * inv_d
    depth = d - (hl * np.abs(ox) + hw * np.abs(oy)) * inv_d
    full = depth <= 1e-6
    half_ang = np.arctan2(p, np.maximum(depth, 1e-6))
    k0 = np.where(full, 0, np.ceil((bearing - half_ang) / step)).astype(np.int64)
    k1 = np.floor((bearing + half_ang) / step).astype(np.int64)
    counts = np.clip(np.where(full, n_beams, k1 - k0 + 1), 0, n_beams)
    total = int(counts.sum())
    if total == 0:
        return out.reshape(a_n, n_beams)
    rel_h = own_h - pair_heading
    pair = np.repeat(np.arange(len(pair_obs)), counts)
    k = np.repeat(k0 - np.cumsum(counts) + counts, counts) + np.arange(total)
    # beam direction in the box frame: angle rel_h + k * step, by angle addition
    kk = k % n_beams
    cr, sr = np.cos(rel_h)[pair], np.sin(rel_h)[pair]
    ck, sk = _beam_table(n_beams)
    dx = cr * ck[kk] - sr * sk[kk]
    dy = sr * ck[kk] + cr * sk[kk]
    oxp, oyp = ox[pair], oy[pair]
    with np.errstate(divide="ignore", invalid="ignore"):
        tx1, tx2 = (-hl - oxp) / dx, (hl - oxp) / dx
        ty1, ty2 = (-hw - oyp) / dy, (hw - oyp) / dy
    t_in = np.maximum(np.minimum(tx1, tx2), np.minimum(ty1, ty2))
    t_out = np.minimum(np.maximum(tx1, tx2), np.maximum(ty1, ty2))
    hit = (t_out >= np.maximum(t_in, 0.0)) & (t_out < np.inf)
    flat = pair_obs[pair[hit]] * n_beams + kk[hit]
    np.minimum.at(out, flat, np.maximum(t_in[hit], 0.0))
    return np.minimum(out, max_range).reshape(a_n, n_beams)


def candidates(self, pos: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``GridIndex.candidates`` before the kernels: (point index, item index) pairs of items near each point (a superset)."""
    c = np.floor((pos - self.origin) / self.cell).astype(np.int64)
    c = np.minimum(np.maximum(c, 0), self.shape - 1)  # np.clip, cheaper on small arrays
    rows = self.table[c[:, 0] * self.shape[1] + c[:, 1]]
    pi, k = np.nonzero(rows >= 0)
    return pi, rows[pi, k]


def boxes_overlap(
    c1: np.ndarray,
    h1: np.ndarray,
    half1: np.ndarray,
    c2: np.ndarray,
    h2: np.ndarray,
    half2: np.ndarray,
) -> np.ndarray:
    """Whether pairs of oriented boxes overlap (separating-axis test); inputs row-aligned.

    ``half1``/``half2`` are (N, 2) half extents (along, across) of each box.
    """
    # in box 1's frame box 1 is axis-aligned; box 2 is rotated by dh = h2 - h1
    c, s = np.cos(h1), np.sin(h1)
    dx, dy = c2[:, 0] - c1[:, 0], c2[:, 1] - c1[:, 1]
    tx, ty = c * dx + s * dy, -s * dx + c * dy
    dh = h2 - h1
    cos_dh, sin_dh = np.cos(dh), np.sin(dh)
    cd, sd = np.abs(cos_dh), np.abs(sin_dh)
    a1, b1, a2, b2 = half1[:, 0], half1[:, 1], half2[:, 0], half2[:, 1]
    overlap = np.abs(tx) <= a1 + a2 * cd + b2 * sd  # box 1's forward axis
    overlap &= np.abs(ty) <= b1 + a2 * sd + b2 * cd  # box 1's left axis
    # box 2's axes: project the centre offset and box 1 onto them
    u = cos_dh * tx + sin_dh * ty
    w = -sin_dh * tx + cos_dh * ty
    overlap &= np.abs(u) <= a2 + a1 * cd + b1 * sd
    overlap &= np.abs(w) <= b2 + a1 * sd + b1 * cd
    return overlap


def footprint_samples(center: np.ndarray, heading: np.ndarray, half_len: float, half_wid: float) -> np.ndarray:
    """Nine points (N, 9, 2) on a box footprint: centre, corners and edge midpoints."""
    fwd, left = box_axes(heading)
    coefs = np.array([[0, 0], [1, 1], [1, -1], [-1, 1], [-1, -1], [1, 0], [-1, 0], [0, 1], [0, -1]], dtype=float)
    return center[:, None, :] + coefs[None, :, 0:1] * half_len * fwd[:, None, :] + coefs[None, :, 1:2] * half_wid * left[:, None, :]


def _localize(self, idx: np.ndarray) -> np.ndarray:
    """``DrivingSimulator._localize`` before the kernels. Update each vehicle's lane and reference road; return whether it is on a lane."""
    m = self.map
    pos, hd = self.pos[idx], self.heading[idx]
    contains = m.hull_contains(pos)
    on_lane = contains.any(1)
    vi, li = np.nonzero(contains)
    key = np.full(contains.shape, np.inf)
    if len(vi):
        s, r = m.local_coordinates(li, pos[vi])
        same_dir = np.cos(m.heading_at(li, s) - hd[vi]) > 0
        l1 = np.abs(r) + np.maximum(s - m.length[li], 0) + np.maximum(-s, 0)
        route = self.route[idx][vi]
        ref = self.ref_idx[idx][vi]
        road = m.lane_road[li]
        cur_road = m.route_roads[route, ref]
        nxt_road = m.route_roads[route, np.minimum(ref + 1, m.route_nroads[route] - 1)]
        prio = np.where(road == cur_road, 0.0, np.where(road == nxt_road, 1.0, 2.0))
        key[vi, li] = np.where(same_dir, prio * 1e6 + l1, np.inf)
    best = key.argmin(1)
    found = np.isfinite(key[np.arange(len(idx)), best])
    lane = np.where(found, best, self.lane[idx])
    self.lane[idx] = lane
    # reference road: switch when the localised lane starts a later road of the route
    s_lane, _ = m.local_coordinates(lane, pos)
    pos_in_route = m.route_road_pos[self.route[idx], m.lane_road[lane]]
    switch = (pos_in_route > self.ref_idx[idx]) & (s_lane < CKPT_UPDATE_RANGE)
    self.ref_idx[idx] = np.where(switch, pos_in_route, self.ref_idx[idx])
    return on_lane


def _touches_solid_line(self, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``DrivingSimulator._touches_solid_line`` before the kernels: whether a footprint touches a solid line box."""
    out = np.zeros(len(pos), bool)
    if self.seg_grid is None or len(pos) == 0:
        return out
    vi, si = candidates(self.seg_grid, pos)
    rel = pos[vi] - self.seg_center[si]
    near = rel[:, 0] ** 2 + rel[:, 1] ** 2 < (self.seg_half[si, 0] + self.half_diag + self.seg_half[si, 1]) ** 2
    vi, si = vi[near], si[near]
    if len(vi):
        hit = boxes_overlap(
            pos[vi], heading[vi], np.broadcast_to(self.half, (len(vi), 2)), self.seg_center[si], self.seg_heading[si], self.seg_half[si]
        )
        np.logical_or.at(out, vi, hit)
    return out


def _on_sidewalk(self, pos: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """``DrivingSimulator._on_sidewalk`` before the kernels. Whether a footprint sample point lies on a sidewalk (triangulated strips)."""
    m = self.map
    out = np.zeros(len(pos), bool)
    if self.sidewalk_grid is None or len(pos) == 0:
        return out
    vi, ti = candidates(self.sidewalk_grid, pos)
    near = np.hypot(*(pos[vi] - self.tri_centroid[ti]).T) < self.tri_radius[ti] + self.half_diag
    vi, ti = vi[near], ti[near]
    if len(vi):
        pts = footprint_samples(pos, heading, self.half[0], self.half[1])[vi]  # (C, 9, 2)
        px, py = pts[..., 0], pts[..., 1]
        nrm, off = m.sidewalk_normals[ti], m.sidewalk_offsets[ti]
        inside = np.ones(px.shape, bool)
        for k in range(nrm.shape[1]):
            inside &= nrm[:, k, 0:1] * px + nrm[:, k, 1:2] * py <= off[:, k : k + 1]
        np.logical_or.at(out, vi, inside.any(1))
    return out


def _crashes(self, poses: np.ndarray) -> np.ndarray:
    """``DrivingSimulator._crashes`` before the kernels. Per slot: whether its box overlaps another active or dying vehicle's box
    at one of the instants of ``poses`` (N, K, 3)."""
    out = np.zeros(self.num_slots, bool)
    e, s = self.num_envs, self.slots_per_env
    live = (self.status != EMPTY).reshape(e, s)
    for k in range(poses.shape[1]):
        p = poses[:, k].reshape(e, s, 3)
        dx = p[:, :, None, 0] - p[:, None, :, 0]
        dy = p[:, :, None, 1] - p[:, None, :, 1]
        close = (dx * dx + dy * dy < (2 * self.half_diag) ** 2) & live[:, None, :] & live[:, :, None]
        ee, i, j = np.nonzero(np.triu(close, 1))
        i, j = ee * s + i, ee * s + j
        if len(i):
            hb = np.broadcast_to(self.half, (len(i), 2))
            flat = poses[:, k]
            hit = boxes_overlap(flat[i, :2], flat[i, 2], hb, flat[j, :2], flat[j, 2], hb)
            out[i[hit]] = True
            out[j[hit]] = True
    return out


def _respawn(self, vacated: np.ndarray, env_ok: np.ndarray) -> np.ndarray:
    """``DrivingSimulator._respawn`` before the kernels. Spawn new agents on free respawn places while under each env's cap; new slots."""
    cfg, m = self.cfg, self.map
    if not cfg.allow_respawn:
        return np.zeros(0, dtype=np.int64)
    e_n, s_n, p_n = self.num_envs, self.slots_per_env, len(self.place_pos)
    live = (self.status != EMPTY).reshape(e_n, s_n)
    allowed = np.where(env_ok & (self.env_step < cfg.horizon), cfg.num_agents - live.sum(1), 0)
    if not (allowed > 0).any():
        return np.zeros(0, dtype=np.int64)
    # which places are blocked by a vehicle of the same env (8 x 3 m box at the place)
    ee, jj = np.nonzero(live & (allowed > 0)[:, None])
    blocked = np.zeros((e_n, p_n), bool)
    if len(ee):
        slot = np.repeat(ee * s_n + jj, p_n)
        pl = np.tile(np.arange(p_n), len(ee))
        hit = boxes_overlap(
            self.place_pos[pl],
            self.place_heading[pl],
            np.broadcast_to(self.place_half, (len(pl), 2)),
            self.pos[slot],
            self.heading[slot],
            np.broadcast_to(self.half, (len(pl), 2)),
        )
        np.logical_or.at(blocked, (np.repeat(ee, p_n), pl), hit)
    free = (self.status == EMPTY) & ~vacated
    new_slots = []
    for e in np.nonzero(allowed > 0)[0]:
        avail = np.nonzero(~blocked[e])[0]
        rows = self.env_slots(int(e))
        slots = rows[free[rows]]
        k = min(int(allowed[e]), len(avail), len(slots), cfg.respawns_per_step or len(slots))  # the per-step cap came later
        if k == 0:
            continue
        places = self.rngs[e].choice(avail, size=k, replace=False)
        self._spawn(slots[:k], m.respawn_lane[places], m.respawn_s[places], np.zeros(k))
        new_slots.append(slots[:k])
    return np.concatenate(new_slots) if new_slots else np.zeros(0, dtype=np.int64)


def observe(self, slots: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``DrivingSimulator.observe`` before the kernels. Observations (n, obs_dim) and local states (n, 10) of the vehicles in ``slots``."""
    cfg, m = self.cfg, self.map
    pos, hd = self.pos[slots], self.heading[slots]
    route, ref = self.route[slots], self.ref_idx[slots]
    ref_road = m.route_roads[route, ref]
    next_road = m.route_roads[route, np.minimum(ref + 1, m.route_nroads[route] - 1)]
    ego, ck1, ck2 = ego_features(
        m, pos, hd, self.heading_prev[slots], self.speed[slots], self.action[slots], self.lane[slots], ref_road, next_road,
        cfg.dynamics.max_speed_kmh, cfg.navi_point_dist, cfg.dynamics.dt,
    )  # fmt: skip
    row = np.full(self.num_slots, -1)
    row[slots] = np.arange(len(slots))
    boxes = self._chassis_poses()  # rays from the shown poses, against the others' chassis
    e, s = self.num_envs, self.slots_per_env
    live = (self.status != EMPTY).reshape(e, s)
    p, b = self.pos.reshape(e, s, 2), boxes[:, :2].reshape(e, s, 2)
    dx = p[:, :, None, 0] - b[:, None, :, 0]
    dy = p[:, :, None, 1] - b[:, None, :, 1]
    close = (dx * dx + dy * dy < (cfg.lidar_range + self.half_diag) ** 2) & live[:, None, :]
    close &= (row >= 0).reshape(e, s)[:, :, None] & ~np.eye(s, dtype=bool)[None]
    ee, i, j = np.nonzero(close)
    po, pb = ee * s + i, ee * s + j
    lidar = lidar_scan(pos, hd, row[po], boxes[pb, :2], boxes[pb, 2], tuple(self.half), cfg.lidar_beams, cfg.lidar_range)
    if cfg.obs_layout == "bottleneck96":  # MetaDrive's bottleneck observation
        hw = m.solid_half_width
        side = line_detector(pos, hd, m.line_p1[m.line_solid], m.line_p2[m.line_solid], hw, cfg.side_detector_range)
        lanes = line_detector(pos, hd, m.line_p1, m.line_p2, hw, cfg.lane_line_detector_range)
        ego = np.concatenate([side, ego[:, 2:8], lanes, ego[:, 9:19]], 1)
    obs = np.concatenate([ego, lidar / cfg.lidar_range], 1).astype(np.float32)
    state = local_state(pos, self.vel[slots], hd, ck1, ck2, m.centre, m.scale, cfg.max_speed, cfg.navi_point_dist)
    return obs, state


def position(self, lane: np.ndarray, s: np.ndarray, r: np.ndarray) -> np.ndarray:
    """``RoadMap.position`` before the kernel: world positions (N, 2) of lane-local coordinates (s, r) on lanes ``lane``."""
    circ = self.is_circ[lane]
    u = self.unit[lane]
    straight = self.start[lane] + u * s[:, None] + np.stack([u[:, 1], -u[:, 0]], 1) * r[:, None]
    direc = self.direction[lane]
    rad = self.radius[lane]
    phi = self.start_phase[lane] + direc * s / rad
    rr = rad + r * direc
    curved = self.center[lane] + rr[:, None] * np.stack([np.cos(phi), np.sin(phi)], 1)
    return np.where(circ[:, None], curved, straight)


def right_normal(self, lane: np.ndarray, pos: np.ndarray) -> np.ndarray:
    """``RoadMap.right_normal`` before the kernel: unit vector pointing to the right of the lane's direction at ``pos``."""
    u = self.unit[lane]
    straight = np.stack([u[:, 1], -u[:, 0]], 1)
    delta = pos - self.center[lane]
    nrm = np.maximum(np.hypot(delta[:, 0], delta[:, 1]), 1e-9)[:, None]
    curved = self.direction[lane][:, None] * delta / nrm
    return np.where(self.is_circ[lane][:, None], curved, straight)


def checkpoint_features(
    road_map: RoadMap,
    ref_lane: np.ndarray,
    mid_offset: np.ndarray,
    lane_span: np.ndarray,
    pos: np.ndarray,
    heading: np.ndarray,
    navi_dist: float,
) -> tuple[np.ndarray, np.ndarray]:
    """``sensors.checkpoint_features`` before the kernel: MetaDrive's 5 navigation features of one checkpoint, and its world position.

    The checkpoint is the end of ``ref_lane`` shifted ``mid_offset`` to the right (the
    lateral middle of the current road); features are [forward, left, radius, dir, angle].
    """
    ck = road_map.position(ref_lane, road_map.length[ref_lane], mid_offset)
    d = ck - pos
    norm = np.hypot(d[:, 0], d[:, 1])
    d = d * np.where(norm > navi_dist, navi_dist / np.maximum(norm, 1e-9), 1.0)[:, None]
    c, s = np.cos(heading), np.sin(heading)
    fwd = (d[:, 0] * c + d[:, 1] * s) / navi_dist
    left = (-d[:, 0] * s + d[:, 1] * c) / navi_dist
    circ = road_map.is_circ[ref_lane]
    radius = np.where(circ, road_map.radius[ref_lane] / (CURVE_RADIUS_MAX + lane_span), 0.0)
    direc = np.where(circ, (-road_map.direction[ref_lane] + 1) / 2, 0.5)
    angle = np.where(circ, (np.rad2deg(road_map.angle[ref_lane]) / CURVE_ANGLE_MAX_DEG + 1) / 2, 0.5)
    feats = np.stack([(fwd + 1) / 2, (left + 1) / 2, radius, direc, angle], 1)
    return feats, ck


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
    """``sensors.ego_features`` before the kernel: the 19 ego + navigation features (N, 19) in [0, 1], and both checkpoints (N, 2) each."""
    ref0 = road_map.road_first_lane[ref_road]
    ref_last = road_map.road_last_lane[ref_road]
    n_lanes = road_map.road_nlanes[ref_road].astype(float)
    w = road_map.width[ref0]
    n = len(pos)
    _, r_both = road_map.local_coordinates(np.concatenate([ref0, lane]), np.concatenate([pos, pos]))  # one call for both
    r_ref0, r_cur = r_both[:n], r_both[n:]
    dl = r_ref0 + w / 2
    hvec = np.stack([np.cos(heading), np.sin(heading)], 1)
    heading_err = 0.5 + 0.5 * np.einsum("nd,nd->n", hvec, road_map.right_normal(ref_last, pos))
    speed_f = (3.6 * speed + 1) / (max_speed_kmh + 1)
    steer_f = (action[:, 0] / STEERING_QUIRK + 1) / 2
    hprev = np.stack([np.cos(heading_prev), np.sin(heading_prev)], 1)
    yaw = np.arccos(np.clip(np.einsum("nd,nd->n", hvec, hprev), 0.0, 1.0)) / dt
    mid = (n_lanes / 2 - 0.5) * w
    span = n_lanes * w
    # both checkpoints in one call: the end of the reference road and of the next one
    two = np.concatenate
    nav, ck = checkpoint_features(
        road_map, two([ref0, road_map.road_first_lane[next_road]]), two([mid, mid]), two([span, span]), two([pos, pos]),
        two([heading, heading]), navi_dist,
    )  # fmt: skip
    nav1, nav2, ck1, ck2 = nav[:n], nav[n:], ck[:n], ck[n:]
    ego = np.stack(
        [
            dl / MAX_LANE_SPAN,
            (span - dl) / MAX_LANE_SPAN,
            heading_err,
            speed_f,
            steer_f,
            (action[:, 0] + 1) / 2,
            (action[:, 1] + 1) / 2,
            np.minimum(yaw, 1.0),
            0.5 + r_cur / LANE_OFFSET_NORM,
        ],
        1,
    )
    return np.clip(np.concatenate([ego, nav1, nav2], 1), 0.0, 1.0), ck1, ck2


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
    """``sensors.local_state`` before the kernel: the 10-dim world-frame local state s_i of n vehicles (float32, (n, 10)).

    ``[(p - centre) / scale, v / max_speed, cos h, sin h, (ck1 - p), (ck2 - p)]`` where each
    checkpoint vector is clipped to ``navi_dist`` metres and divided by it.
    """

    def clip_vec(d: np.ndarray) -> np.ndarray:
        n = np.maximum(np.hypot(d[:, 0], d[:, 1]), 1e-9)
        return d * np.minimum(1.0, navi_dist / n)[:, None] / navi_dist

    return np.concatenate(
        [
            (pos - centre) / scale,
            vel / max_speed,
            np.stack([np.cos(heading), np.sin(heading)], 1),
            clip_vec(ck1 - pos),
            clip_vec(ck2 - pos),
        ],
        1,
    ).astype(np.float32)


class NumpyRoadMap(RoadMap):
    """A road map whose lane queries are the numpy ones before the kernels."""

    local_coordinates = local_coordinates
    heading_at = heading_at
    hull_contains = hull_contains
    position = position
    right_normal = right_normal


class NumpyRaycastVehicles(RaycastVehicles):
    """MetaDrive's car stepped by the numpy step before the kernel."""

    step = vehicle_step


class NumpySimulator(DrivingSimulator):
    """``DrivingSimulator`` as it was before the kernels: every compiled piece replaced by its former numpy body."""

    def __init__(self, config: ScenarioConfig, num_envs: int = 1):
        super().__init__(config, num_envs)
        self.map = NumpyRoadMap(config.scenario)
        self.place_heading = self.map.heading_at(self.map.respawn_lane, self.map.respawn_s)

    def _alloc(self) -> None:
        super()._alloc()
        if self.bodies is not None:
            self.bodies = NumpyRaycastVehicles(self.num_slots)

    _localize = _localize
    _touches_solid_line = _touches_solid_line
    _on_sidewalk = _on_sidewalk
    _crashes = _crashes
    _respawn = _respawn
    observe = observe


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
    """``dynamics.friction_bicycle_step`` before the kernel.

    One step of the seed-2 paper's kinematic bicycle with friction (Eq. 1) for N vehicles.

    Semi-implicit order, as the paper's text describes (the action acts on the very next
    position): ``v' = friction * v + pedal * dt``; ``psi' = psi + v' * tan(steer) * dt / L``
    (wrapped to [-pi, pi)); ``(x, y)' = (x, y) + v' * dt * (cos psi', sin psi')``. The speed
    may be negative (reversing).
    """
    v_new = friction * speed + pedal * dt
    heading_new = wrap_angle(heading + v_new * np.tan(steer) * dt / wheelbase)
    pos_new = pos + (v_new * dt)[:, None] * np.stack([np.cos(heading_new), np.sin(heading_new)], axis=1)
    return pos_new, heading_new, v_new


def rollout_clearance(
    obs: np.ndarray,
    actions: np.ndarray,
    horizon: int,
    dt: float = 0.1,
    friction: float = 0.99,
    wheelbase: float = 2.0,
    max_steer: float = 0.8,
    max_pedal: float = 1.0,
) -> np.ndarray:
    """``arena.heuristic.rollout_clearance`` before the kernel.

    (N, K) least clearance over ``horizon`` steps between each vehicle holding action k of ``actions`` (N, K, 2) and its
    closest entity (moving at its observed speed and heading); inf without an entity. ``obs`` (N, 13): the paper's layout."""
    obs = as_rows(obs)
    n, k = actions.shape[:2]
    speed = np.repeat(obs[:, 4] * SPEED_SCALE, k)  # the rollouts flat, (n * k), for the dynamics
    pos, heading = np.zeros((n * k, 2)), np.zeros(n * k)  # in the vehicle's own frame
    steer = actions[..., 0].reshape(-1) * max_steer
    pedal = actions[..., 1].reshape(-1) * max_pedal
    centre = (obs[:, 6:8] * POSITION_SCALE)[:, None, :]  # (n, 1, 2): broadcast over the k rollouts
    velocity = ((obs[:, 11] * SPEED_SCALE)[:, None] * np.stack([obs[:, 9], obs[:, 8]], 1))[:, None, :]  # (cos, sin)
    reach = (obs[:, 10] * SIZE_SCALE)[:, None] + FOOTPRINT_RADIUS
    least = np.full((n, k), np.inf)
    for t in range(1, horizon + 1):
        pos, heading, speed = friction_bicycle_step(pos, heading, speed, pedal, steer, dt, wheelbase, friction)
        other = centre + t * dt * velocity
        axis = (FOOTPRINT_OFFSET * np.stack([np.cos(heading), np.sin(heading)], 1)).reshape(n, k, 2)
        at = pos.reshape(n, k, 2)
        for sign in (1.0, -1.0):
            least = np.minimum(least, np.linalg.norm(at + sign * axis - other, axis=2) - reach)
    return np.where((obs[:, 12] > 0.5)[:, None], least, np.inf)


def candidate_clearance(
    obs: np.ndarray, horizon: int = FILTER_HORIZON, margin: float = FILTER_MARGIN, dt: float = 0.1, friction: float = 0.99, **physics: float
) -> tuple[np.ndarray, np.ndarray]:
    """``arena.heuristic.candidate_clearance`` before the kernel.

    The planning filter's candidates (N, 22, 2), the plain driver's action first, and each one's least rollout clearance
    (N, 22) over every observed entity (inf where none may come within ``margin``), for observations (N, 6 + 7 k [+ 44]).

    Only the (vehicle, entity) pairs that ``may_come_near`` are rolled out: the others cannot
    come within ``margin``, so a clearance left at inf stands for one of at least ``margin``.
    ``physics``: the arena's ``wheelbase``, ``max_steer`` and ``max_pedal`` where they are not the defaults.
    """
    views = entity_views(obs)
    n = len(views[0])
    nominal = heuristic_actions(views[0], dt=dt, friction=friction, max_steer=physics.get("max_steer", 0.8))
    candidates = np.concatenate([nominal[:, None, :], np.broadcast_to(CANDIDATES, (n, *CANDIDATES.shape))], axis=1)
    clearance = np.full(candidates.shape[:2], np.inf)
    pairs = np.concatenate(views)  # (k N, 13): entity block b of vehicle i at row b N + i
    vehicle = np.tile(np.arange(n), len(views))
    near = may_come_near(pairs, horizon, margin, dt, physics.get("max_pedal", 1.0))
    if near.any():
        least = rollout_clearance(pairs[near], candidates[vehicle[near]], horizon, dt=dt, friction=friction, **physics)
        np.minimum.at(clearance, vehicle[near], least)
    return candidates, clearance


def heuristic_actions(obs: np.ndarray, cruise: float = 4.0, dt: float = 0.1, friction: float = 0.99, max_steer: float = 0.8) -> np.ndarray:
    """``arena.heuristic.heuristic_actions`` before the kernel.

    (steering, pedal) in [-1, 1] for observations (N, 6 + 7 k) (only the target and own numbers are read)."""
    obs = as_rows(obs)
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
