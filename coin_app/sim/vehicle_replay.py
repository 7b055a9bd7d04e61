"""Open-loop replay of recorded MetaDrive vehicle traces in the native vehicle model (issue 21).

The traces (``maps/metadrive_traces.npz``, written by ``coin_app.backends.vehicle_traces``) hold
MetaDrive's actions and states. :func:`replay_windows` starts the native model from MetaDrive's
state at the start of a window and applies the recorded actions open loop; :func:`window_errors`
compares position, heading and speed. The ``raycast`` model starts from the whole chassis state
(height, tilt, 3-D velocities); MetaDrive reports a moving car's pose one physics step behind,
so a window that starts mid-route advances the reported pose by that step first (a scripted
manoeuvre starts at rest on the suspension, where reported and physical poses agree). The
bicycle models start from position, heading, speed and yaw rate.
Scripted manoeuvres have one window from their start; the heuristic routes one window every
``stride`` steps along the route. Everything is vectorized over windows.

``benchmarks/vehicle_parity.py`` prints the error of every trace after 1 s and 3 s and the worst
case at or below 40 km/h.
"""

from __future__ import annotations

from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from coin_app.sim.config import PHYSICS_DT, DynamicsConfig
from coin_app.sim.dynamics import bicycle_step, wrap_angle
from coin_app.sim.vehicle import RaycastVehicles, chassis_basis, turn_matrices

TRACES_FILE = "metadrive_traces.npz"


@dataclass(frozen=True)
class Traces:
    """Recorded MetaDrive traces: actions (k, T, 2) and states (k, T + 1, 14), NaN-padded to the longest."""

    names: np.ndarray
    kinds: np.ndarray
    lengths: np.ndarray
    actions: np.ndarray
    states: np.ndarray  # coin_app.backends.vehicle_traces.STATE_COLUMNS: x, y, heading, speed, yaw rate, ... (14)


def load_traces(path: str | Path | None = None) -> Traces:
    """The traces in ``path`` (default: the recorded file shipped with the simulator)."""
    source = Path(path) if path is not None else Path(str(resources.files("coin_app.sim") / "maps" / TRACES_FILE))
    with np.load(source) as data:
        return Traces(data["names"], data["kinds"], data["lengths"], data["actions"].astype(float), data["states"])


@dataclass(frozen=True)
class Windows:
    """Replay windows: trace index and start step of each, and the native and MetaDrive states over ``steps``."""

    trace: np.ndarray  # (w,)
    start: np.ndarray  # (w,)
    native: np.ndarray  # (w, steps + 1, 4): x, y, heading, speed
    recorded: np.ndarray  # (w, steps + 1, 6)


def window_starts(traces: Traces, steps: int, stride: int = 10) -> tuple[np.ndarray, np.ndarray]:
    """(trace, start) of every window of ``steps`` steps: a scripted trace's start, and every ``stride`` steps of a route."""
    trace, start = [], []
    for k, (kind, length) in enumerate(zip(traces.kinds, traces.lengths)):
        starts = [0] if kind == "scripted" else list(range(0, int(length) - steps + 1, stride))
        for s in starts:
            if s + steps <= length:
                trace.append(k)
                start.append(s)
    return np.array(trace, int), np.array(start, int)


