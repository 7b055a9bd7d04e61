"""The table of trainable algorithms, and the routing of ``--set key=value`` overrides.

Each algorithm package exports its :class:`~coin_app.algorithms.spec.AlgorithmSpec`; this
module only lists them. An override key goes to the scenario config (``ScenarioConfig`` /
``ArenaConfig`` fields) or to the algorithm's documented hyper-parameters; anything else is
refused with the allowed keys listed.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

from coin_app.algorithms.choices import ALGORITHM_NAMES
from coin_app.algorithms.cig_td3.settings import CIG_TD3
from coin_app.algorithms.copo.settings import COPO
from coin_app.algorithms.nav_ppo.settings import NAV_PPO
from coin_app.algorithms.ppo_family.settings import CPPO, IPPO, MFPO
from coin_app.algorithms.spec import AlgorithmSpec
from coin_app.algorithms.td3.settings import ITD3
from coin_app.algorithms.traco.settings import TRACO
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import PRESETS, ScenarioConfig
from coin_app.sim.road_map import load_map
from coin_app.sim.scenarios import AnyScenarioConfig, config_from_dict
from coin_app.sim.scenes import DRIVING_SCENARIOS
from coin_app.sim.seeds import check_training_seed

ALGORITHMS: dict[str, AlgorithmSpec] = {spec.name: spec for spec in (CIG_TD3, ITD3, TRACO, IPPO, CPPO, MFPO, COPO, NAV_PPO)}
if tuple(ALGORITHMS) != ALGORITHM_NAMES:  # the CLI parses --algo from the Ray-free name list
    raise ImportError(f"choices.ALGORITHM_NAMES {ALGORITHM_NAMES} does not match the registry {tuple(ALGORITHMS)}")

# A small setting that learns within minutes on a laptop CPU (--quick, the CI learning test, benchmarks/learning_curves.py,
# the smoke and reduced scales): 4 vehicles and episodes of 300 env steps on the intersection (its longest route, 150.5 m,
# at 5 m/s); every other scene's horizon fits its own longest route in the same way (quick_scenario). Each spec's ``quick``
# adds its small-network settings.
QUICK_SCENARIO: dict[str, Any] = {"num_agents": 4, "horizon": 300, "max_agent_steps": 300}
QUICK_SETTINGS: dict[str, Any] = {**QUICK_SCENARIO, **CIG_TD3.quick}  # CIG-TD3 / ITD3 on the quick scenario

# The smallest settings that build, update and checkpoint in seconds (the tests' tiny runs, tests/fixtures.py): short
# episodes of a few vehicles (the arena: its short step limit), plus each spec's ``tiny`` (small networks and batches).
TINY_SCENARIO: dict[str, Any] = {"num_agents": 3, "horizon": 40, "max_agent_steps": 40}
TINY_ARENA: dict[str, Any] = {"max_steps": 40}


# --set keys of every algorithm: how it samples (the algorithm's own keys say how much)
RUNNER_KEYS: dict[str, tuple[Any, str]] = {
    "env_runner": (
        "auto",
        "'batched' (coin_app's vectorized env runner: all vehicles of all envs in one forward pass per step), "
        "'multi_agent' (RLlib's MultiAgentEnvRunner on the MultiAgentEnv adapter), 'auto' = batched on the native "
        "simulator, multi_agent on MetaDrive",
    ),
    "num_envs_per_env_runner": (
        "auto",
        "envs each env runner steps in lock step; 'auto' = on-policy: the train batch in one sampling round "
        "(batch / (rollout_fragment_length x runners)), off-policy: 1",
    ),
}
ENV_RUNNERS = ("auto", "batched", "multi_agent")
# --set keys of every algorithm: where its learner runs (RLlib's AlgorithmConfig.learners)
LEARNER_KEYS: dict[str, tuple[Any, str]] = {
    "num_learners": (
        0,
        "remote learner actors: 0 = the learner runs in the training process, 1 = one remote learner (e.g. on a GPU node; "
        "the batches are sent to it); more are not supported (one replay buffer, one LCF distribution)",
    ),
    "num_gpus_per_learner": (0, "GPUs per learner (with num_learners=0: for the learner in the training process)"),
}
COMMON_KEYS: dict[str, tuple[Any, str]] = {**RUNNER_KEYS, **LEARNER_KEYS}


@dataclass(frozen=True)
class RunSettings:
    """How a run samples and where its learner runs (the ``COMMON_KEYS`` values)."""

    env_runner: str = "auto"
    num_envs_per_env_runner: int | str = "auto"
    num_learners: int = 0
    num_gpus_per_learner: float = 0


def get(name: str) -> AlgorithmSpec:
    """The spec of algorithm ``name``; unknown names raise a ValueError listing the choices."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; allowed: {', '.join(sorted(ALGORITHMS))}")
    return ALGORITHMS[name]


