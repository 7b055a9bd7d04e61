"""MetaDrive backend: the real MetaDrive 0.4.3 multi-agent scenarios behind the driving-env interface.

:class:`MetaDriveDrivingEnv` has the interface of the native
:class:`~coin_app.sim.driving_env.DrivingEnv` (``reset`` / ``step`` on dicts of agents,
``agents``, ``possible_agents``, ``episode_over``, the same per-agent info keys), so the
RLlib and PettingZoo adapters, the evaluation and the algorithms run on either backend with
``backend="metadrive"`` in the scenario config. MetaDrive is an optional extra
(``pip install -r requirements-metadrive.txt``); nothing else in coin_app imports it.

How the native config maps onto MetaDrive (``metadrive_config``): ``num_agents``,
``horizon`` (MetaDrive's horizon is also each vehicle's step limit, so ``max_agent_steps``
must equal it), ``delay_done``, ``allow_respawn``, the rewards, ``crash_penalty`` (vehicle and
object crashes), ``out_of_road_penalty``, the lidar (``lidar_beams``, ``lidar_range``, no
other-vehicle features), on the bottleneck the side / lane-line detector ranges and the neck's
centre line (``solid_center_line``: COIN's patched block parameter, set for the process). Keys
with no MetaDrive setting (the vehicle model, spawn jitter, ``navi_point_dist``...) are
refused by :func:`~coin_app.sim.config.make_config` unless left at their default.

What the adapter adds to MetaDrive:

* **Offline physics.** With ``metadrive_assets="skip"`` (default) the engine's asset pull
  is disabled before the engine starts, so nothing touches the network; everything except
  3D rendering works. ``render("topdown")`` draws with coin_app's renderer (same GIF and
  trajectory writers as the native env); ``render("metadrive_topdown")`` uses MetaDrive's
  own top-down renderer; 3D modes are refused with an explanation.
* **Seeding.** MetaDrive's multi-agent scenarios draw spawn places, spawn jitter and
  destinations from generators that ``reset(seed)`` does not control (the spawn manager
  ignores the seed, respawn places use a fresh OS-seeded generator). The adapter seeds the
  spawn manager with the episode seed and sets the respawn seed before every step from a
  generator seeded by it, so the same seed and actions give the same episode.
* **The 10-dim local state** s_i of the native env, from MetaDrive's vehicle objects
  (position, velocity, heading and the two navigation checkpoints exactly as MetaDrive's
  navigation places them), read before MetaDrive retires finished vehicles.
* **Native flags.** ``terminated`` = arrival, crash or leaving the road; a vehicle's step
  limit and the force stop at 5 x horizon are ``truncated`` only (MetaDrive's multi-agent
  envs report them as both). Crashes into static objects or buildings count as out of road.
  ``global_reward`` is the mean reward of the agents that acted.

MetaDrive runs one engine per process: a second open env in the same process is refused
with a clear message (close the first, or give each env its own process: RLlib env runners
with one env each, evaluation in a worker process).
"""

from __future__ import annotations

import importlib.util
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np

from coin_app.sim import schema
from coin_app.sim.config import ScenarioConfig, make_config
from coin_app.sim.inputs import checked_actions
from coin_app.sim.rendering import render_frame
from coin_app.sim.road_map import RoadMap, load_map
from coin_app.sim.scenes import SCENES
from coin_app.sim.sensors import local_state
from coin_app.sim.simulator import ACTIVE, DYING, MAX_RESPAWN_PER_STEP, agent_name

INSTALL_HINT = "install the optional extra: pip install -r requirements-metadrive.txt"
ENV_CLASSES = {name: s.metadrive_class for name, s in SCENES.items()}
FORCE_STOP_FACTOR = 5  # MetaDrive truncates every agent once the env step exceeds 5 x horizon
RENDER_MODES = ("topdown", "metadrive_topdown")
_OPEN: list[MetaDriveDrivingEnv] = []  # the adapter that owns this process's MetaDrive engine


