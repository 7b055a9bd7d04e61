"""MetaDrive's car as Bullet simulates it: a vectorized port of ``btRaycastVehicle`` (issue 21).

MetaDrive drives its vehicles with Bullet's raycast vehicle: a rigid chassis (1100 kg, MetaDrive's
inertia) on four raycast wheels with spring-damper suspensions, engine force and brake applied
as per-wheel impulses, and Bullet's friction model (a damped lateral constraint per wheel, clamped
by a friction circle of ``suspension force x friction slip``, which is where the car slides in
hard turns and the rear wheels lock under hard braking). This module steps the same equations
for every vehicle, compiled (Numba), in Bullet's order per physics step of 0.02 s (MetaDrive's
``physics_world_step_size``; 5 per env step, its ``decision_repeat``):

1. gravity: ``v += g dt`` (``integrateVelocities``);
2. ``x += v dt``, ``R = exp([w] dt) R`` (``integrateTransforms``);
3. the vehicle (``btRaycastVehicle::updateVehicle``): a ray per wheel from its chassis
   connection point down to the ground plane z = 0; suspension force
   ``m (k (rest - length) - c v_rel)`` (c: compression or relaxation damping), clamped to
   [0, 6000 N], applied as an impulse at the contact point; then the friction impulses:
   sideways ``-0.2 v_axle / J`` (``resolveSingleBilateral``), forward the engine impulse
   ``F dt`` or, without throttle, the rolling/brake impulse that would stop the contact point,
   clamped to the brake value; if ``(0.5 forward)^2 + side^2`` exceeds
   ``(N dt mu)^2`` the wheel skids and both are scaled down; side impulses act with their
   height above the ground scaled by the roll influence (0.5).

MetaDrive reads poses through Bullet's motion state, which (latency interpolation) shows the
chassis one physics step behind: the pose before the last integration of an env step.
:meth:`RaycastVehicles.step` returns that reported pose, as MetaDrive's ``vehicle.position`` and
``heading_theta``; the velocity is the body's current one, as MetaDrive's ``velocity``.

Every constant is MetaDrive 0.4.3's for its ``DefaultVehicle`` (read from the running engine);
nothing is fitted. Open-loop replay of recorded MetaDrive traces (``coin_app.sim.vehicle_replay``)
stays within 7 mm after 1 s and 5 cm after 3 s (benchmarks/vehicle_parity.py). Frames: world x, y on the
ground, z up; chassis axes right (x), forward (y), up (z), as Bullet's vehicle in MetaDrive.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numba
import numpy as np


@dataclass(frozen=True)
class VehicleParams:
    """MetaDrive 0.4.3's ``DefaultVehicle`` in Bullet (SI units; chassis frame: right, forward, up from the centre of mass)."""

    mass: float = 1100.0
    inertia: tuple[float, float, float] = (1998.45, 444.217, 2183.05)  # about the right, forward and up axes
    half_track: float = 0.815  # lateral offset of each wheel's connection point
    front_axle: float = 1.05234  # forward offset of the front connection points
    rear_axle: float = 1.4166  # backward offset of the rear connection points
    connection_height: float = 0.113  # connection points above the centre of mass
    wheel_radius: float = 0.313
    suspension_rest: float = 0.4
    suspension_travel: float = 0.15  # m either way from rest (Bullet's max travel, 15 cm)
    suspension_stiffness: float = 40.0  # per unit chassis mass, as Bullet multiplies
    damping_relaxation: float = 4.8
    damping_compression: float = 1.2
    max_suspension_force: float = 6000.0  # N per wheel
    friction_slip: float = 0.9
    roll_influence: float = 0.5
    engine_force: float = 800.0  # N per wheel at full throttle (all four wheels driven)
    brake_force: float = 150.0  # brake impulse per wheel and physics step at full brake
    coast_brake: float = 2.0  # MetaDrive's brake value while not braking (rolling resistance)
    side_damping: float = 0.2  # resolveSingleBilateral's contact damping
    forward_skid_factor: float = 0.5  # weight of the forward impulse in the friction circle
    gravity: float = 9.81
    physics_dt: float = 0.02
    spawn_height: float = 0.595  # MetaDrive puts a new vehicle's centre of mass at HEIGHT / 2, at rest
    connection: np.ndarray = field(init=False, repr=False, compare=False)
    front: np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        """The four connection points (front right, front left, rear right, rear left) and the steered ones."""
        w, f, r, h = self.half_track, self.front_axle, self.rear_axle, self.connection_height
        object.__setattr__(self, "connection", np.array([[w, f, h], [-w, f, h], [w, -r, h], [-w, -r, h]]))
        object.__setattr__(self, "front", np.array([True, True, False, False]))


