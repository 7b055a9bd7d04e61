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

# cross products of vectors stacked on a leading axis (x, y, z): a x b = a[_ROLL1] * b[_ROLL2] - a[_ROLL2] * b[_ROLL1]
_ROLL1, _ROLL2 = np.array([1, 2, 0]), np.array([2, 0, 1])
_W_ROLL1, _W_ROLL2 = 3 + _ROLL1, 3 + _ROLL2  # the same rows of the angular part of a stacked (v, w)
# turn_matrices' entries of a flattened 3 x 3 matrix: the diagonal; the off-diagonals' skew axis, sign and product pair
_DIAGONAL, _DIAG_A, _DIAG_B = np.array([0, 4, 8]), np.array([1, 0, 0]), np.array([2, 2, 1])
_OFF_DIAGONAL = np.array([1, 2, 3, 5, 6, 7])
_SKEW_AXIS, _SKEW_SIGN = np.array([2, 1, 2, 0, 1, 0]), np.array([-1.0, 1.0, 1.0, -1.0, -1.0, 1.0])
_PAIR_A, _PAIR_B = np.array([0, 0, 0, 1, 0, 1]), np.array([1, 2, 1, 2, 2, 2])


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
    """Rotation matrices (n, 3, 3) of turning at world angular velocities ``w`` (n, 3) for ``dt`` (the exponential map).

    Rodrigues' formula ``I + sin(a) [k] + (1 - cos(a)) [k]^2`` about the unit axis ``k``, written
    entry by entry: the diagonal ``1 - c1 (k_j^2 + k_k^2)``, the off-diagonals ``+-s k_m + c1 k_a k_b``.
    """
    norm = np.sqrt((w * w).sum(1))
    angle = norm * dt
    k = w / np.maximum(norm, 1e-12)[:, None]
    s, c1 = np.sin(angle)[:, None], 1.0 - np.cos(angle)[:, None]
    sq = k * k
    out = np.empty((len(w), 9))
    out[:, _DIAGONAL] = 1 - c1 * (sq[:, _DIAG_A] + sq[:, _DIAG_B])
    out[:, _OFF_DIAGONAL] = (s * k)[:, _SKEW_AXIS] * _SKEW_SIGN + (c1 * k)[:, _PAIR_A] * k[:, _PAIR_B]
    return out.reshape(-1, 3, 3)