def keys(name: str) -> tuple[str, ...]:
    """All ``--set`` keys of algorithm ``name`` besides the scenario's: its own, the sampling and the learner ones."""
    return (*get(name).keys(), *COMMON_KEYS)


def split_run_settings(algo_cfg: dict[str, Any]) -> RunSettings:
    """Pop the ``COMMON_KEYS`` from an algorithm's ``--set`` values; a ValueError names a bad one."""
    run = RunSettings(**{k: algo_cfg.pop(k) for k in COMMON_KEYS if k in algo_cfg})
    if run.env_runner not in ENV_RUNNERS:
        raise ValueError(f"bad value for 'env_runner': {run.env_runner!r}; allowed: {', '.join(map(repr, ENV_RUNNERS))}")
    n_envs = run.num_envs_per_env_runner
    if n_envs != "auto" and not (isinstance(n_envs, int) and not isinstance(n_envs, bool) and n_envs >= 1):
        raise ValueError(f"bad value for 'num_envs_per_env_runner': {n_envs!r}; allowed: 'auto' or an integer >= 1")
    if run.num_learners not in (0, 1) or isinstance(run.num_learners, bool):
        raise ValueError(
            f"bad value for 'num_learners': {run.num_learners!r}; "
            "allowed: 0 (the learner in the training process) or 1 (one remote learner)"
        )
    gpus = run.num_gpus_per_learner
    if isinstance(gpus, bool) or not isinstance(gpus, (int, float)) or not gpus >= 0:
        raise ValueError(f"bad value for 'num_gpus_per_learner': {gpus!r}; allowed: a number >= 0 (1 = one GPU per learner)")
    return run


def longest_route(scenario: str) -> float:
    """Metres of the longest spawn-to-destination route of driving scenario ``scenario``'s map."""
    road_map = load_map(scenario)
    lane_of = [next(int(lane) for lane in lanes if lane >= 0) for lanes in road_map.road_lanes]
    return max(sum(float(road_map.length[lane_of[road]]) for road in route.roads) for route in road_map.routes)


def quick_scenario(scenario: str = "intersection") -> dict[str, Any]:
    """The quick scenario on ``scenario``: ``QUICK_SCENARIO`` with a horizon scaled by the scene's longest route against the
    intersection's (to the nearest 10 steps; intersection 300, roundabout 690, bottleneck 340)."""
    if scenario == "intersection" or scenario not in DRIVING_SCENARIOS:
        return dict(QUICK_SCENARIO)
    horizon = int(round(QUICK_SCENARIO["horizon"] * longest_route(scenario) / longest_route("intersection"), -1))
    return QUICK_SCENARIO | {"horizon": horizon, "max_agent_steps": horizon}


def quick_settings(name: str, scenario: str = "intersection") -> dict[str, Any]:
    """Settings of algorithm ``name`` on the small quick scenario of ``scenario`` (learning test, learning curves)."""
    return {**quick_scenario(scenario), **get(name).quick}


def tiny_settings(name: str, scenario: str | None = None) -> dict[str, Any]:
    """Settings of algorithm ``name`` at the smallest scale on ``scenario`` (default: its first): the tiny scenario and its ``tiny``."""
    spec = get(name)
    scenario = scenario or spec.scenarios[0]
    return {**(TINY_ARENA if scenario == "arena" else TINY_SCENARIO), **spec.tiny}


def scenario_keys(scenario: str) -> set[str]:
    """The ``--set`` keys of a scenario's config."""
    if scenario == "arena":
        return {f.name for f in fields(ArenaConfig)}
    return {f.name for f in fields(ScenarioConfig)} - {"scenario"} | {"preset"}


