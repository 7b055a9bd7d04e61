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

# cross products of vectors stacked on a leading axis (x, y, z), one gather per factor: with the rolled rows
# a[_ROLL12] = (a_y, a_z, a_x, a_z, a_x, a_y) and b[_ROLL21] = (b_z, b_x, b_y, b_y, b_z, b_x), d = a[_ROLL12] * b[_ROLL21]
# gives a x b = d[:3] - d[3:]; r[_ROLL121][:6] and [3:] are r[_ROLL12] and r[_ROLL21] from one gather
_ROLL12, _ROLL21, _ROLL121 = np.array([1, 2, 0, 2, 0, 1]), np.array([2, 0, 1, 1, 2, 0]), np.array([1, 2, 0, 2, 0, 1, 1, 2, 0])
_W_ROLL12 = 3 + _ROLL12  # the same rows of the angular part of a stacked (v, w)
# turn_matrices: the product pairs of its off-diagonal entries, and its entries' rows in row-major matrix order
_PAIR_A, _PAIR_B = np.array([0, 1, 0]), np.array([1, 2, 2])
_MATRIX_ORDER = np.array([6, 0, 5, 3, 7, 1, 2, 4, 8])


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


class RaycastVehicles:
    """The chassis state of ``n`` vehicles (position, rotation, linear and angular velocity) and Bullet's vehicle step."""

    def __init__(self, n: int, params: VehicleParams | None = None):
        self.p = params or VehicleParams()
        self.pos = np.zeros((n, 3))
        self.rot = np.tile(np.eye(3), (n, 1, 1))
        self.vel = np.zeros((n, 3))
        self.ang = np.zeros((n, 3))
        self.inv_inertia = 1.0 / np.asarray(self.p.inertia)
        # constants of the step, shaped for the stacked (component, wheel, vehicle) arrays
        self._connection = np.ascontiguousarray(self.p.connection.T[:, :, None])  # (3, 4, 1): right, forward, up
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
        state is kept in the world frame. Vectors are stacked on a leading axis (x, y, z) over
        (wheel, vehicle), so that each line below is one array operation for every component,
        wheel and vehicle.
        """
        p = self.p
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
        points[0, :2] = self._connection[:2]
        r = points[0]
        dirs = np.empty((2, 3, 4, n))  # each wheel's forward direction and axle on the ground
        lift_sums = np.empty((6, 4, n))  # the suspension impulses and their torques, per wheel
        friction_sums = np.empty((2, 6, 4, n))  # the forward and side impulses and their torques, per wheel
        friction = np.empty((2, 4, n))  # the forward and side impulse sizes
        shown_pos, shown_fwd = pos[:, :2], rot[:, :2, 1]
        for k in range(substeps):
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
            arm = up * self._connection
            height = pos[:, 2] + arm[0] + arm[1] + arm[2]  # connection points above the ground (4, n)
            steep = nz > 0.1
            upright = steep.all()  # the usual case, and then np.where(steep, x, y) is x
            safe_nz = nz if upright else np.where(steep, nz, 1.0)
            dist = height / safe_nz if upright else np.where(steep, height / safe_nz, np.inf)
            contact = (dist >= 0.0) & (dist <= ray)
            grounded = contact.all()  # the usual case, and then np.where(contact, x, y) is x
            length = np.minimum(np.maximum(dist - p.wheel_radius, self._length_min), self._length_max)  # np.clip to the bit
            np.subtract(self._connection[2], dist if grounded else np.where(contact, dist, ray), out=r[2])  # contact heights
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
            vw += lift_sums.sum(1) * self._inv_mass
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
            q = moment * moment * self._inv_inertia
            den = self._inv_m + q[:, 0] + q[:, 1] + q[:, 2]
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
            total = friction_sums.sum(2) * self._inv_mass
            vw += total[0]
            vw += total[1]
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