def metadrive_available() -> bool:
    """Whether the optional ``metadrive-simulator`` package is installed."""
    return importlib.util.find_spec("metadrive") is not None


def open_in_this_process() -> bool:
    """Whether this process already has an open MetaDrive env (MetaDrive allows one engine per process)."""
    return bool(_OPEN)


def metadrive_assets_present() -> bool:
    """Whether MetaDrive's 3D assets (needed only for 3D rendering) are on disk."""
    spec = importlib.util.find_spec("metadrive")
    if spec is None or spec.origin is None:
        return False
    return (Path(spec.origin).parent / "assets" / "version.txt").exists()


def metadrive_config(config: ScenarioConfig) -> dict[str, Any]:
    """MetaDrive env config equivalent to the native scenario ``config``."""
    vehicle: dict[str, Any] = {"lidar": {"num_lasers": config.lidar_beams, "distance": config.lidar_range, "num_others": 0}}
    if config.obs_layout == "bottleneck96":  # the layout's side and lane-line detectors
        vehicle["side_detector"] = {"num_lasers": 4, "distance": config.side_detector_range}
        vehicle["lane_line_detector"] = {"num_lasers": 4, "distance": config.lane_line_detector_range}
    return {
        "num_agents": config.num_agents,
        "horizon": config.horizon,
        "delay_done": config.delay_done,
        "allow_respawn": config.allow_respawn,
        "driving_reward": config.driving_reward,
        "speed_reward": config.speed_reward,
        "success_reward": config.success_reward,
        "crash_vehicle_penalty": config.crash_penalty,
        "crash_object_penalty": config.crash_penalty,
        "out_of_road_penalty": config.out_of_road_penalty,
        "vehicle_config": vehicle,
        "use_render": False,
        "log_level": logging.CRITICAL,
        "start_seed": 0,
        "num_scenarios": 1,  # one fixed map; the adapter seeds the spawns itself
    }


def _import_metadrive(assets: str) -> Any:
    """The ``metadrive.envs.marl_envs`` module, with the asset pull disabled unless ``assets == "download"``."""
    if not metadrive_available():
        raise ImportError(f"backend 'metadrive' needs the metadrive-simulator package, which is not installed; {INSTALL_HINT}")
    os.environ.setdefault("SDL_VIDEODRIVER", "dummy")  # pygame (top-down renderer) without a display
    from metadrive.engine.base_engine import BaseEngine  # optional: the MetaDrive extra

    original = BaseEngine.__dict__.get("_coin_original_pull", BaseEngine.__dict__["try_pull_asset"])
    BaseEngine._coin_original_pull = original
    BaseEngine.try_pull_asset = staticmethod(lambda: None) if assets == "skip" else original
    import metadrive.envs.marl_envs as marl  # optional: the MetaDrive extra

    return marl


def _env_class(scenario: str, assets: str) -> type:
    """A subclass of MetaDrive's env for ``scenario`` that seeds its spawns and records final local states."""
    marl = _import_metadrive(assets)
    from metadrive.base_class.randomizable import Randomizable  # optional: the MetaDrive extra

    base = getattr(marl, ENV_CLASSES[scenario])

    class CoinMetaDriveEnv(base):  # type: ignore[misc, valid-type]
        """MetaDrive's env with seeded spawns and a hook that records states before vehicles are retired."""

        coin_seed = 0
        coin_state_fn: Any = None
        coin_final: dict[str, Any] = {}  # replaced in every step

        def setup_engine(self) -> None:
            """MetaDrive's engine setup, then seed the spawn manager with coin_app's episode seed."""
            super().setup_engine()
            manager = self.engine.spawn_manager
            env = self

            def seed(_scenario_seed: int) -> None:
                Randomizable.seed(manager, env.coin_seed)

            manager.seed = seed

        def _after_vehicle_done(self, obs: dict, reward: dict, terminated: dict, truncated: dict, info: dict) -> tuple:
            """Record every acting vehicle's pose before MetaDrive retires the finished ones."""
            self.coin_final = {aid: self.coin_state_fn(self.agents[aid]) for aid in terminated}
            return super()._after_vehicle_done(obs, reward, terminated, truncated, info)

    return CoinMetaDriveEnv


