"""Scenario configuration: every constant of a native driving scenario in one dataclass.

Defaults follow the COIN paper where it speaks (penalties 5, lidar 50 m) and MetaDrive
0.4.3's multi-agent scenarios elsewhere (``docs/decisions.md`` §2.1, §3.1). The preset
``metadrive_compat`` restores MetaDrive's own values (penalties 10, lidar 40 m).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field, fields
from typing import Any

from coin_app.sim.road_map import MAP_NAMES
from coin_app.sim.scenes import SCENES

DEFAULT_NUM_AGENTS = {name: s.default_vehicles for name, s in SCENES.items()}  # COIN Table 5.1 (sim/scenes.py)
SPAWN_CAPACITY = 48  # MetaDrive's spawn slots per map (6 per lane of every spawn road)


DYNAMICS_MODELS = ("raycast", "bicycle")
PHYSICS_DT = 0.02  # s, MetaDrive's physics step (the raycast vehicle takes dt / PHYSICS_DT of them per env step)


@dataclass(frozen=True)
class DynamicsConfig:
    """Vehicle model: MetaDrive's car as Bullet simulates it (``model="raycast"``), or a bicycle model.

    ``model="raycast"`` (default) steps a port of Bullet's raycast vehicle with MetaDrive's own
    constants (``coin_app/sim/vehicle.py``); it uses ``dt``, ``max_steer_deg`` and
    ``max_speed_kmh`` of this config and ignores the bicycle constants. ``model="bicycle"`` is
    the kinematic bicycle whose constants below were fitted to MetaDrive's car before the port
    (``maps/vehicle_dynamics_fit.json``; ``curvature_per_steer=None`` gives the textbook
    tan(delta)/L). With ``yaw_rate_alpha=1, beta_gain=0, scrub=0, brake_steer=0,
    lateral_grip=inf`` the bicycle is exactly the seed-2 paper's Eq. 1 in semi-implicit order
    (the ``kinematic`` preset).
    """

    model: str = "raycast"  # "raycast" (MetaDrive's Bullet vehicle) | "bicycle"
    dt: float = 0.1  # s per env step (MetaDrive: 5 x 0.02 s)
    max_steer_deg: float = 40.0  # steering angle at |a0| = 1
    wheelbase: float = 2.46894  # m, front to rear axle
    curvature_per_steer: float | None = 0.2697195149202444  # 1/m per unit a0 (fit), None = tan(delta)/L
    throttle_accel: float = 2.909090909090909  # m/s^2 per unit a1 > 0 (4 x 800 N / 1100 kg)
    coast_decel: float = 0.36363636363636365  # m/s^2 at a1 = 0 or above max speed
    brake_linear: float = 27.272727272727273  # m/s^2 per unit brake, below saturation
    brake_sat_intercept: float = 5.414138062029027  # friction-limited brake: c + k*b
    brake_sat_slope: float = 9.650087717020922
    max_speed_kmh: float = 80.0
    lateral_grip: float = 8.707595044203563  # m/s^2, lateral acceleration cap at a0 = 0
    lateral_grip_steer2: float = 2.706596419114096  # cap drops by this * a0^2
    yaw_rate_alpha: float = 0.333176619483477  # first-order lag of the yaw rate per step
    scrub: float = 0.27399397868708614  # speed loss ~ |v r tan(delta)| in hard turns
    scrub_throttle: float = 2.724422022498398
    brake_steer: float = 0.5054811796176552  # brake loses this fraction at full lock
    beta_gain: float = 0.7144937481838857  # sideslip of the centre, fraction of kinematic
    lf: float = 1.05234  # m, centre to front axle
    lr: float = 1.4166  # m, centre to rear axle

    @classmethod
    def kinematic(cls) -> DynamicsConfig:
        """The plain seed-2 bicycle (Eq. 1) with MetaDrive's geometry and pedal mapping."""
        return cls(
            model="bicycle", curvature_per_steer=None, lateral_grip=math.inf, yaw_rate_alpha=1.0, scrub=0.0, brake_steer=0.0, beta_gain=0.0
        )