def chassis_basis(heading: np.ndarray, pitch: np.ndarray | float = 0.0, roll: np.ndarray | float = 0.0) -> np.ndarray:
    """Rotation matrices (n, 3, 3) whose columns are the chassis right, forward and up axes; ``heading``: of the forward axis."""
    heading = np.asarray(heading, float)
    pitch = np.broadcast_to(np.asarray(pitch, float), heading.shape)
    roll = np.broadcast_to(np.asarray(roll, float), heading.shape)
    h = heading - np.pi / 2.0  # the chassis' forward axis is its y axis
    ch, sh, cp, sp, cr, sr = np.cos(h), np.sin(h), np.cos(pitch), np.sin(pitch), np.cos(roll), np.sin(roll)
    # Rz(h) @ Rx(pitch) @ Ry(roll)
    return np.stack(
        [
            np.stack([ch * cr - sh * sp * sr, -sh * cp, ch * sr + sh * sp * cr], -1),
            np.stack([sh * cr + ch * sp * sr, ch * cp, sh * sr - ch * sp * cr], -1),
            np.stack([-cp * sr, sp, cp * cr], -1),
        ],
        -2,
    )


@numba.njit(cache=True)
def _turn(wx: float, wy: float, wz: float, dt: float) -> tuple:
    """The 9 entries (row-major) of the rotation of turning at angular velocity (wx, wy, wz) for ``dt``: see ``turn_matrices``."""
    norm = np.sqrt(wx * wx + wy * wy + wz * wz)
    angle = norm * dt
    inv = max(norm, 1e-12)
    kx, ky, kz = wx / inv, wy / inv, wz / inv
    s, c1 = np.sin(angle), 1.0 - np.cos(angle)
    kxx, kyy, kzz = kx * kx, ky * ky, kz * kz
    xy, yz, xz = c1 * kx * ky, c1 * ky * kz, c1 * kx * kz
    sx, sy, sz = s * kx, s * ky, s * kz
    return (1.0 - c1 * (kyy + kzz), xy - sz, xz + sy, xy + sz, 1.0 - c1 * (kxx + kzz), yz - sx, xz - sy, yz + sx, 1.0 - c1 * (kxx + kyy))


@numba.njit(cache=True)
def _turn_all(w: np.ndarray, dt: float) -> np.ndarray:
    out = np.empty((len(w), 3, 3))
    for i in range(len(w)):
        t = _turn(w[i, 0], w[i, 1], w[i, 2], dt)
        for a in range(3):
            for b in range(3):
                out[i, a, b] = t[3 * a + b]
    return out