class RaycastVehicles:
    """The chassis state of ``n`` vehicles (position, rotation, linear and angular velocity) and Bullet's vehicle step."""

    def __init__(self, n: int, params: VehicleParams | None = None):
        self.p = params or VehicleParams()
        self.pos = np.zeros((n, 3))
        self.rot = np.tile(np.eye(3), (n, 1, 1))
        self.vel = np.zeros((n, 3))
        self.ang = np.zeros((n, 3))
        self.inv_inertia = 1.0 / np.asarray(self.p.inertia)
        # constants of the step, shaped for the stacked (component, vehicle, wheel) arrays
        self._connection = np.ascontiguousarray(self.p.connection.T[:, None, :])  # (3, 1, 4): right, forward, up
        self._inv_m = 1.0 / self.p.mass
        self._inv_inertia = self.inv_inertia[:, None, None]
        self._inv_mass = np.concatenate([np.full(3, self._inv_m), self.inv_inertia])[:, None]  # (6, 1): of (v, w)
        self._length_min = self.p.suspension_rest - self.p.suspension_travel
        self._length_max = self.p.suspension_rest + self.p.suspension_travel

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
        state is kept in the world frame. Vectors are stacked on a leading axis of 3 (x, y, z)
        over (vehicle, wheel), so that each line below is one array operation for every
        component, wheel and vehicle.
        """
        p = self.p
        dt, gdt, ray = p.physics_dt, p.gravity * p.physics_dt, p.suspension_rest + p.wheel_radius
        pos, rot = self.pos[slots], self.rot[slots]
        world_v = self.vel[slots]
        n = len(pos)
        # MetaDrive's _apply_throttle_brake, once per env step: engine off above the speed limit, brake 2.0 unless braking
        fast = np.sqrt(world_v[:, 0] ** 2 + world_v[:, 1] ** 2) * 3.6 > max_speed_kmh
        pedal = action[:, 1]
        engine = np.where(pedal >= 0.0, np.where(fast, 0.0, p.engine_force * pedal), 0.0)[:, None]
        brake = np.where(pedal >= 0.0, p.coast_brake, -pedal * p.brake_force)[:, None]
        engine_on, engine_impulse = engine != 0.0, engine * dt
        delta = np.where(p.front[None, :], np.deg2rad(max_steer_deg) * action[:, 0:1], 0.0)  # (n, 4)
        # the wheels' heading in the chassis plane; z = -0.0 so that 0 - x keeps the sign of -x exactly
        wheel_dir = np.stack([np.cos(delta), np.sin(delta), np.full((n, 4), -0.0)])
        vw = np.empty((6, n))  # chassis-frame linear and angular velocity
        vw[:3] = np.einsum("nji,nj->ni", rot, world_v).T
        vw[3:] = np.einsum("nji,nj->ni", rot, self.ang[slots]).T
        points = np.empty((2, 3, n, 4))  # contact points and the side impulses' points, relative to the centre of mass
        points[0, :2] = self._connection[:2]
        dirs = np.empty((2, 3, n, 4))  # each wheel's forward direction and axle on the ground
        shown_pos, shown_fwd = pos[:, :2], rot[:, :2, 1]
        for k in range(substeps):
            if k == substeps - 1:  # Bullet's motion state shows the pose before the last integration
                shown_pos, shown_fwd = pos[:, :2].copy(), rot[:, :2, 1].copy()
            vw[:3] -= gdt * rot[:, 2, :].T  # gravity (the world up in the chassis frame)
            v = np.ascontiguousarray(vw[:3].T)
            pos = pos + np.einsum("nij,nj->ni", rot, v) * dt
            turn = turn_matrices(np.ascontiguousarray(vw[3:].T), dt)  # a body-frame turn: R exp([w] dt)
            rot = rot @ turn
            vw[:3] = np.einsum("nji,nj->ni", turn, v).T  # the same world velocity in the turned frame
            up = rot[:, 2, :].T[:, :, None]  # world up in the chassis frame (3, n, 1)
            nz = up[2]
            # rays straight down the chassis' -z from the connection points to the ground z = 0
            arm = up * self._connection
            height = pos[:, 2:3] + arm[0] + arm[1] + arm[2]  # connection points above the ground (n, 4)
            steep = nz > 0.1
            safe_nz = np.where(steep, nz, 1.0)
            dist = np.where(steep, height / safe_nz, np.inf)
            contact = (dist >= 0.0) & (dist <= ray)
            length = np.minimum(np.maximum(dist - p.wheel_radius, self._length_min), self._length_max)  # np.clip, bit for bit
            r = points[0]
            np.subtract(self._connection[2], np.where(contact, dist, ray), out=r[2])  # contact point heights
            r1, r2 = r[_ROLL1], r[_ROLL2]
            # suspension: spring and damper along the ray, impulse along world up at the contact
            cv = _point_velocity(vw, r1, r2)
            inv_cos = np.where(steep, 1.0 / safe_nz, 10.0)
            along = up * cv
            rel_vel = np.where(steep, (along[0] + along[1] + along[2]) * inv_cos, 0.0)
            damping = np.where(rel_vel < 0.0, p.damping_compression, p.damping_relaxation)
            force = (p.suspension_stiffness * (p.suspension_rest - length) * inv_cos - damping * rel_vel) * p.mass
            force = np.where(contact, np.maximum(force, 0.0), 0.0)
            lift = np.minimum(force, p.max_suspension_force) * dt
            vw += _impulse_sums(lift * up, r1, r2) * self._inv_mass
            # friction: each wheel's axle and forward direction on the ground
            tilt = wheel_dir[0] * up[0] + wheel_dir[1] * up[1]
            axle = wheel_dir - up * tilt
            sq = axle * axle
            np.divide(axle, np.sqrt(sq[0] + sq[1] + sq[2]), out=dirs[1])
            axle = dirs[1]
            np.subtract(up[_ROLL1] * axle[_ROLL2], up[_ROLL2] * axle[_ROLL1], out=dirs[0])  # up x axle
            cv = _point_velocity(vw, r1, r2)
            den = _denominator(dirs, r1, r2, self._inv_inertia, self._inv_m)  # (2, n, 4): forward, side
            along = cv * dirs
            speed = along[:, 0] + along[:, 1] + along[:, 2]
            side = np.where(contact, -p.side_damping * speed[1] / den[1], 0.0)
            stop = -speed[0] / den[0]  # the impulse that stops the contact point (not shared out)
            rolling = np.where(contact, np.where(engine_on, engine_impulse, np.minimum(np.maximum(stop, -brake), brake)), 0.0)
            limit = force * dt * p.friction_slip
            demand = (rolling * p.forward_skid_factor) ** 2 + side * side
            skidding = contact & (demand > limit * limit)
            if skidding.any():
                skid = np.where(skidding, limit / np.sqrt(np.where(skidding, demand, 1.0)), 1.0)
                scale = np.where(skidding.any(1, keepdims=True) & (side != 0.0) & (skid < 1.0), skid, 1.0)
                rolling, side = rolling * scale, side * scale
            # the forward impulse acts at the contact point; the side one with its height over the ground scaled (roll influence)
            across = up * r
            up_part = (1.0 - p.roll_influence) * (across[0] + across[1] + across[2])
            np.subtract(r, up_part * up, out=points[1])
            sums = _impulse_sums(np.stack([rolling, side])[:, None] * dirs, points[:, _ROLL1], points[:, _ROLL2]) * self._inv_mass
            vw += sums[0]
            vw += sums[1]
        self.pos[slots], self.rot[slots] = pos, rot
        self.vel[slots] = np.einsum("nij,nj->ni", rot, np.ascontiguousarray(vw[:3].T))
        self.ang[slots] = np.einsum("nij,nj->ni", rot, np.ascontiguousarray(vw[3:].T))
        return shown_pos, np.arctan2(shown_fwd[:, 1], shown_fwd[:, 0])


@functools.cache
def equilibrium(params: VehicleParams) -> tuple[float, float, float]:
    """(height, pitch, vertical velocity) of a car at rest on its suspension: 3 s after a spawn, on flat ground."""
    probe = RaycastVehicles(1, params)
    probe.place(np.array([0]), np.zeros((1, 2)), np.zeros(1))
    for _ in range(30):
        probe.step(np.array([0]), np.zeros((1, 2)))
    return float(probe.pos[0, 2]), float(np.arcsin(probe.rot[0, 2, 1])), float(probe.vel[0, 2])


def _point_velocity(vw: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """Velocity v + w x r (3, n, 4) of the chassis at the points r, all in the chassis frame.

    ``vw`` (6, n): linear and angular velocity; ``r1``, ``r2``: the points' components rolled by one and two (``r[_ROLL1]``, ``r[_ROLL2]``).
    """
    return vw[:3, :, None] + vw[_W_ROLL1, :, None] * r2 - vw[_W_ROLL2, :, None] * r1


def _denominator(d: np.ndarray, r1: np.ndarray, r2: np.ndarray, inv_inertia: np.ndarray, inv_m: float) -> np.ndarray:
    """Bullet's impulse denominator 1/m + (r x d)^T I^-1 (r x d) for directions d (..., 3, n, 4) at points r (chassis frame, diagonal I)."""
    c = r1 * d[..., _ROLL2, :, :] - r2 * d[..., _ROLL1, :, :]
    q = c * c * inv_inertia
    return inv_m + q[..., 0, :, :] + q[..., 1, :, :] + q[..., 2, :, :]


def _impulse_sums(impulse: np.ndarray, r1: np.ndarray, r2: np.ndarray) -> np.ndarray:
    """The impulses (..., 3, n, 4) applied at the points r and their torques r x impulse, each summed over the wheels: (..., 6, n)."""
    torque = r1 * impulse[..., _ROLL2, :, :] - r2 * impulse[..., _ROLL1, :, :]
    return np.concatenate([impulse, torque], -3).sum(-1)
