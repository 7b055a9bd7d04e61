"""RLlib (2.60, new API stack) ``MultiAgentEnv`` adapter of the driving env, and its registration.

Contract of :class:`CoinMultiAgentEnv` (``docs/decisions.md`` §6.1-6.3):

* ``possible_agents`` is the whole id pool of an episode; ``observation_spaces`` /
  ``action_spaces`` map every pool id to one shared ``Box`` object, so an agent that
  spawns mid-episode always has declared spaces (``NormalizeAndClipActions`` needs them).
  Ids are strings, restart at ``agent0`` on ``reset`` and are never reused in an episode.
* ``terminateds`` and ``truncateds`` always hold ``"__all__"``. ``terminateds["__all__"]``
  is True when the episode is over: the driving env has no acting agent left
  (``DrivingEnv.episode_over``), *or* every agent that acted in this step is done in this
  step. In the second case RLlib's ``MultiAgentEpisode`` ends the episode by itself (all
  agents it has seen are done) and drops agents that first appear in that step, while the
  vector env would not reset and would keep stepping the env with empty actions. So in
  that step the adapter ends the episode itself and **drops the observations and infos of
  the agents spawned in that step**; RLlib never sees them and the next ``step`` call of
  the vector env resets this env.
* ``truncateds["__all__"]`` is True when the episode is over and every agent that finished
  in the last step finished by a time limit. RLlib still marks such an episode (and its
  agents) as terminated as well (``docs/decisions.md`` §6.2 item 5).
* A vehicle's own step limit (``max_step``) and the env's force stop are per-agent
  ``truncated=True, terminated=False``; arrival, crash and leaving the road are
  ``terminated=True``.
* ``infos`` only has agents that have an observation in the same return; ``rewards`` /
  per-agent flags only agents that acted in the step.
* ``config["lcf"] = {"mean": m, "std": s}`` (CoPO) gives every agent a local coordination
  factor at spawn, appended to its observation (``coin_app.adapters.lcf``);
  ``set_lcf_distribution`` moves the distribution for agents spawned later.
* ``outcomes`` counts the agents that ended since it was last cleared (``finished``) and how
  many of them succeeded (``arrive_dest`` / arena ``success``) or had collided, and, on the
  driving scenarios, the agent steps taken (``agent_steps``) and the sum of the acting vehicles'
  speeds after each step (``speed_sum``, m/s: training's stand-still detector reads their ratio);
  the ``AgentOutcomes`` callback (``coin_app.algorithms.common``) moves them into the env runner
  metrics.
* RLlib's env checker (``disable_env_checking=False``) steps once after ``reset(seed=42)``
  and requires every returned id to still be in ``agents``; it fails if an agent is done
  on that very first step (not the case for the shipped scenarios).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from functools import partial
from typing import Any

import numpy as np
from ray.rllib.env.multi_agent_env import MultiAgentEnv
from ray.tune.registry import register_env

from coin_app.adapters.lcf import LocalCoordination
from coin_app.backends.factory import make_driving_env
from coin_app.sim import schema
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.inputs import check_seed
from coin_app.sim.scenarios import env_config as env_config_of_parts
from coin_app.sim.scenarios import scenario_name
from coin_app.sim.scenes import SCENARIOS, env_id

OUTCOMES = ("finished", "succeeded", "collided", "agent_steps", "speed_sum")  # CoinMultiAgentEnv.outcomes (module doc)
SCENARIO_CONFIG_KEY = "scenario_config"  # env_config key of an already parsed (typed) scenario config
WHO = "CoinMultiAgentEnv"  # how the shared checks name this env
ADAPTER_KEYS = ("scenario", "lcf", SCENARIO_CONFIG_KEY)  # env_config keys of the adapter itself, not of the scenario
ENV_IDS: dict[str, str] = {env_id(name): name for name in SCENARIOS}


def env_id_of(config: ScenarioConfig | ArenaConfig) -> str:
    """The registered env id of a parsed scenario config (``coin-<scenario>-v0``)."""
    return env_id(scenario_name(config))


class CoinMultiAgentEnv(MultiAgentEnv):
    """A COIN driving scenario as an RLlib ``MultiAgentEnv`` with respawning agents (see module doc).

    ``config`` holds either ``scenario_config``, a parsed :class:`~coin_app.sim.config.ScenarioConfig`
    or :class:`~coin_app.sim.arena.config.ArenaConfig` (what :func:`env_config_of` writes and the
    algorithms pass: the config is parsed once, where the run is set up), or ``scenario``
    (default ``"intersection"``; ``"arena"`` takes ``ArenaConfig`` fields instead), ``preset``
    (default ``"paper"``) and any ``ScenarioConfig`` field as an override (``backend="metadrive"``
    runs MetaDrive itself). Optionally ``lcf`` (``{"mean", "std"}``: CoPO's local coordination
    factors). An unknown key raises ``ValueError`` naming it and the allowed keys.
    """

    def __init__(self, config: Mapping[str, Any] | None = None):
        super().__init__()
        self.config, lcf = parse_env_config(config)
        self.driving_env = make_driving_env(self.config)
        self.lcf = None if lcf is None else LocalCoordination(**lcf)
        self.metadata = {"render_modes": [], "render_fps": round(1.0 / self.config.dt)}
        self.possible_agents = list(self.driving_env.possible_agents)
        obs_space, act_space = self.driving_env.observation_space, self.driving_env.action_space
        if self.lcf is not None:
            obs_space = self.lcf.observation_space(obs_space)
        self.observation_spaces = dict.fromkeys(self.possible_agents, obs_space)
        self.action_spaces = dict.fromkeys(self.possible_agents, act_space)
        self.agents = []
        self._over = True
        self.outcomes = dict.fromkeys(OUTCOMES, 0)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[dict[str, np.ndarray], dict[str, dict]]:
        """Start a new episode (``seed``: None or an integer >= 0); returns observations and infos of the initial agents
        (``options`` is unused)."""
        seed = check_seed(seed)
        super().reset(seed=seed, options=options)
        obs, infos = self.driving_env.reset(seed)
        self.agents = list(self.driving_env.agents)
        self._over = False
        if self.lcf is not None:
            self.lcf.reset(seed)
            obs, infos = self.lcf.augment(obs, infos)
        return obs, infos

    def step(self, action_dict: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        """Act for every agent in ``agents``; returns obs, rewards, terminateds, truncateds, infos."""
        if self._over:
            raise RuntimeError("the episode is over; call reset() first")
        acting = list(self.driving_env.agents)
        obs, rewards, terms, truncs, infos = self.driving_env.step(action_dict)
        ended = [a for a in acting if terms[a] or truncs[a]]
        self._count_outcomes([infos[a] for a in ended])
        self._count_speeds([infos[a] for a in acting])
        over = self.driving_env.episode_over or len(ended) == len(acting)
        if over:
            for aid in [a for a in obs if a not in rewards]:  # spawned in this step
                del obs[aid], infos[aid]
            self.agents = []
            self._over = True
        else:
            self.agents = list(self.driving_env.agents)
        terms["__all__"] = over
        truncs["__all__"] = over and all(truncs[a] for a in ended)
        if self.lcf is not None:
            obs, infos = self.lcf.augment(obs, infos)
        return obs, rewards, terms, truncs, infos

    def _count_outcomes(self, final_infos: list[dict[str, Any]]) -> None:
        """Add the ended agents' outcomes (their last infos) to ``outcomes``."""
        self.outcomes["finished"] += len(final_infos)
        self.outcomes["succeeded"] += sum(bool(i.get(schema.ARRIVE_DEST, i.get(schema.SUCCESS, False))) for i in final_infos)
        self.outcomes["collided"] += sum(bool(i.get(schema.CRASH_VEHICLE, i.get(schema.COLLIDED, False))) for i in final_infos)

    def _count_speeds(self, infos: list[dict[str, Any]]) -> None:
        """Add the acting vehicles' steps and speeds after the step (m/s, from their local state) to ``outcomes``."""
        if not infos or not isinstance(self.config, ScenarioConfig):
            return
        velocity = np.stack([i[schema.STATE][2:4] for i in infos])  # v / max_speed (sim/sensors.py local_state)
        self.outcomes["agent_steps"] += len(infos)
        self.outcomes["speed_sum"] += float(np.hypot(velocity[:, 0], velocity[:, 1]).sum()) * self.config.max_speed

    def set_start_difficulty(self, difficulty: float) -> None:
        """The arena curriculum's start spread for scenarios generated from now on (``ArenaConfig.start_difficulty``)."""
        setter = getattr(self.driving_env, "set_start_difficulty", None)
        if setter is None:
            raise ValueError(f"start_difficulty is an arena setting; this env runs {type(self.config).__name__}")
        setter(difficulty)
        self.config = self.driving_env.config

    def set_num_agents(self, n: int) -> None:
        """A curriculum's phase: vehicles at reset (and the respawn cap) from the next episode on, 1 to the config's num_agents."""
        setter = getattr(self.driving_env, "set_num_agents", None)
        if setter is None:
            raise ValueError(f"a num_agents curriculum needs the native driving simulator; this env runs {type(self.driving_env).__name__}")
        setter(n)

    def set_lcf_distribution(self, mean: float, std: float) -> None:
        """Draw the LCFs of agents spawned from now on from N(mean, std) (an env with LCFs only)."""
        if self.lcf is None:
            raise RuntimeError("this env has no local coordination factors (env_config has no 'lcf')")
        self.lcf.set_distribution(mean, std)

    def close(self) -> None:
        """Release the backend (shuts a MetaDrive engine down)."""
        self.driving_env.close()


