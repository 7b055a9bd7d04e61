"""MetaDrive's car as Bullet simulates it: a vectorized port of ``btRaycastVehicle`` (issue 21).

MetaDrive drives its vehicles with Bullet's raycast vehicle: a rigid chassis (1100 kg, MetaDrive's
inertia) on four raycast wheels with spring-damper suspensions, engine force and brake applied
as per-wheel impulses, and Bullet's friction model (a damped lateral constraint per wheel, clamped
by a friction circle of ``suspension force x friction slip``, which is where the car slides in
hard turns and the rear wheels lock under hard braking). This module steps the same equations
for every vehicle at once, in numpy, in Bullet's order per physics step of 0.02 s (MetaDrive's
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


def turn_matrices(w: np.ndarray, dt: float) -> np.ndarray:
    """Rotation matrices (n, 3, 3) of turning at world angular velocities ``w`` (n, 3) for ``dt`` (the exponential map)."""
    norm = np.sqrt((w * w).sum(1))
    angle = norm * dt
    k = w / np.maximum(norm, 1e-12)[:, None]
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    s, c1 = np.sin(angle), 1.0 - np.cos(angle)
    return np.stack(
        [
            np.stack([1 - c1 * (ky * ky + kz * kz), -s * kz + c1 * kx * ky, s * ky + c1 * kx * kz], -1),
            np.stack([s * kz + c1 * kx * ky, 1 - c1 * (kx * kx + kz * kz), -s * kx + c1 * ky * kz], -1),
            np.stack([-s * ky + c1 * kx * kz, s * kx + c1 * ky * kz, 1 - c1 * (kx * kx + ky * ky)], -1),
        ],
        -2,
    )


class RaycastVehicles:
    """The chassis state of ``n`` vehicles (position, rotation, linear and angular velocity) and Bullet's vehicle step."""

    def __init__(self, n: int, params: VehicleParams | None = None):
        self.p = params or VehicleParams()
        self.pos = np.zeros((n, 3))
        self.rot = np.tile(np.eye(3), (n, 1, 1))
        self.vel = np.zeros((n, 3))
        self.ang = np.zeros((n, 3))
        self.inv_inertia = 1.0 / np.asarray(self.p.inertia)

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
        The physics runs in the chassis frame (constant connection points, diagonal inertia); the
        state is kept in the world frame.
        """
        p = self.p
        dt, g, inv_m = p.physics_dt, p.gravity, 1.0 / p.mass
        inv_ix, inv_iy, inv_iz = self.inv_inertia
        rx, ry, hz = p.connection[:, 0], p.connection[:, 1], p.connection[:, 2]  # (4,) chassis frame
        pos, rot = self.pos[slots], self.rot[slots]
        world_v = self.vel[slots]
        # MetaDrive's _apply_throttle_brake, once per env step: engine off above the speed limit, brake 2.0 unless braking
        fast = np.sqrt(world_v[:, 0] ** 2 + world_v[:, 1] ** 2) * 3.6 > max_speed_kmh
        pedal = action[:, 1]
        engine = np.where(pedal >= 0.0, np.where(fast, 0.0, p.engine_force * pedal), 0.0)[:, None]
        brake = np.where(pedal >= 0.0, p.coast_brake, -pedal * p.brake_force)[:, None]
        delta = np.where(p.front[None, :], np.deg2rad(max_steer_deg) * action[:, 0:1], 0.0)  # (n, 4)
        cos_d, sin_d = np.cos(delta), np.sin(delta)
        v = np.einsum("nji,nj->ni", rot, world_v)  # chassis-frame velocities
        w = np.einsum("nji,nj->ni", rot, self.ang[slots])
        vx, vy, vz, wx, wy, wz = v[:, 0], v[:, 1], v[:, 2], w[:, 0], w[:, 1], w[:, 2]
        ray = p.suspension_rest + p.wheel_radius
        shown_pos, shown_fwd = pos[:, :2], rot[:, :2, 1]
        for k in range(substeps):
            if k == substeps - 1:  # Bullet's motion state shows the pose before the last integration
                shown_pos, shown_fwd = pos[:, :2].copy(), rot[:, :2, 1].copy()
            nx, ny, nz = rot[:, 2, 0], rot[:, 2, 1], rot[:, 2, 2]  # world up in the chassis frame
            vx, vy, vz = vx - g * dt * nx, vy - g * dt * ny, vz - g * dt * nz  # gravity
            world = np.einsum("nij,nj->ni", rot, np.stack([vx, vy, vz], 1))
            pos = pos + world * dt
            turn = turn_matrices(np.stack([wx, wy, wz], 1), dt)  # a body-frame turn: R exp([w] dt)
            rot = rot @ turn
            v = np.einsum("nji,nj->ni", turn, np.stack([vx, vy, vz], 1))  # the same world velocity in the turned frame
            vx, vy, vz = v[:, 0], v[:, 1], v[:, 2]
            nx, ny, nz = rot[:, 2, 0:1], rot[:, 2, 1:2], rot[:, 2, 2:3]  # (n, 1)
            # rays straight down the chassis' -z from the connection points to the ground z = 0
            height = pos[:, 2:3] + nx * rx + ny * ry + nz * hz  # connection points above the ground (n, 4)
            steep = nz > 0.1
            dist = np.where(steep, height / np.where(steep, nz, 1.0), np.inf)
            contact = (dist >= 0.0) & (dist <= ray)
            length = np.clip(dist - p.wheel_radius, p.suspension_rest - p.suspension_travel, p.suspension_rest + p.suspension_travel)
            rz = hz - np.where(contact, dist, ray)  # contact points relative to the centre of mass: (rx, ry, rz)
            # suspension: spring and damper along the ray, impulse along world up at the contact
            cvx, cvy, cvz = _point_velocity(vx, vy, vz, wx, wy, wz, rx, ry, rz)
            inv_cos = np.where(steep, 1.0 / np.where(steep, nz, 1.0), 10.0)
            rel_vel = np.where(steep, (nx * cvx + ny * cvy + nz * cvz) * inv_cos, 0.0)
            damping = np.where(rel_vel < 0.0, p.damping_compression, p.damping_relaxation)
            force = (p.suspension_stiffness * (p.suspension_rest - length) * inv_cos - damping * rel_vel) * p.mass
            force = np.where(contact, np.maximum(force, 0.0), 0.0)
            lift = np.minimum(force, p.max_suspension_force) * dt
            vx, vy, vz, wx, wy, wz = _impulses(vx, vy, vz, wx, wy, wz, lift, nx, ny, nz, rx, ry, rz, inv_m, inv_ix, inv_iy, inv_iz)
            # friction: each wheel's axle and forward direction on the ground
            ax, ay, az = cos_d - nx * (cos_d * nx + sin_d * ny), sin_d - ny * (cos_d * nx + sin_d * ny), -nz * (cos_d * nx + sin_d * ny)
            norm = np.sqrt(ax * ax + ay * ay + az * az)
            ax, ay, az = ax / norm, ay / norm, az / norm
            fx, fy, fz = ny * az - nz * ay, nz * ax - nx * az, nx * ay - ny * ax  # up x axle
            cvx, cvy, cvz = _point_velocity(vx, vy, vz, wx, wy, wz, rx, ry, rz)
            den_side = _denominator(ax, ay, az, rx, ry, rz, inv_m, inv_ix, inv_iy, inv_iz)
            side = np.where(contact, -p.side_damping * (cvx * ax + cvy * ay + cvz * az) / den_side, 0.0)
            den_fwd = _denominator(fx, fy, fz, rx, ry, rz, inv_m, inv_ix, inv_iy, inv_iz)
            stop = -(cvx * fx + cvy * fy + cvz * fz) / den_fwd  # the impulse that stops the contact point (not shared out)
            rolling = np.where(contact, np.where(engine != 0.0, engine * dt, np.clip(stop, -brake, brake)), 0.0)
            limit = force * dt * p.friction_slip
            demand = (rolling * p.forward_skid_factor) ** 2 + side * side
            skidding = contact & (demand > limit * limit)
            skid = np.where(skidding, limit / np.sqrt(np.where(skidding, demand, 1.0)), 1.0)
            scale = np.where(skidding.any(1, keepdims=True) & (side != 0.0) & (skid < 1.0), skid, 1.0)
            rolling, side = rolling * scale, side * scale
            # the forward impulse acts at the contact point; the side one with its height over the ground scaled (roll influence)
            up_part = (1.0 - p.roll_influence) * (nx * rx + ny * ry + nz * rz)
            sx, sy, sz = rx - up_part * nx, ry - up_part * ny, rz - up_part * nz
            vx, vy, vz, wx, wy, wz = _impulses(vx, vy, vz, wx, wy, wz, rolling, fx, fy, fz, rx, ry, rz, inv_m, inv_ix, inv_iy, inv_iz)
            vx, vy, vz, wx, wy, wz = _impulses(vx, vy, vz, wx, wy, wz, side, ax, ay, az, sx, sy, sz, inv_m, inv_ix, inv_iy, inv_iz)
        self.pos[slots], self.rot[slots] = pos, rot
        self.vel[slots] = np.einsum("nij,nj->ni", rot, np.stack([vx, vy, vz], 1))
        self.ang[slots] = np.einsum("nij,nj->ni", rot, np.stack([wx, wy, wz], 1))
        return shown_pos, np.arctan2(shown_fwd[:, 1], shown_fwd[:, 0])


@functools.cache
def equilibrium(params: VehicleParams) -> tuple[float, float, float]:
    """(height, pitch, vertical velocity) of a car at rest on its suspension: 3 s after a spawn, on flat ground."""
    probe = RaycastVehicles(1, params)
    probe.place(np.array([0]), np.zeros((1, 2)), np.zeros(1))
    for _ in range(30):
        probe.step(np.array([0]), np.zeros((1, 2)))
    return float(probe.pos[0, 2]), float(np.arcsin(probe.rot[0, 2, 1])), float(probe.vel[0, 2])


def _point_velocity(
    vx: np.ndarray, vy: np.ndarray, vz: np.ndarray, wx: np.ndarray, wy: np.ndarray, wz: np.ndarray,
    rx: np.ndarray, ry: np.ndarray, rz: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """Velocity v + w x r of the chassis at the points r (n, 4), all in the chassis frame."""
    vx, vy, vz, wx, wy, wz = vx[:, None], vy[:, None], vz[:, None], wx[:, None], wy[:, None], wz[:, None]
    return vx + wy * rz - wz * ry, vy + wz * rx - wx * rz, vz + wx * ry - wy * rx


def _denominator(
    dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, rx: np.ndarray, ry: np.ndarray, rz: np.ndarray,
    inv_m: float, inv_ix: float, inv_iy: float, inv_iz: float,
) -> np.ndarray:  # fmt: skip
    """Bullet's impulse denominator 1/m + (r x d)^T I^-1 (r x d) for directions d at points r (chassis frame, diagonal I)."""
    cx, cy, cz = ry * dz - rz * dy, rz * dx - rx * dz, rx * dy - ry * dx
    return inv_m + cx * cx * inv_ix + cy * cy * inv_iy + cz * cz * inv_iz


def _impulses(
    vx: np.ndarray, vy: np.ndarray, vz: np.ndarray, wx: np.ndarray, wy: np.ndarray, wz: np.ndarray,
    j: np.ndarray, dx: np.ndarray, dy: np.ndarray, dz: np.ndarray, rx: np.ndarray, ry: np.ndarray, rz: np.ndarray,
    inv_m: float, inv_ix: float, inv_iy: float, inv_iz: float,
) -> tuple[np.ndarray, ...]:  # fmt: skip
    """Chassis velocities after impulses of size j (n, 4) along d at the points r (chassis frame)."""
    px, py, pz = j * dx, j * dy, j * dz
    tx, ty, tz = ry * pz - rz * py, rz * px - rx * pz, rx * py - ry * px
    return (
        vx + px.sum(1) * inv_m, vy + py.sum(1) * inv_m, vz + pz.sum(1) * inv_m,
        wx + tx.sum(1) * inv_ix, wy + ty.sum(1) * inv_iy, wz + tz.sum(1) * inv_iz,
    )  # fmt: skip