def turn_matrices(w: np.ndarray, dt: float) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of turning at world angular velocities ``w`` (n, 3) for ``dt`` (the exponential map).

    Rodrigues' formula ``I + sin(a) [k] + (1 - cos(a)) [k]^2`` about the unit axis ``k``: off the diagonal
    ``c1 k_i k_j -+ s k_m``, on it ``1 - c1 (k_j^2 + k_m^2)`` (s = sin(a), c1 = 1 - cos(a)).
    """
    return _turn_all(np.ascontiguousarray(w, dtype=np.float64), float(dt))


class RaycastVehicles:
    """The chassis state of ``n`` vehicles (position, rotation, linear and angular velocity) and Bullet's vehicle step."""

    def __init__(self, n: int, params: VehicleParams | None = None):
        self.p = params or VehicleParams()
        self.pos = np.zeros((n, 3))
        self.rot = np.tile(np.eye(3), (n, 1, 1))
        self.vel = np.zeros((n, 3))
        self.ang = np.zeros((n, 3))
        self.inv_inertia = 1.0 / np.asarray(self.p.inertia)
        self.path = np.zeros((0, 1, 3))

    def place(self, slots: np.ndarray, xy: np.ndarray, heading: np.ndarray, speed: np.ndarray | float = 0.0, settled: bool = False) -> None:
        """Put vehicles at ``xy`` and ``heading``, driving straight at ``speed``.

        ``settled=False``: level at the spawn height, as MetaDrive spawns a car (it then settles
        onto its suspension in about a second). ``settled=True``: already at rest on its suspension
        (the height, pitch and vertical velocity of the equilibrium), as a car driving straight.
        """
        slots = np.atleast_1d(slots)
        heading = np.broadcast_to(np.asarray(heading, float), slots.shape)
        height, pitch, climb = equilibrium(self.p) if settled else (self.p.spawn_height, 0.0, 0.0)
        self.pos[slots, :2] = xy
        self.pos[slots, 2] = height
        self.rot[slots] = chassis_basis(heading, pitch)
        self.vel[slots, 0] = np.cos(heading) * speed
        self.vel[slots, 1] = np.sin(heading) * speed
        self.vel[slots, 2] = climb
        self.ang[slots] = 0.0

    def step(
        self, slots: np.ndarray, action: np.ndarray, substeps: int = 5, max_speed_kmh: float = 80.0, max_steer_deg: float = 40.0
    ) -> tuple[np.ndarray, np.ndarray]:
        """Advance ``slots`` by one env step of ``substeps`` physics steps with ``action`` (n, 2) = [steering, throttle_brake].

        Returns the reported pose of each: position (n, 2) and heading (n,), as MetaDrive reads them.
        Sets :attr:`path` (n, substeps + 1, 3): each one's chassis pose (x, y, heading) before each
        physics step and after the last, the poses Bullet's collision tests see.
        The physics runs in the chassis frame (constant connection points, diagonal inertia); the
        state is kept in the world frame (``_raycast_step``, compiled).
        """
        slots = np.ascontiguousarray(np.atleast_1d(slots), dtype=np.int64)
        action = np.ascontiguousarray(action, dtype=np.float64).reshape(len(slots), 2)
        self.path = np.empty((len(slots), int(substeps) + 1, 3))
        return _raycast_step(
            self.pos,
            self.rot,
            self.vel,
            self.ang,
            slots,
            action,
            self.path,
            int(substeps),
            float(max_speed_kmh),
            float(max_steer_deg),
            _constants(self.p),
        )


@functools.cache
def _constants(p: VehicleParams) -> np.ndarray:
    """The kernel's constants of ``p`` in the order ``_raycast_step`` reads them."""
    return np.array(
        [
            p.mass, *p.inertia, p.wheel_radius, p.suspension_rest, p.suspension_travel, p.suspension_stiffness, p.damping_relaxation,
            p.damping_compression, p.max_suspension_force, p.friction_slip, p.roll_influence, p.engine_force, p.brake_force,
            p.coast_brake, p.side_damping, p.forward_skid_factor, p.gravity, p.physics_dt, *p.connection.reshape(-1),
        ]
    )  # fmt: skip