def _scenario_config(env_config: dict[str, Any]) -> ScenarioConfig | ArenaConfig:
    """The scenario config of an env_config without its ``lcf``: the typed one it carries, or parsed from overrides."""
    if SCENARIO_CONFIG_KEY not in env_config:
        return env_config_of_parts(None, env_config.pop("scenario", None), env_config.pop("preset", None), env_config, WHO)
    config = env_config.pop(SCENARIO_CONFIG_KEY)
    if not isinstance(config, (ScenarioConfig, ArenaConfig)):
        raise ValueError(f"bad env_config scenario_config {config!r}; allowed: a ScenarioConfig or an ArenaConfig")
    name = env_config.pop("scenario", scenario_name(config))
    if name != scenario_name(config):
        raise ValueError(f"env_config has a scenario_config of {scenario_name(config)!r} and scenario {name!r}; allowed: one scenario")
    return env_config_of_parts(config, None, env_config.pop("preset", None), env_config, WHO)  # refuses any other key: never dropped


def parse_env_config(env_config: Mapping[str, Any] | None) -> tuple[ScenarioConfig | ArenaConfig, dict[str, float] | None]:
    """(scenario config, CoPO's LCF distribution or None) of an adapter ``env_config``; a ValueError names a bad key or value."""
    overrides = dict(env_config or {})
    lcf = overrides.pop("lcf", None)
    if lcf is not None and not (isinstance(lcf, Mapping) and set(lcf) <= {"mean", "std"}):
        raise ValueError(f"bad env_config lcf {lcf!r}; allowed: None or a dict with keys 'mean' and 'std'")
    return _scenario_config(overrides), None if lcf is None else dict(lcf)


