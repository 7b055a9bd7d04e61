"""Open-loop replay of MetaDrive vehicle traces: the windows, an exact replay of native traces, the shipped recording."""

import numpy as np

from coin_app.sim.config import DynamicsConfig
from coin_app.sim.dynamics import bicycle_step
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.vehicle import RaycastVehicles
from coin_app.sim.vehicle_replay import Traces, error_table, load_traces, window_errors, window_starts


def _native_traces(cfg: DynamicsConfig, lengths=(40, 35), kinds=("scripted", "route")) -> Traces:
    """Traces made by stepping one vehicle at a time through the bicycle model (the replay must reproduce them exactly)."""
    rng = np.random.default_rng(3)
    horizon = max(lengths)
    actions = np.full((len(lengths), horizon, 2), np.nan)
    states = np.full((len(lengths), horizon + 1, 14), np.nan)
    for k, n in enumerate(lengths):
        pos, heading, speed, yaw = np.array([[5.0 * k, -2.0]]), np.array([0.3 * k]), np.array([6.0 + k]), np.zeros(1)
        states[k, 0, :6] = [*pos[0], heading[0], speed[0], yaw[0], 0.0]
        for t in range(n):
            a = rng.uniform(-1.0, 1.0, size=(1, 2))
            actions[k, t] = a[0]
            pos, heading, speed, yaw = bicycle_step(cfg, pos, heading, speed, yaw, a)
            states[k, t + 1, :6] = [*pos[0], heading[0], speed[0], yaw[0], 0.0]
    return Traces(np.array(["a", "b"]), np.array(kinds), np.array(lengths), actions, states)


def _raycast_traces(lengths=(40, 35), kinds=("scripted", "route")) -> Traces:
    """Traces of the raycast model itself, recorded as MetaDrive's are (reported pose, body state; scripted: from rest)."""
    rng = np.random.default_rng(5)
    horizon = max(lengths)
    actions = np.full((len(lengths), horizon, 2), np.nan)
    states = np.full((len(lengths), horizon + 1, 14), np.nan)
    for k, n in enumerate(lengths):
        car = RaycastVehicles(1)
        car.place(np.array([0]), np.array([[3.0 * k, 1.0]]), np.array([0.2 * k]), 8.0, settled=True)
        xy, heading = car.pos[:, :2].copy(), np.array([0.2 * k])
        for t in range(n + 1):
            rot = car.rot[0]
            lateral = -np.sin(heading[0]) * car.vel[0, 0] + np.cos(heading[0]) * car.vel[0, 1]
            states[k, t] = [*xy[0], heading[0], np.hypot(*car.vel[0, :2]), car.ang[0, 2], lateral, car.pos[0, 2],
                            *car.vel[0], car.ang[0, 0], car.ang[0, 1], rot[2, 1], rot[2, 0]]  # fmt: skip
            if t < n:
                actions[k, t] = rng.uniform(-1.0, 1.0, size=2)
                xy, heading = car.step(np.array([0]), actions[k, t : t + 1])
    return Traces(np.array(["a", "b"]), np.array(kinds), np.array(lengths), actions, states)


def test_window_starts_by_hand():
    traces = _native_traces(DynamicsConfig())
    trace, start = window_starts(traces, steps=10, stride=10)
    # scripted: one window at 0; a 35-step route: windows at 0, 10, 20 (20 + 10 <= 35; 30 + 10 > 35)
    assert trace.tolist() == [0, 1, 1, 1] and start.tolist() == [0, 0, 10, 20]
    trace, start = window_starts(traces, steps=30, stride=10)
    assert trace.tolist() == [0, 1] and start.tolist() == [0, 0]


def test_replaying_native_traces_reproduces_them_exactly():
    cfg = DynamicsConfig(model="bicycle")
    traces = _native_traces(cfg)
    for steps in (1, 10, 30):
        e = window_errors(cfg, traces, steps)
        assert len(e.position) == len(window_starts(traces, steps)[0])
        assert e.position.max() < 1e-9 and e.heading.max() < 1e-9 and e.speed_kmh.max() < 1e-9
    # another model does not reproduce them: the comparison can fail
    assert window_errors(DynamicsConfig.kinematic(), traces, 30).position.max() > 0.1


def test_replaying_raycast_traces_reproduces_them():
    traces = _raycast_traces()
    for steps in (10, 30):
        e = window_errors(DynamicsConfig(), traces, steps, stride=5)
        scripted = traces.kinds[e.trace] == "scripted"
        assert e.position[scripted].max() < 1e-9 and e.speed_kmh[scripted].max() < 1e-9  # from rest: the exact state
        # mid-route the recorded pose is one physics step behind: advancing it with the recorded velocity is close, not exact
        mid = ~scripted & (e.start > 0)
        assert mid.sum() >= 1 and e.position[mid].max() < 0.01 and e.speed_kmh[mid].max() < 0.05


