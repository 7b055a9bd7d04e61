"""MetaDrive's car in Bullet, ported (coin_app/sim/vehicle.py): hand-computed physics of its constants."""

import numpy as np
import pytest

from coin_app.sim.vehicle import RaycastVehicles, VehicleParams, chassis_basis, equilibrium, turn_matrices

P = VehicleParams()
WHEELBASE = P.front_axle + P.rear_axle


def one_car(speed=0.0, settled=True, heading=0.0):
    cars = RaycastVehicles(1)
    cars.place(np.array([0]), np.zeros((1, 2)), np.array([heading]), speed, settled=settled)
    return cars


def drive(cars, action, steps):
    out = None
    for _ in range(steps):
        out = cars.step(np.array([0]), np.array([action], float))
    return out


def suspension_forces(cars):
    """Per-wheel spring force at rest: Bullet's k m (rest - length) with length from the connection points' heights."""
    height = cars.pos[0, 2] + (cars.rot[0] @ P.connection.T)[2]  # connection points above the ground
    length = height / cars.rot[0, 2, 2] - P.wheel_radius
    return P.suspension_stiffness * P.mass * (P.suspension_rest - length)


def test_at_rest_the_springs_carry_the_weight_split_by_the_axle_distances():
    cars = one_car(settled=False)
    drive(cars, [0.0, 0.0], 40)  # 4 s after a spawn at MetaDrive's height: settled
    force = suspension_forces(cars)
    weight = P.mass * P.gravity
    assert force.sum() == pytest.approx(weight, rel=2e-3)
    # moments about the centre of mass: front and rear axle loads in the ratio rear : front distance
    assert force[:2].sum() == pytest.approx(weight * P.rear_axle / WHEELBASE, rel=1e-2)
    assert force[0] == pytest.approx(force[1], rel=1e-6) and force[2] == pytest.approx(force[3], rel=1e-6)
    # the centre of mass sits between the compressed axles: rest length minus k m deflection, plus the wheel radius
    axle_height = P.wheel_radius + P.suspension_rest - force[[0, 2]] / (P.suspension_stiffness * P.mass) - P.connection_height
    expected = axle_height[1] + (axle_height[0] - axle_height[1]) * P.rear_axle / WHEELBASE
    assert cars.pos[0, 2] == pytest.approx(expected, abs=2e-3)
    assert equilibrium(P)[0] == pytest.approx(cars.pos[0, 2], abs=1e-4)


def test_full_throttle_and_coasting_accelerations_by_hand():
    cars = one_car()
    drive(cars, [0.0, 1.0], 10)  # 4 wheels x 800 N on 1100 kg for 1 s
    assert np.hypot(*cars.vel[0, :2]) == pytest.approx(4 * 800.0 / 1100.0, abs=0.01)
    cars = one_car(speed=10.0)
    drive(cars, [0.0, 0.0], 10)  # the brake value 2.0 per wheel and physics step: 4 x 2.0 / (0.02 s x 1100 kg)
    assert np.hypot(*cars.vel[0, :2]) == pytest.approx(10.0 - 4 * 2.0 / (0.02 * 1100.0), abs=0.01)


def test_no_more_grip_than_the_friction_circle():
    cars = one_car(speed=40 / 3.6)
    lateral = []
    for _ in range(30):  # full lock at 40 km/h: the tyres saturate
        drive(cars, [1.0, 0.0], 1)
        v = cars.vel[0, :2]
        lateral.append(abs(np.linalg.norm(v) * cars.ang[0, 2]))  # centripetal acceleration v * yaw rate
    assert max(lateral) <= P.friction_slip * P.gravity * 1.05  # mu g (a few % of transient load transfer)
    assert max(lateral) > 0.6 * P.friction_slip * P.gravity  # and it does use it
    assert np.hypot(*cars.vel[0, :2]) < 40 / 3.6 - 3.0  # scrubbing speed off, as MetaDrive's car does