def env_config_of(config: ScenarioConfig | ArenaConfig, lcf: Mapping[str, float] | None = None) -> dict[str, Any]:
    """The RLlib ``env_config`` of a parsed scenario config (and CoPO's LCF distribution): the typed config travels as is."""
    out: dict[str, Any] = {"scenario": scenario_name(config), SCENARIO_CONFIG_KEY: config}
    if lcf is not None:
        out["lcf"] = dict(lcf)
    return out


def make_env(scenario: str, env_config: Mapping[str, Any] | None = None) -> CoinMultiAgentEnv:
    """Env of ``scenario`` with ``env_config`` overrides merged on (a different ``scenario`` key is an error)."""
    cfg = dict(env_config or {})
    if cfg.get("scenario", scenario) != scenario:
        raise ValueError(f"env_config scenario {cfg['scenario']!r} contradicts the registered scenario {scenario!r}")
    cfg["scenario"] = scenario
    return CoinMultiAgentEnv(cfg)


def register_envs() -> list[str]:
    """Register ``coin-<scenario>-v0`` for every scenario with Ray Tune; returns the env ids."""
    for name, scenario in ENV_IDS.items():
        creator: Callable[[Mapping[str, Any] | None], CoinMultiAgentEnv] = partial(make_env, scenario)
        register_env(name, creator)
    return list(ENV_IDS)