def test_error_table_takes_each_traces_worst_window():
    cfg = DynamicsConfig(model="bicycle")
    traces = _native_traces(cfg)
    shifted = traces.states.copy()
    shifted[1, 25, 0] += 2.0  # the route's state at step 25: only its window 20..30 ends there after 5 steps
    rows = error_table(cfg, Traces(traces.names, traces.kinds, traces.lengths, traces.actions, shifted), horizons=(5,), stride=5)
    assert rows[0]["position@5"] < 1e-9 and abs(rows[1]["position@5"] - 2.0) < 1e-9


def test_shipped_recording_holds_every_manoeuvre():
    traces = load_traces()
    names = set(traces.names.tolist())
    for speed in (20, 30, 40):
        for lock in ("full", "half"):
            assert f"{lock}_lock_left_{speed}kmh_coast" in names and f"{lock}_lock_right_{speed}kmh_throttle0.3" in names
        assert f"brake_in_turn_{speed}kmh" in names and f"lane_change_{speed}kmh" in names
    assert {f"heuristic_{s}_seed0" for s in DRIVING_SCENARIOS} <= names
    for k, n in enumerate(traces.lengths):
        assert np.isfinite(traces.actions[k, :n]).all() and np.isfinite(traces.states[k, : n + 1]).all()
        assert np.isnan(traces.states[k, n + 1 :]).all()
    scripted = traces.kinds == "scripted"
    start = traces.states[scripted, 0]
    nominal = np.array([float(n.split("kmh")[0].split("_")[-1]) if "kmh" in n else 0.0 for n in traces.names[scripted]])
    assert np.allclose(start[:, 3] * 3.6, nominal, atol=0.01)  # each starts at its speed, driving straight
    assert np.abs(start[:, 4]).max() < 1e-6 and np.abs(start[:, 5]).max() < 1e-3 and np.abs(start[:, 10:12]).max() < 1e-2
    # mirror manoeuvres mirror each other (MetaDrive's car is symmetric): same speed, opposite heading change
    left, right = (np.flatnonzero(traces.names == f"full_lock_{s}_40kmh_coast")[0] for s in ("left", "right"))
    assert np.allclose(traces.states[left, :41, 3], traces.states[right, :41, 3], atol=1e-3)
    turn = traces.states[[left, right], 40, 2] - traces.states[[left, right], 0, 2]
    assert abs(np.angle(np.exp(1j * turn[0])) + np.angle(np.exp(1j * turn[1]))) < 1e-2


def test_native_car_matches_metadrive_on_every_recorded_manoeuvre():
    """Issue 21: after 1 s and 3 s, speed within 1 km/h and position within 0.3 m for every manoeuvre at <= 40 km/h."""
    traces = load_traces()
    rows = error_table(DynamicsConfig(), traces, horizons=(10, 30))
    scripted = [r for r in rows if r["kind"] == "scripted"]
    assert len(scripted) == 37 and all(r["start_kmh_max@10"] <= 40.0 + 1e-6 for r in scripted)
    for r in rows:  # every window of the heuristic routes too
        for h in (10, 30):
            assert r[f"position@{h}"] <= 0.3 and r[f"speed_kmh@{h}"] <= 1.0, r
    # the bicycle fitted before the port does not: 1.30 m and 7.2 km/h after 1 s at full lock, 40 km/h
    old = error_table(DynamicsConfig(model="bicycle"), traces, horizons=(10,))
    assert max(r["position@10"] for r in old) > 1.0 and max(r["speed_kmh@10"] for r in old) > 5.0


def test_recorder_reproduces_the_shipped_traces():
    """Recording again with MetaDrive gives the shipped file's traces (one scripted manoeuvre, one route)."""
    import pytest

    pytest.importorskip("metadrive", reason="the optional MetaDrive extra is not installed")
    from coin_app.backends.vehicle_traces import _open_env, record_route, record_scripted, scripted_manoeuvres

    shipped = load_traces()
    index = {str(n): k for k, n in enumerate(shipped.names)}
    man = next(m for m in scripted_manoeuvres() if m.name == "full_lock_left_40kmh_coast")
    env = _open_env("intersection")
    try:
        actions, states = record_scripted(env, man)
        k = index[man.name]
        assert np.allclose(actions, shipped.actions[k, : len(actions)], atol=1e-6)
        assert np.abs(states - shipped.states[k, : len(states)]).max() < 1e-3  # float32 physics after other episodes
        actions, states = record_route(env, "intersection", 0)
        k = index["heuristic_intersection_seed0"]
        assert len(actions) == shipped.lengths[k]  # closed loop in float32 physics: equal to within 1 mm
        assert np.abs(states - shipped.states[k, : len(states)]).max() < 1e-3
    finally:
        env.close()