def replay_windows(cfg: DynamicsConfig, traces: Traces, steps: int, stride: int = 10) -> Windows:
    """Replay every window of ``steps`` steps in the native model from MetaDrive's state at its start."""
    trace, start = window_starts(traces, steps, stride)
    offsets = start[:, None] + np.arange(steps + 1)[None, :]
    recorded = traces.states[trace[:, None], offsets]
    actions = np.clip(traces.actions[trace[:, None], offsets[:, :-1]], -1.0, 1.0)
    x0 = recorded[:, 0]
    native = np.empty((len(trace), steps + 1, 4))
    native[:, 0] = x0[:, :4]
    if cfg.model == "raycast":
        bodies = _bodies_at(x0, moving=traces.kinds[trace] != "scripted")
        slots = np.arange(len(trace))
        for t in range(steps):
            xy, heading = bodies.step(slots, actions[:, t], round(cfg.dt / PHYSICS_DT), cfg.max_speed_kmh, cfg.max_steer_deg)
            native[:, t + 1] = np.column_stack([xy, heading, np.hypot(bodies.vel[:, 0], bodies.vel[:, 1])])
    else:
        pos, heading, speed, yaw = x0[:, :2].copy(), x0[:, 2].copy(), x0[:, 3].copy(), x0[:, 4].copy()
        for t in range(steps):
            pos, heading, speed, yaw = bicycle_step(cfg, pos, heading, speed, yaw, actions[:, t])
            native[:, t + 1] = np.column_stack([pos, heading, speed])
    return Windows(trace, start, native, recorded)


def _bodies_at(x0: np.ndarray, moving: np.ndarray) -> RaycastVehicles:
    """Raycast chassis states of the recorded states ``x0`` (w, 14); ``moving``: advance the reported pose by one physics step."""
    bodies = RaycastVehicles(len(x0))
    params = bodies.p
    pitch = np.arcsin(np.clip(x0[:, 12], -1.0, 1.0))
    roll = np.arcsin(np.clip(-x0[:, 13] / np.cos(pitch), -1.0, 1.0))
    bodies.rot[:] = chassis_basis(x0[:, 2], pitch, roll)
    bodies.pos[:] = np.column_stack([x0[:, 0], x0[:, 1], x0[:, 6]])
    bodies.vel[:] = x0[:, 7:10]
    bodies.ang[:] = np.column_stack([x0[:, 10], x0[:, 11], x0[:, 4]])
    before = bodies.vel[moving] - np.array([0.0, 0.0, params.gravity * params.physics_dt])  # the velocity it moved with
    bodies.pos[moving] += before * params.physics_dt
    bodies.rot[moving] = turn_matrices(bodies.ang[moving], params.physics_dt) @ bodies.rot[moving]
    return bodies


@dataclass(frozen=True)
class WindowErrors:
    """Per window at its last step: position error (m), heading error (rad), speed error (km/h), and its start speed (km/h)."""

    trace: np.ndarray
    start: np.ndarray
    position: np.ndarray
    heading: np.ndarray
    speed_kmh: np.ndarray
    start_speed_kmh: np.ndarray


def window_errors(cfg: DynamicsConfig, traces: Traces, steps: int, stride: int = 10) -> WindowErrors:
    """Native-vs-MetaDrive errors after ``steps`` steps of every window."""
    w = replay_windows(cfg, traces, steps, stride)
    end_native, end_md = w.native[:, -1], w.recorded[:, -1]
    return WindowErrors(
        w.trace,
        w.start,
        np.hypot(*(end_native[:, :2] - end_md[:, :2]).T),
        np.abs(wrap_angle(end_native[:, 2] - end_md[:, 2])),
        np.abs(end_native[:, 3] - end_md[:, 3]) * 3.6,
        w.recorded[:, 0, 3] * 3.6,
    )


def error_table(cfg: DynamicsConfig, traces: Traces, horizons: tuple[int, ...] = (10, 30), stride: int = 10) -> list[dict]:
    """One row per trace: its worst position / speed / heading error over its windows after each horizon (steps)."""
    rows = []
    per = {h: window_errors(cfg, traces, h, stride) for h in horizons}
    for k, name in enumerate(traces.names):
        row: dict = {"trace": str(name), "kind": str(traces.kinds[k])}
        for h, e in per.items():
            sel = e.trace == k
            row[f"start_kmh_max@{h}"] = float(e.start_speed_kmh[sel].max()) if sel.any() else float("nan")
            for key in ("position", "speed_kmh", "heading"):
                row[f"{key}@{h}"] = float(getattr(e, key)[sel].max()) if sel.any() else float("nan")
        rows.append(row)
    return rows