def test_mirror_manoeuvres_mirror_each_other():
    left, right = one_car(speed=30 / 3.6), one_car(speed=30 / 3.6)
    for _ in range(20):
        a = drive(left, [0.7, 0.2], 1)
        b = drive(right, [-0.7, 0.2], 1)
        assert a[0][0, 0] == pytest.approx(b[0][0, 0], abs=1e-9) and a[0][0, 1] == pytest.approx(-b[0][0, 1], abs=1e-9)
        assert a[1][0] == pytest.approx(-b[1][0], abs=1e-9)


def test_reported_pose_is_one_physics_step_behind():
    cars = one_car(speed=10.0, heading=0.5)
    for _ in range(3):
        (xy,), (heading,) = drive(cars, [0.0, 0.3], 1)
        # the last integration moved the body by (velocity before the last impulses) x 0.02 s, along its heading
        gap = cars.pos[0, :2] - xy
        assert np.linalg.norm(gap) == pytest.approx(np.linalg.norm(cars.vel[0, :2]) * P.physics_dt, rel=1e-2)
        assert np.arctan2(gap[1], gap[0]) == pytest.approx(0.5, abs=1e-6) and heading == pytest.approx(0.5, abs=1e-6)


def test_a_car_in_the_air_falls_freely():
    cars = one_car()
    cars.pos[0, 2] = 5.0  # no wheel reaches the ground: gravity only
    drive(cars, [1.0, 1.0], 5)
    assert cars.pos[0, 2] == pytest.approx(5.0 - 0.5 * P.gravity * 0.5**2, abs=0.06)
    assert np.allclose(cars.vel[0, :2], 0.0) and np.allclose(cars.ang[0], 0.0)


def test_fast_paths_for_upright_grounded_cars_match_the_general_path():
    """A tipped-over car and a car in the air (the general path) change nothing for the other cars (the fast path)."""
    rng = np.random.default_rng(3)
    n = 12
    mixed = RaycastVehicles(n)
    mixed.place(np.arange(n), rng.uniform(-20, 20, (n, 2)), rng.uniform(-3, 3, n), rng.uniform(0, 20, n), settled=True)
    mixed.rot[0] = chassis_basis(np.array([0.3]), np.array([2.0]))[0]  # tipped over: its up axis points down
    mixed.pos[1, 2] = 2.0  # in the air: no wheel reaches the ground
    alone = RaycastVehicles(n - 2)
    for name in ("pos", "rot", "vel", "ang"):
        getattr(alone, name)[:] = getattr(mixed, name)[2:]
    for action in rng.uniform(-1.0, 1.0, (10, n, 2)):
        xy, heading = mixed.step(np.arange(n), action)
        xy_alone, heading_alone = alone.step(np.arange(n - 2), action[2:])
        np.testing.assert_array_equal(xy[2:], xy_alone)
        np.testing.assert_array_equal(heading[2:], heading_alone)
        for name in ("pos", "rot", "vel", "ang"):
            np.testing.assert_array_equal(getattr(mixed, name)[2:], getattr(alone, name))
    assert mixed.rot[0, 2, 2] < 0.1  # the tipped car kept the batch on the general path throughout


def test_turn_matrices_are_rodrigues_rotations():
    """turn_matrices(w, dt) rotates by |w| dt about w: it fixes w, is orthonormal and matches the series of exp([w] dt)."""
    rng = np.random.default_rng(4)
    w = rng.normal(0.0, 2.0, (20, 3))
    w[0] = 0.0
    turn = turn_matrices(w, 0.02)
    np.testing.assert_allclose(turn @ turn.transpose(0, 2, 1), np.broadcast_to(np.eye(3), turn.shape), atol=1e-14)
    np.testing.assert_allclose(np.einsum("nij,nj->ni", turn, w), w, atol=1e-14)
    skew = np.zeros((20, 3, 3))
    skew[:, 0, 1], skew[:, 0, 2], skew[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    skew -= skew.transpose(0, 2, 1)
    series, term = np.broadcast_to(np.eye(3), turn.shape).copy(), np.broadcast_to(np.eye(3), turn.shape).copy()
    for k in range(1, 20):
        term = term @ (skew * 0.02) / k
        series += term
    np.testing.assert_allclose(turn, series, atol=1e-14)
