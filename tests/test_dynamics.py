"""Bicycle-model step against values computed by hand from the model's equations."""

import math

import numpy as np
import pytest

from coin_app.sim.config import DynamicsConfig
from coin_app.sim.dynamics import bicycle_step

FIT = DynamicsConfig()
KIN = DynamicsConfig.kinematic()


def one(cfg, x=0.0, y=0.0, h=0.0, v=0.0, r=0.0, a0=0.0, a1=0.0):
    p, hd, vv, rr = bicycle_step(cfg, np.array([[x, y]]), np.array([h]), np.array([v]), np.array([r]), np.array([[a0, a1]]))
    return p[0, 0], p[0, 1], hd[0], vv[0], rr[0]


def test_kinematic_seed2_semi_implicit_step():
    # seed-2 Eq. 1, semi-implicit: speed first, then heading, then position with the new values
    v0, a0, dt, wheelbase = 10.0, 0.5, 0.1, 2.46894
    x, y, h, v, _ = one(KIN, v=v0, h=0.3, a0=a0, a1=0.0)
    v1 = v0 - 0.36363636363636365 * dt  # coasting
    h1 = 0.3 + v1 * math.tan(math.radians(20.0)) / wheelbase * dt
    assert v == pytest.approx(v1, abs=1e-12)
    assert h == pytest.approx(h1, abs=1e-12)
    assert x == pytest.approx(v1 * math.cos(h1) * dt, abs=1e-12)
    assert y == pytest.approx(v1 * math.sin(h1) * dt, abs=1e-12)


def test_full_lock_is_forty_degrees_in_kinematic_model():
    _, _, h, v, _ = one(KIN, v=5.0, a0=1.0, a1=0.0)
    assert h == pytest.approx(v * math.tan(math.radians(40.0)) / 2.46894 * 0.1, abs=1e-12)
    _, _, h_neg, _, _ = one(KIN, v=5.0, a0=-1.0, a1=0.0)
    assert h_neg == pytest.approx(-h, abs=1e-12)


def test_throttle_is_linear_and_matches_metadrive_speed_curve():
    # MetaDrive: 2.909 m/s^2 per unit throttle, 2.91 m/s after 1 s and 14.55 m/s after 5 s
    v = 0.0
    speeds = []
    for _ in range(50):
        _, _, _, v, _ = one(FIT, v=v, a1=1.0)
        speeds.append(v)
    assert speeds[0] == pytest.approx(0.2909090909, abs=1e-9)
    assert speeds[9] == pytest.approx(2.909090909, abs=1e-8)
    assert speeds[49] == pytest.approx(14.545454545, abs=1e-7)
    _, _, _, v_half, _ = one(FIT, v=3.0, a1=0.5)
    assert v_half == pytest.approx(3.0 + 0.5 * 2.909090909 * 0.1, abs=1e-9)


def test_braking_saturates_and_never_reverses():
    # decel = min(27.27 b, 5.414 + 9.650 b): b = 0.2 linear, b = 1 friction-limited
    _, _, _, v, _ = one(FIT, v=20.0, a1=-0.2)
    assert v == pytest.approx(20.0 - 0.1 * 27.272727272727273 * 0.2, abs=1e-9)
    _, _, _, v, _ = one(FIT, v=20.0, a1=-1.0)
    assert v == pytest.approx(20.0 - 0.1 * (5.414138062029027 + 9.650087717020922), abs=1e-9)
    _, _, _, v, _ = one(FIT, v=0.5, a1=-1.0)
    assert v == 0.0


def test_coasting_and_speed_limit():
    _, _, _, v, _ = one(FIT, v=10.0, a1=0.0)
    assert v == pytest.approx(10.0 - 0.036363636, abs=1e-8)
    vmax = 80 / 3.6
    _, _, _, v, _ = one(FIT, v=vmax - 0.01, a1=1.0)
    assert v == pytest.approx(vmax)  # clipped at 80 km/h
    _, _, _, v, _ = one(FIT, v=vmax + 0.05, a1=1.0)
    assert v == pytest.approx(vmax)  # never above the limit


def test_fitted_yaw_rate_lag_converges_to_linear_curvature():
    # low speed: steady-state curvature kappa = 0.2697 * a0 (MetaDrive measured 0.281 * a0 at 2 m/s)
    kappa = 0.2697195149202444 * 0.5
    _, _, _, v1, r1 = one(FIT, v=2.0, a0=0.5, a1=0.0)
    assert v1 == pytest.approx(2.0 - 0.036363636, abs=1e-8)  # coasting; no scrub while r = 0
    assert r1 == pytest.approx(0.333176619483477 * v1 * kappa, rel=1e-9)  # first-order lag
    r = r1
    for _ in range(80):
        _, _, _, v_new, r = one(FIT, v=2.0, r=r, a0=0.5, a1=0.0)  # hold the input speed
    assert r / v_new == pytest.approx(kappa, rel=1e-6)


def test_lateral_grip_caps_curvature_at_speed():
    v = 20.0
    _, _, _, v1, r = one(FIT.__class__(yaw_rate_alpha=1.0, scrub=0.0), v=v, a0=1.0, a1=1.0)
    cap = (8.707595044203563 - 2.706596419114096) / v1**2
    assert r == pytest.approx(v1 * cap, rel=1e-9)