@numba.njit(cache=True)
def _raycast_step(
    pos_all: np.ndarray,
    rot_all: np.ndarray,
    vel_all: np.ndarray,
    ang_all: np.ndarray,
    slots: np.ndarray,
    action: np.ndarray,
    path: np.ndarray,
    substeps: int,
    max_speed_kmh: float,
    max_steer_deg: float,
    c: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Bullet's vehicle step (module doc) for the vehicles ``slots``, in place; their reported poses (n, 2) and headings (n,).
    ``path`` (n, substeps + 1, 3) receives each one's pose (x, y, heading) before every physics step and after the last.

    One vehicle at a time, in Bullet's order; per wheel: the ray, the suspension impulse, then the friction impulses.
    """
    mass, inertia = c[0], c[1:4]
    wheel_radius, rest, travel, stiffness, relax, compress, max_force = c[4], c[5], c[6], c[7], c[8], c[9], c[10]
    friction_slip, roll_influence, engine_force, brake_force, coast_brake, side_damping, skid_factor = c[11:18]
    gravity, dt = c[18], c[19]
    conn = c[20:32].reshape(4, 3)  # front right, front left, rear right, rear left: right, forward, up
    inv_m = 1.0 / mass
    inv_mass = np.array([inv_m, inv_m, inv_m, 1.0 / inertia[0], 1.0 / inertia[1], 1.0 / inertia[2]])
    gdt, ray = gravity * dt, rest + wheel_radius
    length_min, length_max = rest - travel, rest + travel
    n = len(slots)
    shown_xy = np.empty((n, 2))
    shown_heading = np.empty(n)
    rot = np.empty((3, 3))
    vw = np.empty(6)  # chassis-frame linear and angular velocity
    up = np.empty(3)  # world up in the chassis frame
    r = np.empty((4, 3))  # contact points relative to the centre of mass
    force = np.empty(4)
    fwd = np.empty((4, 3))
    axle = np.empty((4, 3))
    rolling = np.empty(4)
    side = np.empty(4)
    contact = np.empty(4, np.bool_)
    sums = np.empty(6)
    side_sums = np.empty(6)
    for i in range(n):
        sl = slots[i]
        px, py, pz = pos_all[sl, 0], pos_all[sl, 1], pos_all[sl, 2]
        rot[:] = rot_all[sl]
        vx, vy = vel_all[sl, 0], vel_all[sl, 1]
        # MetaDrive's _apply_throttle_brake, once per env step: engine off above the speed limit, brake 2.0 unless braking
        fast = np.sqrt(vx**2 + vy**2) * 3.6 > max_speed_kmh
        steer, pedal = action[i, 0], action[i, 1]
        engine = (0.0 if fast else engine_force * pedal) if pedal >= 0.0 else 0.0
        brake = coast_brake if pedal >= 0.0 else -pedal * brake_force
        engine_on, engine_impulse = engine != 0.0, engine * dt
        delta = np.deg2rad(max_steer_deg) * steer
        cos_d, sin_d = np.cos(delta), np.sin(delta)
        for a in range(3):
            vw[a] = rot[0, a] * vel_all[sl, 0] + rot[1, a] * vel_all[sl, 1] + rot[2, a] * vel_all[sl, 2]
            vw[3 + a] = rot[0, a] * ang_all[sl, 0] + rot[1, a] * ang_all[sl, 1] + rot[2, a] * ang_all[sl, 2]
        shown_px, shown_py, shown_fx, shown_fy = px, py, rot[0, 1], rot[1, 1]
        for k in range(substeps):
            path[i, k, 0], path[i, k, 1], path[i, k, 2] = px, py, np.arctan2(rot[1, 1], rot[0, 1])
            if k == substeps - 1:  # Bullet's motion state shows the pose before the last integration
                shown_px, shown_py, shown_fx, shown_fy = px, py, rot[0, 1], rot[1, 1]
            for a in range(3):  # gravity
                vw[a] -= gdt * rot[2, a]
            v0, v1, v2 = vw[0], vw[1], vw[2]
            px += (rot[0, 0] * v0 + rot[0, 1] * v1 + rot[0, 2] * v2) * dt
            py += (rot[1, 0] * v0 + rot[1, 1] * v1 + rot[1, 2] * v2) * dt
            pz += (rot[2, 0] * v0 + rot[2, 1] * v1 + rot[2, 2] * v2) * dt
            t = _turn(vw[3], vw[4], vw[5], dt)  # a body-frame turn: R exp([w] dt)
            for a in range(3):
                r0, r1, r2 = rot[a, 0], rot[a, 1], rot[a, 2]
                rot[a, 0] = r0 * t[0] + r1 * t[3] + r2 * t[6]
                rot[a, 1] = r0 * t[1] + r1 * t[4] + r2 * t[7]
                rot[a, 2] = r0 * t[2] + r1 * t[5] + r2 * t[8]
            for a in range(3):  # the same world velocity in the turned frame
                vw[a] = t[a] * v0 + t[3 + a] * v1 + t[6 + a] * v2
            up[0], up[1], up[2] = rot[2, 0], rot[2, 1], rot[2, 2]
            nz = up[2]
            steep = nz > 0.1
            safe_nz = nz if steep else 1.0
            inv_cos = 1.0 / safe_nz if steep else 10.0
            sums[:] = 0.0
            for w in range(4):
                # a ray straight down the chassis' -z from the connection point to the ground z = 0
                height = pz + up[0] * conn[w, 0] + up[1] * conn[w, 1] + up[2] * conn[w, 2]
                dist = height / safe_nz if steep else np.inf
                contact[w] = (dist >= 0.0) and (dist <= ray)
                length = min(max(dist - wheel_radius, length_min), length_max)
                r[w, 0], r[w, 1] = conn[w, 0], conn[w, 1]
                r[w, 2] = conn[w, 2] - (dist if contact[w] else ray)
                # suspension: spring and damper along the ray, impulse along world up at the contact
                cv0 = vw[0] + vw[4] * r[w, 2] - vw[5] * r[w, 1]  # v + w x r
                cv1 = vw[1] + vw[5] * r[w, 0] - vw[3] * r[w, 2]
                cv2 = vw[2] + vw[3] * r[w, 1] - vw[4] * r[w, 0]
                rel_vel = (up[0] * cv0 + up[1] * cv1 + up[2] * cv2) * inv_cos if steep else 0.0
                damping = compress if rel_vel < 0.0 else relax
                f = max((stiffness * (rest - length) * inv_cos - damping * rel_vel) * mass, 0.0)
                force[w] = f if contact[w] else 0.0
                lift = min(force[w], max_force) * dt
                l0, l1, l2 = lift * up[0], lift * up[1], lift * up[2]
                sums[0] += l0
                sums[1] += l1
                sums[2] += l2
                sums[3] += r[w, 1] * l2 - r[w, 2] * l1
                sums[4] += r[w, 2] * l0 - r[w, 0] * l2
                sums[5] += r[w, 0] * l1 - r[w, 1] * l0
            for a in range(6):
                vw[a] += sums[a] * inv_mass[a]
            for w in range(4):
                # friction: the wheel's axle and forward direction on the ground
                wd0, wd1 = (cos_d, sin_d) if w < 2 else (1.0, 0.0)
                tilt = wd0 * up[0] + wd1 * up[1]
                a0, a1, a2 = wd0 - up[0] * tilt, wd1 - up[1] * tilt, -0.0 - up[2] * tilt
                norm = np.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
                a0, a1, a2 = a0 / norm, a1 / norm, a2 / norm
                axle[w, 0], axle[w, 1], axle[w, 2] = a0, a1, a2
                f0, f1, f2 = up[1] * a2 - up[2] * a1, up[2] * a0 - up[0] * a2, up[0] * a1 - up[1] * a0  # forward: up x axle
                fwd[w, 0], fwd[w, 1], fwd[w, 2] = f0, f1, f2
                r0, r1, r2 = r[w, 0], r[w, 1], r[w, 2]
                cv0 = vw[0] + vw[4] * r2 - vw[5] * r1
                cv1 = vw[1] + vw[5] * r0 - vw[3] * r2
                cv2 = vw[2] + vw[3] * r1 - vw[4] * r0
                # Bullet's impulse denominators 1/m + (r x d)^T I^-1 (r x d) (forward, side)
                m0, m1, m2 = r1 * f2 - r2 * f1, r2 * f0 - r0 * f2, r0 * f1 - r1 * f0
                den_f = inv_m + m0 * m0 * inv_mass[3] + m1 * m1 * inv_mass[4] + m2 * m2 * inv_mass[5]
                m0, m1, m2 = r1 * a2 - r2 * a1, r2 * a0 - r0 * a2, r0 * a1 - r1 * a0
                den_s = inv_m + m0 * m0 * inv_mass[3] + m1 * m1 * inv_mass[4] + m2 * m2 * inv_mass[5]
                slip_f = cv0 * f0 + cv1 * f1 + cv2 * f2  # contact point velocity (forward, side)
                slip_s = cv0 * a0 + cv1 * a1 + cv2 * a2
                if contact[w]:
                    side[w] = -side_damping * slip_s / den_s
                    stop = -slip_f / den_f  # the impulse that stops the contact point (not shared out)
                    rolling[w] = engine_impulse if engine_on else min(max(stop, -brake), brake)
                else:
                    side[w], rolling[w] = 0.0, 0.0
            for w in range(4):
                limit = force[w] * dt * friction_slip
                demand = (rolling[w] * skid_factor) ** 2 + side[w] * side[w]
                if contact[w] and demand > limit * limit and side[w] != 0.0:
                    skid = limit / np.sqrt(demand)
                    if skid < 1.0:
                        rolling[w] *= skid
                        side[w] *= skid
            # the forward impulse acts at the contact point; the side one with its height over the ground scaled (roll influence)
            sums[:] = 0.0
            for w in range(4):
                i0, i1, i2 = rolling[w] * fwd[w, 0], rolling[w] * fwd[w, 1], rolling[w] * fwd[w, 2]
                sums[0] += i0
                sums[1] += i1
                sums[2] += i2
                sums[3] += r[w, 1] * i2 - r[w, 2] * i1
                sums[4] += r[w, 2] * i0 - r[w, 0] * i2
                sums[5] += r[w, 0] * i1 - r[w, 1] * i0
            side_sums[:] = 0.0
            for w in range(4):
                up_part = (1.0 - roll_influence) * (up[0] * r[w, 0] + up[1] * r[w, 1] + up[2] * r[w, 2])
                q0, q1, q2 = r[w, 0] - up_part * up[0], r[w, 1] - up_part * up[1], r[w, 2] - up_part * up[2]
                i0, i1, i2 = side[w] * axle[w, 0], side[w] * axle[w, 1], side[w] * axle[w, 2]
                side_sums[0] += i0
                side_sums[1] += i1
                side_sums[2] += i2
                side_sums[3] += q1 * i2 - q2 * i1
                side_sums[4] += q2 * i0 - q0 * i2
                side_sums[5] += q0 * i1 - q1 * i0
            for a in range(6):
                vw[a] += sums[a] * inv_mass[a]
            for a in range(6):
                vw[a] += side_sums[a] * inv_mass[a]
        pos_all[sl, 0], pos_all[sl, 1], pos_all[sl, 2] = px, py, pz
        path[i, substeps, 0], path[i, substeps, 1], path[i, substeps, 2] = px, py, np.arctan2(rot[1, 1], rot[0, 1])
        rot_all[sl] = rot
        for a in range(3):
            vel_all[sl, a] = rot[a, 0] * vw[0] + rot[a, 1] * vw[1] + rot[a, 2] * vw[2]
            ang_all[sl, a] = rot[a, 0] * vw[3] + rot[a, 1] * vw[4] + rot[a, 2] * vw[5]
        shown_xy[i, 0], shown_xy[i, 1] = shown_px, shown_py
        shown_heading[i] = np.arctan2(shown_fy, shown_fx)
    return shown_xy, shown_heading


@functools.cache
def equilibrium(params: VehicleParams) -> tuple[float, float, float]:
    """(height, pitch, vertical velocity) of a car at rest on its suspension: 3 s after a spawn, on flat ground."""
    probe = RaycastVehicles(1, params)
    probe.place(np.array([0]), np.zeros((1, 2)), np.zeros(1))
    for _ in range(30):
        probe.step(np.array([0]), np.zeros((1, 2)))
    return float(probe.pos[0, 2]), float(np.arcsin(probe.rot[0, 2, 1])), float(probe.vel[0, 2])