def bottleneck_center_line(solid: bool) -> None:
    """Build MetaDrive's bottleneck blocks with a solid neck centre line (COIN's patched ``pg_space``) or a broken one (0.4.3).

    Sets the blocks' parameter space for this process (MetaDrive runs one engine per process), not the installed package.
    """
    from metadrive.component.pg_space import BlockParameterSpace, ConstantSpace, ParameterSpace  # optional: the MetaDrive extra
    from metadrive.component.pgblock.bottleneck import Bottleneck  # optional: the MetaDrive extra

    space = {**BlockParameterSpace.BOTTLENECK_PARAMETER, "solid_center_line": ConstantSpace(int(solid))}
    Bottleneck.PARAMETER_SPACE = ParameterSpace(space)


@dataclass
class VehicleView:
    """A snapshot of the vehicles of a MetaDrive env in the native simulator's array layout (for rendering)."""

    map: RoadMap
    status: np.ndarray
    pos: np.ndarray
    heading: np.ndarray
    agent_num: np.ndarray
    half: np.ndarray
    episode_step: int


class MetaDriveDrivingEnv:
    """A MetaDrive multi-agent scenario with the native driving env's interface (see module doc)."""

    def __init__(self, config: ScenarioConfig | None = None, scenario: str = "intersection", preset: str = "paper", **overrides: Any):
        if config is None:
            config = make_config(scenario, preset, backend="metadrive", **overrides)
        elif config.backend != "metadrive":
            raise ValueError(f"config.backend is {config.backend!r}; build it with make_config(..., backend='metadrive')")
        self.config = config
        if _OPEN:
            raise RuntimeError(
                f"MetaDrive allows one engine per process and this process already has an open MetaDrive env "
                f"({_OPEN[0].config.scenario}); close() it first, or run each MetaDrive env in its own process "
                "(RLlib env runners with one env each; evaluation runs in a worker process)"
            )
        cls = _env_class(config.scenario, config.metadrive_assets)
        bottleneck_center_line(config.solid_center_line)
        self.map = load_map(config.scenario, config.solid_center_line)
        self.md = cls(metadrive_config(config))
        self.md.coin_state_fn = self._vehicle_state
        _OPEN.append(self)
        self.possible_agents = [
            agent_name(i) for i in range(config.num_agents + min(MAX_RESPAWN_PER_STEP, config.num_agents) * config.horizon)
        ]
        self._pool = frozenset(self.possible_agents)
        self.observation_space = gym.spaces.Box(0.0, 1.0, (config.obs_dim,), np.float32)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)
        self.agents: list[str] = []
        self.episode_over = True
        self._rng = np.random.default_rng()
        self._returns: dict[str, float] = {}
        self._last_pose: dict[str, tuple[float, float, float]] = {}
        self.closed = False

    @property
    def scenario(self) -> str:
        """Name of the scenario (map)."""
        return self.config.scenario

    # ------------------------------------------------------------------ lifecycle
    def reset(self, seed: int | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start a new episode (spawns drawn from ``seed``); returns observations and infos of the initial agents."""
        self._require_open()
        if seed is not None:
            if not isinstance(seed, (int, np.integer)) or seed < 0:
                raise ValueError(f"bad seed {seed!r}; allowed: an integer >= 0 or None")
            self._rng = np.random.default_rng(int(seed))
        episode_seed = int(self._rng.integers(2**31 - 1))
        self.md.coin_seed = episode_seed
        obs, _ = self.md.reset(seed=0)
        if len(obs) and next(iter(obs.values())).shape != (self.config.obs_dim,):
            raise RuntimeError(f"MetaDrive observations have shape {next(iter(obs.values())).shape}; expected ({self.config.obs_dim},)")
        self._returns = dict.fromkeys(obs, 0.0)
        states = {aid: self._vehicle_state(self.md.agents[aid]) for aid in obs}
        infos = {aid: self._info(aid, {}, states[aid], 0.0, spawned=True) for aid in obs}
        self.agents = self._check_ids(list(self.md.agents))
        self.episode_over = len(self.agents) == 0
        self._last_pose = {}
        self._remember(states)
        return {aid: np.asarray(o, np.float32) for aid, o in obs.items()}, infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Apply one action per agent in ``agents``; returns obs, rewards, terminations, truncations, infos."""
        self._require_open()
        if self.episode_over:
            raise RuntimeError("the episode is over (every vehicle is done); call reset() first")
        acts = checked_actions(actions, self.agents)
        acting = list(self.agents)
        self.md._DEBUG_RANDOM_SEED = int(self._rng.integers(2**31 - 1))  # seeds MetaDrive's respawn-place choice
        obs, rew, tm, tc, md_infos = self.md.step({aid: acts[aid] for aid in acting})
        final = self.md.coin_final
        g = float(np.mean([rew[a] for a in acting])) if acting else 0.0
        out_obs, rewards, terms, truncs, infos = {}, {}, {}, {}, {}
        states = dict(final)
        for aid in acting:
            info = md_infos[aid]
            r = float(rew[aid])
            self._returns[aid] += r
            done = bool(tm[aid] or tc[aid])
            reason = bool(info.get("arrive_dest") or info.get("crash_vehicle") or self._off_road(info))
            rewards[aid] = r
            terms[aid] = done and reason
            truncs[aid] = done and not reason
            out_obs[aid] = np.asarray(obs[aid], np.float32)
            infos[aid] = self._info(aid, info, final[aid], g, spawned=False)
        for aid in obs:
            if aid in rewards:
                continue
            self._returns[aid] = 0.0
            states[aid] = self._vehicle_state(self.md.agents[aid])
            out_obs[aid] = np.asarray(obs[aid], np.float32)
            infos[aid] = self._info(aid, {}, states[aid], g, spawned=True)
        self.agents = self._check_ids(list(self.md.agents))
        self.episode_over = len(self.agents) == 0
        self._last_pose = {}
        self._remember(states)
        return out_obs, rewards, terms, truncs, infos

    def close(self) -> None:
        """Shut the MetaDrive engine down (a new MetaDrive env can then be opened in this process)."""
        if not self.closed:
            self.closed = True
            if self in _OPEN:
                _OPEN.remove(self)
            self.md.close()

    def __enter__(self) -> MetaDriveDrivingEnv:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ pieces
    def _require_open(self) -> None:
        if self.closed:
            raise RuntimeError("this MetaDrive env is closed; create a new one")

    def _check_ids(self, ids: list[str]) -> list[str]:
        bad = [a for a in ids if a not in self._pool]
        if bad:
            raise RuntimeError(f"MetaDrive created agent ids {bad} beyond the declared pool of {len(self.possible_agents)} ids")
        return ids

    @staticmethod
    def _off_road(info: dict) -> bool:
        return bool(info.get("out_of_road") or info.get("crash_object") or info.get("crash_building"))

    def _info(self, aid: str, md_info: dict, state: np.ndarray, global_reward: float, spawned: bool) -> dict[str, Any]:
        """The native env's info dict of one agent."""
        return {
            schema.ARRIVE_DEST: bool(md_info.get("arrive_dest", False)),
            schema.CRASH_VEHICLE: bool(md_info.get("crash_vehicle", False)),
            schema.OUT_OF_ROAD: self._off_road(md_info),
            schema.MAX_STEP: bool(md_info.get("max_step", False)),
            schema.STEP_REWARD: float(md_info.get("step_reward", 0.0)) if not spawned else 0.0,
            schema.EPISODE_LENGTH: int(md_info.get("episode_length", 0)) if not spawned else 0,
            schema.EPISODE_REWARD: float(self._returns.get(aid, 0.0)),
            schema.STATE: state,
            schema.ENV_STEP: int(self.md.episode_step),
            schema.GLOBAL_REWARD: float(global_reward),
        }

    def _vehicle_state(self, vehicle: Any) -> np.ndarray:
        """The native 10-dim local state of one MetaDrive vehicle."""
        nav = vehicle.navigation
        mid = (float(nav.get_current_lane_num()) / 2 - 0.5) * nav.get_current_lane_width()
        ref1 = nav.current_ref_lanes[0]
        ref2 = nav.next_ref_lanes[0] if nav.next_ref_lanes is not None else ref1
        ck1 = np.asarray(ref1.position(ref1.length, mid), float)[None, :2]
        ck2 = np.asarray(ref2.position(ref2.length, mid), float)[None, :2]
        pos = np.asarray(vehicle.position, float)[None, :2]
        vel = np.asarray(vehicle.velocity, float)[None, :2]
        hd = np.array([float(vehicle.heading_theta)])
        cfg = self.config
        return local_state(pos, vel, hd, ck1, ck2, self.map.centre, self.map.scale, cfg.max_speed, cfg.navi_point_dist)[0]

    def _remember(self, states: dict[str, np.ndarray]) -> None:
        """Keep the pose of every vehicle of the last return (finished ones are drawn in traces at their end)."""
        for aid, s in states.items():
            x, y = s[:2] * self.map.scale + self.map.centre
            self._last_pose[aid] = (float(x), float(y), float(np.arctan2(s[5], s[4])))

    # ------------------------------------------------------------------ rendering
    @property
    def sim(self) -> VehicleView:
        """Active and dying vehicles (plus last poses of vehicles that just finished) as a simulator-like view."""
        self._require_open()
        rows: list[tuple[int, int, tuple[float, float, float]]] = []
        for aid, v in self.md.agents.items():
            rows.append((ACTIVE, _num(aid), (float(v.position[0]), float(v.position[1]), float(v.heading_theta))))
        for aid, v in self.md.agent_manager.dying_agents.items():
            rows.append((DYING, _num(aid), (float(v.position[0]), float(v.position[1]), float(v.heading_theta))))
        live = {num for _, num, _ in rows}
        for aid, pose in self._last_pose.items():
            if _num(aid) not in live:
                rows.append((0, _num(aid), pose))
        poses = np.array([p for _, _, p in rows], float).reshape(-1, 3)
        half = np.array([self.config.vehicle_length / 2, self.config.vehicle_width / 2])
        return VehicleView(
            self.map,
            np.array([s for s, _, _ in rows], np.int8),
            poses[:, :2],
            poses[:, 2],
            np.array([n for _, n, _ in rows], np.int64),
            half,
            int(self.md.episode_step),
        )

    def render(self, mode: str = "topdown", size: tuple[int, int] = (480, 480)) -> np.ndarray:
        """Top-down RGB frame (H, W, 3) uint8: coin_app's renderer (``"topdown"``) or MetaDrive's (``"metadrive_topdown"``)."""
        self._require_open()
        if mode == "topdown":
            return render_frame(self, size=size)
        if mode == "metadrive_topdown":
            return np.asarray(self.md.render(mode="topdown", window=False, screen_size=size))
        if not metadrive_assets_present():
            raise RuntimeError(
                f"render mode {mode!r} needs MetaDrive's 3D assets, which are not on this machine (physics-only mode, "
                f"metadrive_assets={self.config.metadrive_assets!r}); allowed without assets: {', '.join(RENDER_MODES)}"
            )
        raise ValueError(
            f"unknown render mode {mode!r}; allowed: {', '.join(RENDER_MODES)} (coin_app does not drive MetaDrive's 3D window)"
        )


def _num(agent_id: str) -> int:
    return int(agent_id[len("agent") :])


__all__ = ["MetaDriveDrivingEnv", "VehicleView", "metadrive_available", "metadrive_assets_present", "metadrive_config"]