@dataclass(frozen=True)
class ScenarioConfig:
    """All constants of one native scenario; build with :func:`make_config`."""

    scenario: str = "intersection"
    num_agents: int = 30  # vehicles at reset; the cap on active + dying while respawning
    horizon: int = 1000  # env steps with respawn; also each vehicle's own step limit
    max_agent_steps: int = 1000  # a vehicle is truncated (max_step) after this many own steps
    delay_done: int = 25  # steps a crashed / off-road vehicle stays as a static obstacle
    allow_respawn: bool = True  # respawn at free entry places while the episode step is below the horizon
    respawns_per_step: int = 1  # at most this many respawns per env step and env (MetaDrive 0.4.3: one); 0: no limit
    own_arm_destinations: bool = True  # MetaDrive also draws the spawn arm's exit (U-turn / full loop)
    # the bottleneck's neck has a solid yellow centre line: touching it is off-road and the side detectors see it (COIN's
    # patched MetaDrive); MetaDrive 0.4.3 builds it broken (metadrive_compat). The other scenes' centre lines are solid
    solid_center_line: bool = True
    force_stop_factor: int = 5  # every agent is truncated at env step factor * horizon
    spawn_jitter_long: float = 1.0  # initial spawns: longitude += U(-a, a) (m)
    spawn_jitter_lat: float = 0.25  # initial spawns: lateral += U(-a, a) (m)
    # reward (COIN App. A.3)
    driving_reward: float = 1.0  # per metre of progress along the localised lane
    speed_reward: float = 0.1  # times speed_kmh / max_speed_kmh (80), per step
    success_reward: float = 10.0  # on arrival, in place of the step reward
    crash_penalty: float = 5.0  # subtracted on a crash into another vehicle (paper 5; MetaDrive 10)
    out_of_road_penalty: float = 5.0  # subtracted when leaving the road (paper 5; MetaDrive 10)
    # sensors
    lidar_beams: int = 72  # beams over 360 degrees, beam 0 straight ahead
    lidar_range: float = 50.0  # m (paper; MetaDrive 40: the metadrive_compat preset)
    navi_point_dist: float = 50.0  # navigation vectors are clipped to this length (m)
    # "standard": 19 ego/navigation features + lidar (91); "bottleneck96": MetaDrive's
    # bottleneck layout with 4-beam side (solid lines, 50 m) and lane-line (20 m) detectors
    obs_layout: str = "standard"
    side_detector_range: float = 50.0  # m, bottleneck96's side detectors (solid lines)
    lane_line_detector_range: float = 20.0  # m, bottleneck96's lane-line detectors (all line dashes)
    # vehicle
    vehicle_length: float = 4.515  # m, MetaDrive's car
    vehicle_width: float = 1.852  # m
    dynamics: DynamicsConfig = field(default_factory=DynamicsConfig)
    # simulator: "native" (coin_app's vectorized core) or "metadrive" (MetaDrive 0.4.3, optional extra)
    backend: str = "native"
    # MetaDrive's 3D assets: "skip" = physics only, never touches the network (default);
    # "download" = let MetaDrive pull its assets from GitHub (needs network; 3D rendering)
    metadrive_assets: str = "skip"

    @property
    def obs_dim(self) -> int:
        """Observation length: 19 (or 24 with detectors) ego/navigation features + lidar beams."""
        return (24 if self.obs_layout == "bottleneck96" else 19) + self.lidar_beams

    @property
    def dt(self) -> float:
        """Seconds per env step."""
        return self.dynamics.dt

    @property
    def max_speed(self) -> float:
        """Maximum speed in m/s."""
        return self.dynamics.max_speed_kmh / 3.6


PRESETS: dict[str, dict[str, Any]] = {
    "paper": {},
    "metadrive_compat": {"crash_penalty": 10.0, "out_of_road_penalty": 10.0, "lidar_range": 40.0, "solid_center_line": False},
    "kinematic": {"dynamics": DynamicsConfig.kinematic()},
}

_POSITIVE_INT = ("num_agents", "horizon", "max_agent_steps", "lidar_beams", "force_stop_factor")
_NON_NEGATIVE = (
    "delay_done",
    "spawn_jitter_long",
    "spawn_jitter_lat",
    "driving_reward",
    "speed_reward",
    "success_reward",
    "crash_penalty",
    "out_of_road_penalty",
)
_POSITIVE = ("lidar_range", "navi_point_dist", "vehicle_length", "vehicle_width", "side_detector_range", "lane_line_detector_range")
_BOOL = tuple(f.name for f in fields(ScenarioConfig) if f.type in ("bool", bool))  # switches: True or False
OBS_LAYOUTS = ("standard", "bottleneck96")
BACKENDS = ("native", "metadrive")
METADRIVE_ASSETS = ("skip", "download")
# keys with no MetaDrive counterpart: the metadrive backend refuses values other than the default
METADRIVE_FIXED = (
    "dynamics",
    "force_stop_factor",
    "spawn_jitter_long",
    "spawn_jitter_lat",
    "vehicle_length",
    "vehicle_width",
    "navi_point_dist",
    "own_arm_destinations",
    "respawns_per_step",
)


def _check(name: str, value: Any, ok: bool, allowed: str) -> None:
    if not ok:
        raise ValueError(f"bad value for {name!r}: {value!r}; allowed: {allowed}")