def split_overrides(name: str, overrides: dict[str, Any], scenario: str = "intersection") -> tuple[dict[str, Any], dict[str, Any]]:
    """Route ``--set`` keys to (scenario config, algorithm config); unknown keys and bad algorithm values are refused."""
    env_keys = scenario_keys(scenario)
    algo_keys = set(keys(name))
    env_cfg = {k: v for k, v in overrides.items() if k in env_keys}
    algo_cfg = {k: v for k, v in overrides.items() if k in algo_keys}
    unknown = sorted(set(overrides) - set(env_cfg) - set(algo_cfg))
    if unknown:
        raise ValueError(
            f"unknown --set key(s) {unknown}; scenario keys: {', '.join(sorted(env_keys))}; {name} keys: {', '.join(sorted(algo_keys))}"
        )
    errors = get(name).value_errors(algo_cfg)  # type, finiteness and range of every value (its declaration's rule)
    if errors:
        raise ValueError(errors[0])
    return env_cfg, algo_cfg


def resolve_run(
    name: str, scenario: str, overrides: dict[str, Any], seed: int = 0
) -> tuple[AnyScenarioConfig, dict[str, Any], RunSettings]:
    """A training run's scenario config, algorithm settings and sampling / learner settings from its ``--set`` values,
    every value checked (Ray-free: ``train`` refuses bad input with it before importing the training machinery).

    A ValueError names the first bad one: the algorithm, the seed, a scenario it does not train on, a key or a value.
    """
    spec = get(name)
    check_training_seed(seed)
    if scenario not in spec.scenarios:
        raise ValueError(f"{name} does not train on scenario {scenario!r}; allowed: {', '.join(spec.scenarios)}")
    env_cfg, algo_cfg = split_overrides(name, overrides, scenario)
    run = split_run_settings(algo_cfg)
    return config_from_dict(scenario, {**spec.scenario_defaults(algo_cfg), **env_cfg}), algo_cfg, run


@dataclass(frozen=True)
class Setting:
    """One merged setting of a run: its key, value, the layer that set it last and (algorithm keys) its meaning."""

    key: str
    value: Any
    origin: str
    meaning: str = ""
    scenario_key: bool = False


def merged_settings(name: str, scenario: str, layers: list[tuple[str, dict[str, Any]]]) -> list[Setting]:
    """Every setting of algorithm ``name`` on ``scenario`` after ``layers`` (named override dicts, lowest first), each with
    its origin: the scenario's defaults, its preset, the algorithm's defaults, then the layer that set it last.

    The merged overrides are validated as ``train`` validates them (unknown keys and bad values refused).
    """
    spec = get(name)
    merged: dict[str, Any] = {}
    origin: dict[str, str] = {}
    for label, layer in layers:
        merged |= layer
        origin |= dict.fromkeys(layer, label)
    env_cfg, algo_cfg = split_overrides(name, merged, scenario)
    split_run_settings(dict(algo_cfg))  # a bad value of the sampling or learner keys is refused too
    env_origin = {k: origin[k] for k in env_cfg}
    below = spec.scenario_defaults(algo_cfg)  # the algorithm's scenario values beneath the user's (nav_ppo's stage mix)
    env_origin = dict.fromkeys(below, f"{name}'s scenario defaults") | env_origin
    env_cfg = below | env_cfg
    config = config_from_dict(scenario, env_cfg)  # refuses bad values as train does
    if scenario == "arena":
        base = {f.name: "ArenaConfig default" for f in fields(ArenaConfig)}
    else:
        preset = env_cfg.get("preset", "paper")
        base = {f.name: "ScenarioConfig default" for f in fields(ScenarioConfig) if f.name != "scenario"}
        base |= {"num_agents": f"{scenario}'s default", "preset": "default"} | dict.fromkeys(PRESETS[preset], f"preset {preset!r}")
    out = []
    if scenario != "arena":  # the arena has no presets
        out.append(Setting("preset", env_cfg.get("preset", "paper"), env_origin.get("preset", "default"), scenario_key=True))
    out += [Setting(k, getattr(config, k), env_origin.get(k, base[k]), scenario_key=True) for k in base if k != "preset"]
    for key, (default, meaning) in {**spec.hyperparameters, **COMMON_KEYS}.items():
        out.append(Setting(key, algo_cfg.get(key, default), origin.get(key, "default"), meaning))
    return out