def make_config(scenario: str = "intersection", preset: str = "paper", **overrides: Any) -> ScenarioConfig:
    """Validated config of ``scenario`` with a preset and key overrides applied.

    Unknown keys and bad values raise ``ValueError`` naming the key and what is allowed.
    ``dynamics`` accepts a :class:`DynamicsConfig` or a dict of its fields.
    """
    if scenario not in MAP_NAMES:
        raise ValueError(f"unknown scenario {scenario!r}; allowed: {', '.join(MAP_NAMES)}")
    if preset not in PRESETS:
        raise ValueError(f"unknown preset {preset!r}; allowed: {', '.join(PRESETS)}")
    allowed = {f.name for f in fields(ScenarioConfig)} - {"scenario"}
    unknown = sorted(set(overrides) - allowed)
    if unknown:
        raise ValueError(f"unknown config key(s) {unknown}; allowed: {', '.join(sorted(allowed))}")
    values: dict[str, Any] = {"num_agents": DEFAULT_NUM_AGENTS[scenario], **PRESETS[preset], **overrides}
    dyn = values.get("dynamics", DynamicsConfig())
    if isinstance(dyn, dict):
        dyn_allowed = {f.name for f in fields(DynamicsConfig)}
        bad = sorted(set(dyn) - dyn_allowed)
        if bad:
            raise ValueError(f"unknown dynamics key(s) {bad}; allowed: {', '.join(sorted(dyn_allowed))}")
        dyn = DynamicsConfig(**dyn)
    _check("dynamics", dyn, isinstance(dyn, DynamicsConfig), "a DynamicsConfig or a dict of its fields")
    _check("dynamics.model", dyn.model, dyn.model in DYNAMICS_MODELS, " | ".join(DYNAMICS_MODELS))
    for f in fields(DynamicsConfig):
        v = getattr(dyn, f.name)
        if (f.name == "curvature_per_steer" and v is None) or f.name == "model":
            continue
        _check(
            f"dynamics.{f.name}",
            v,
            isinstance(v, (int, float)) and not isinstance(v, bool) and v >= 0 and not math.isnan(v),
            "a number >= 0",
        )
    _check("dynamics.dt", dyn.dt, dyn.dt > 0, "a number > 0")
    if dyn.model == "raycast":  # whole physics steps of 0.02 s (MetaDrive's physics_world_step_size)
        ok = abs(dyn.dt / PHYSICS_DT - round(dyn.dt / PHYSICS_DT)) < 1e-9
        _check("dynamics.dt", dyn.dt, ok, f"a multiple of {PHYSICS_DT} s with model 'raycast'")
    values["dynamics"] = dyn
    for k in _POSITIVE_INT:
        v = values.get(k, getattr(ScenarioConfig, k, None))
        _check(k, v, isinstance(v, int) and not isinstance(v, bool) and v > 0, "an integer > 0")
    for k in _NON_NEGATIVE + _POSITIVE:
        v = values.get(k, getattr(ScenarioConfig, k, None))
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        ok = ok and (v > 0 if k in _POSITIVE else v >= 0)
        _check(k, v, ok, "a finite number > 0" if k in _POSITIVE else "a finite number >= 0")
    v = values.get("respawns_per_step", ScenarioConfig.respawns_per_step)
    _check("respawns_per_step", v, isinstance(v, int) and not isinstance(v, bool) and v >= 0, "an integer >= 0 (0: no limit)")
    n = values["num_agents"]
    _check("num_agents", n, n <= SPAWN_CAPACITY, f"an integer from 1 to {SPAWN_CAPACITY} (the map's spawn slots)")
    layout = values.get("obs_layout", "standard")
    _check("obs_layout", layout, layout in OBS_LAYOUTS, " | ".join(OBS_LAYOUTS))
    for key in _BOOL:
        v = values.get(key, getattr(ScenarioConfig, key))
        _check(key, v, isinstance(v, bool), "True or False")
    backend = values.get("backend", "native")
    _check("backend", backend, backend in BACKENDS, " | ".join(BACKENDS))
    assets = values.get("metadrive_assets", "skip")
    _check("metadrive_assets", assets, assets in METADRIVE_ASSETS, " | ".join(METADRIVE_ASSETS))
    if backend == "metadrive":
        _metadrive_rules(scenario, values)
    return dataclasses.replace(ScenarioConfig(scenario=scenario), **values)


def _metadrive_rules(scenario: str, values: dict[str, Any]) -> None:
    """Refuse keys MetaDrive cannot honour; give each scene MetaDrive's own observation layout (``Scene.metadrive_obs_layout``)."""
    default = ScenarioConfig()
    for key in METADRIVE_FIXED:
        if key in values and values[key] != getattr(default, key):
            raise ValueError(
                f"bad value for {key!r} with backend 'metadrive': {values[key]!r}; MetaDrive has no such setting, "
                f"allowed: only the default {getattr(default, key)!r} (or use backend 'native')"
            )
    horizon = values.get("horizon", default.horizon)
    steps = values.get("max_agent_steps", horizon)
    _check("max_agent_steps", steps, steps == horizon, f"equal to horizon ({horizon}) with backend 'metadrive' (one MetaDrive setting)")
    values["max_agent_steps"] = horizon
    layout = SCENES[scenario].metadrive_obs_layout
    got = values.setdefault("obs_layout", layout)
    _check("obs_layout", got, got == layout, f"{layout!r} on the MetaDrive {scenario} (MetaDrive's own observation)")
