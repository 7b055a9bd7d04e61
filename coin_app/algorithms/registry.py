"""Registry of trainable algorithms and the shared training loop behind ``python -m coin_app train``.

An entry builds an RLlib ``AlgorithmConfig`` for a scenario from ``--set key=value``
overrides; keys are routed to the scenario config (``ScenarioConfig`` fields) or to the
algorithm's hyper-parameters, and anything else is refused with the allowed keys listed.
"""

from __future__ import annotations

import json
import time
from collections.abc import Callable
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

from coin_app.sim.config import ScenarioConfig, config_from_dict
from coin_app.sim.seeds import MAX_TRAINING_SEED, VALIDATION_SEED_BASE


@dataclass(frozen=True)
class AlgorithmEntry:
    """A trainable algorithm: its name, what it is, and how to build its config."""

    name: str
    description: str
    build: Callable[[str, dict[str, Any], dict[str, Any], int], Any]  # (scenario, env_cfg, algo_cfg, seed) -> config
    keys: Callable[[], tuple[str, ...]]  # the algorithm's --set keys
    quick: dict[str, Any] = field(default_factory=dict)  # hyper-parameters of the small QUICK scenario
    scenarios: tuple[str, ...] = ("intersection", "roundabout", "bottleneck")  # what it can train on


def _cig_td3_config(itd3: bool) -> Callable[[str, dict[str, Any], dict[str, Any], int], Any]:
    def build(scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> Any:
        from coin_app.algorithms.cig_td3.config import CigTd3Config

        cfg = CigTd3Config().environment(f"coin-{scenario}-v0", env_config=env_cfg).debugging(seed=seed)
        cfg = cfg.env_runners(num_env_runners=0, rollout_fragment_length=algo_cfg.pop("rollout_fragment_length", 1))
        cfg = cfg.evaluation(evaluation_interval=None)
        if itd3:
            cfg = cfg.itd3()
        return cfg.training(**algo_cfg)

    return build


def _cig_td3_keys() -> tuple[str, ...]:
    from coin_app.algorithms.cig_td3.config import HYPERPARAMETERS

    return (*HYPERPARAMETERS, "gamma", "train_batch_size_per_learner", "rollout_fragment_length")


def _ppo_build(variant: str) -> Callable[[str, dict[str, Any], dict[str, Any], int], Any]:
    def build(scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> Any:
        from coin_app.algorithms.ppo_family.config import build_ppo_config

        return build_ppo_config(variant, scenario, env_cfg, algo_cfg, seed)

    return build


def _ppo_keys(variant: str) -> Callable[[], tuple[str, ...]]:
    def keys() -> tuple[str, ...]:
        from coin_app.algorithms.ppo_family.config import ppo_hyperparameter_keys

        return ppo_hyperparameter_keys(variant)

    return keys


ALGORITHMS: dict[str, AlgorithmEntry] = {}

# A small bottleneck setting that learns within minutes on a laptop CPU (CI learning test,
# benchmarks/learning_curves.py): four agents, small networks, faster learning rates.
QUICK_SCENARIO: dict[str, Any] = {"num_agents": 4, "horizon": 300, "max_agent_steps": 300}
QUICK_TD3: dict[str, Any] = {
    "warmup_steps": 500,
    "train_batch_size_per_learner": 128,
    "hidden": 64,
    "latent_dim": 8,
    "node_width": 16,
    "policy_delay": 2,
    "actor_lr": 6e-4,
    "critic_lr": 1e-3,
    "central_critic_lr": 1e-3,
    "eval_every": 0,
}
QUICK_SETTINGS: dict[str, Any] = {**QUICK_SCENARIO, **QUICK_TD3}  # CIG-TD3 / ITD3 on the quick scenario


def register(entry: AlgorithmEntry) -> None:
    """Add an algorithm to the registry."""
    ALGORITHMS[entry.name] = entry


def get(name: str) -> AlgorithmEntry:
    """The registry entry of ``name``; unknown names raise a ValueError listing the choices."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algorithm {name!r}; allowed: {', '.join(sorted(ALGORITHMS))}")
    return ALGORITHMS[name]


register(
    AlgorithmEntry(
        "cig_td3", "COIN: CIG-TD3 with the interaction-aware centralized critic", _cig_td3_config(False), _cig_td3_keys, QUICK_TD3
    )
)
register(AlgorithmEntry("itd3", "ITD3: independent TD3 with parameter sharing", _cig_td3_config(True), _cig_td3_keys, QUICK_TD3))
register(
    AlgorithmEntry(
        "ippo", "IPPO: PPO with one shared policy, value on the own observation", _ppo_build("ippo"), _ppo_keys("ippo"), {"hidden": 64}
    )
)
register(
    AlgorithmEntry(
        "cppo", "CPPO: PPO, value on own + 4 nearest neighbours' (obs, action)", _ppo_build("cppo"), _ppo_keys("cppo"), {"hidden": 64}
    )
)
register(
    AlgorithmEntry(
        "mfpo", "MFPO: PPO, value on own obs + mean neighbour obs and action", _ppo_build("mfpo"), _ppo_keys("mfpo"), {"hidden": 64}
    )
)

register(
    AlgorithmEntry(
        "copo",
        "CoPO: PPO on LCF-coordinated ego/neighbour advantages, LCF meta-gradient",
        _ppo_build("copo"),
        _ppo_keys("copo"),
        {"hidden": 64},
    )
)


def _nav_ppo_build(scenario: str, env_cfg: dict[str, Any], algo_cfg: dict[str, Any], seed: int) -> Any:
    from coin_app.algorithms.nav_ppo.config import build_nav_ppo_config

    return build_nav_ppo_config(scenario, env_cfg, algo_cfg, seed)


def _nav_ppo_keys() -> tuple[str, ...]:
    from coin_app.algorithms.nav_ppo.config import nav_ppo_keys

    return nav_ppo_keys()


register(
    AlgorithmEntry(
        "nav_ppo",
        "seed-2 paper: PPO-Clip navigation (--set stage=long) and parking (stage=short) policies on the arena",
        _nav_ppo_build,
        _nav_ppo_keys,
        {"hidden": 64},
        scenarios=("arena",),
    )
)


def scenario_keys(scenario: str) -> set[str]:
    """The ``--set`` keys of a scenario's config."""
    if scenario == "arena":
        from coin_app.sim.arena.config import ArenaConfig

        return {f.name for f in fields(ArenaConfig)}
    return {f.name for f in fields(ScenarioConfig)} - {"scenario"} | {"preset"}


def split_overrides(name: str, overrides: dict[str, Any], scenario: str = "intersection") -> tuple[dict[str, Any], dict[str, Any]]:
    """Route ``--set`` keys to (scenario config, algorithm config); unknown keys are refused."""
    env_keys = scenario_keys(scenario)
    algo_keys = set(get(name).keys())
    env_cfg = {k: v for k, v in overrides.items() if k in env_keys}
    algo_cfg = {k: v for k, v in overrides.items() if k in algo_keys}
    unknown = sorted(set(overrides) - set(env_cfg) - set(algo_cfg))
    if unknown:
        raise ValueError(
            f"unknown --set key(s) {unknown}; scenario keys: {', '.join(sorted(env_keys))}; {name} keys: {', '.join(sorted(algo_keys))}"
        )
    return env_cfg, algo_cfg


def build_config(name: str, scenario: str, overrides: dict[str, Any], seed: int) -> Any:
    """A validated RLlib config of algorithm ``name`` on ``scenario``."""
    entry = get(name)
    if not 0 <= seed < MAX_TRAINING_SEED:
        raise ValueError(
            f"bad seed {seed}; allowed: an integer in [0, {MAX_TRAINING_SEED}) (validation seeds start at {VALIDATION_SEED_BASE})"
        )
    if scenario not in entry.scenarios:
        raise ValueError(f"{name} does not train on scenario {scenario!r}; allowed: {', '.join(entry.scenarios)}")
    env_cfg, algo_cfg = split_overrides(name, overrides, scenario)
    config_from_dict(scenario, env_cfg)  # refuses bad scenario values before any work
    from coin_app.adapters.rllib_env import register_envs
    from coin_app.algorithms.common import AgentOutcomes

    cfg = entry.build(scenario, env_cfg, dict(algo_cfg), seed).callbacks(AgentOutcomes)
    cfg.validate()

    register_envs()  # the coin-<scenario>-v0 names the config refers to
    return cfg


def fresh_module(name: str, scenario: str | None = None, overrides: dict[str, Any] | None = None, seed: int = 0) -> Any:
    """An untrained shared RLModule of algorithm ``name`` as its config builds it (no Ray session needed)."""
    from coin_app.adapters.rllib_env import make_env
    from coin_app.algorithms.common import SHARED_MODULE_ID

    scenario = scenario or get(name).scenarios[0]
    cfg = build_config(name, scenario, dict(overrides or {}), seed)
    env = make_env(scenario, cfg.env_config)
    agent = env.possible_agents[0]
    spaces = {SHARED_MODULE_ID: (env.observation_spaces[agent], env.action_spaces[agent])}
    env.close()
    return cfg.get_multi_rl_module_spec(spaces=spaces).build()[SHARED_MODULE_ID]


def evaluate_algorithm(algo: Any, seeds: list[int]) -> dict[str, float]:
    """Mean metrics of an algorithm's current deterministic actor on ``seeds`` (either backend)."""
    from coin_app.algorithms.checkpoints import actor_policy
    from coin_app.algorithms.common import SHARED_MODULE_ID, scenario_config_of
    from coin_app.evaluation.evaluate import evaluate_policy
    from coin_app.evaluation.metrics import aggregate

    policy = actor_policy(algo.learner_group._learner.module[SHARED_MODULE_ID].unwrapped())
    per_episode = evaluate_policy(policy, scenario_config_of(algo.config), seeds)
    return {k: v["mean"] for k, v in aggregate(per_episode).items()}


def iteration_metrics(result: dict[str, Any]) -> dict[str, float]:
    """The flat per-iteration figures coin_app logs and reports to Tune, from an RLlib ``algo.train()`` result.

    ``env_steps``, ``episode_return_mean``, ``episode_len_mean``, the agent outcomes of the
    iteration (``agents_finished``, ``train_success_rate``, ``train_collision_rate``; NaN when
    no agent ended), every scalar learner metric of the shared module (``learner/<name>``) and
    the last periodic evaluation on validation seeds (``eval/<metric>``), if any.
    """
    runners = result.get("env_runners", {})
    sampled = result.get("num_env_steps_sampled_lifetime", runners.get("num_env_steps_sampled_lifetime", 0))
    finished = float(runners.get("agents_finished", 0) or 0)
    out = {
        "env_steps": int(sampled),
        "episode_return_mean": float(runners.get("episode_return_mean", float("nan"))),
        "episode_len_mean": float(runners.get("episode_len_mean", float("nan"))),
        "agents_finished": finished,
        "train_success_rate": runners.get("agents_succeeded", 0) / finished if finished else float("nan"),
        "train_collision_rate": runners.get("agents_collided", 0) / finished if finished else float("nan"),
    }
    for key, value in result.get("learners", {}).get("shared", {}).items():
        if isinstance(value, (int, float)) and not isinstance(value, bool):
            out[f"learner/{key}"] = float(value)
    for key, value in result.get("coin_eval", {}).items():
        out[f"eval/{key}"] = float(value)
    return out


def outcome_text(metrics: dict[str, float]) -> str:
    """``"  agents 12  success 0.250  collision 0.083"`` from :func:`iteration_metrics` ('' if no agent ended)."""
    if not metrics["agents_finished"]:
        return ""
    n, success, collision = int(metrics["agents_finished"]), metrics["train_success_rate"], metrics["train_collision_rate"]
    return f"  agents {n}  success {success:.3f}  collision {collision:.3f}"


def quick_settings(name: str) -> dict[str, Any]:
    """Settings of algorithm ``name`` on the small quick scenario (learning test, learning curves)."""
    return {**QUICK_SCENARIO, **get(name).quick}


def checkpoint_meta(name: str, scenario: str, seed: int, overrides: dict[str, Any], **extra: Any) -> dict[str, Any]:
    """The coin_app metadata stored with every checkpoint (what evaluation and export read back)."""
    env_cfg, _ = split_overrides(name, overrides, scenario)
    return {"algo": name, "scenario": scenario, "seed": seed, "overrides": overrides, "env_config": env_cfg, **extra}


def save(algo: Any, checkpoint: Path, meta: dict[str, Any]) -> None:
    """Save the algorithm and its coin_app metadata to ``checkpoint``."""
    from coin_app.algorithms.checkpoints import write_metadata

    algo.save_to_path(str(checkpoint.resolve()))
    write_metadata(checkpoint, meta)


def train(
    name: str,
    scenario: str,
    steps: int,
    seed: int,
    overrides: dict[str, Any],
    out: Path,
    checkpoint_every: int = 10,
    resume: Path | None = None,
    log: Callable[[str], None] = print,
    max_minutes: float | None = None,
) -> dict[str, Any]:
    """Train for ``steps`` env steps or ``max_minutes`` of wall time; checkpoints every ``checkpoint_every`` iterations and at the end."""
    import ray

    from coin_app.adapters.rllib_env import register_envs

    if steps < 1:
        raise ValueError(f"bad steps {steps}; allowed: an integer >= 1")
    if max_minutes is not None and not max_minutes > 0:
        raise ValueError(f"bad max_minutes {max_minutes}; allowed: a number > 0 or None")
    if checkpoint_every < 1:
        raise ValueError(f"bad checkpoint_every {checkpoint_every}; allowed: an integer >= 1")
    cfg = build_config(name, scenario, overrides, seed)
    out.mkdir(parents=True, exist_ok=True)
    if not ray.is_initialized():
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    register_envs()
    algo = cfg.build_algo()
    if resume is not None:
        if not (resume / "rllib_checkpoint.json").exists():
            raise ValueError(f"--resume {resume} is not a checkpoint directory (no rllib_checkpoint.json)")
        algo.restore_from_path(str(resume.resolve()))
        log(f"resumed from {resume}")
    meta = checkpoint_meta(name, scenario, seed, overrides)
    (out / "config.json").write_text(json.dumps(meta, indent=2, default=str))
    t0 = time.perf_counter()
    start = sampled = int(algo.metrics.peek(("env_runners", "num_env_steps_sampled_lifetime"), default=0))
    result: dict[str, Any] = {}
    last_eval: dict[str, float] = {}
    ckpt = out / "checkpoint"
    while sampled < steps and (max_minutes is None or time.perf_counter() - t0 < 60.0 * max_minutes):
        result = algo.train()
        m = iteration_metrics(result)
        sampled = m["env_steps"]
        it = int(result["training_iteration"])
        elapsed = time.perf_counter() - t0
        critic = m.get("learner/local_critic_loss", m.get("learner/vf_loss", float("nan")))
        log(
            f"iter {it:>4}  env steps {sampled:>8}  {(sampled - start) / max(elapsed, 1e-9):7.1f} steps/s  "
            f"episode return {m['episode_return_mean']:8.2f}  critic loss {critic:8.4f}" + outcome_text(m)
        )
        if "coin_eval" in result:
            last_eval = result["coin_eval"]
            log(
                "      eval (validation seeds): "
                + "  ".join(f"{k} {last_eval.get(k, float('nan')):.3f}" for k in ("success_rate", "collision_rate", "out_of_road_rate"))
            )
        if it % checkpoint_every == 0:
            save(algo, ckpt, meta)
    save(algo, ckpt, meta)
    algo.stop()
    summary = {
        "checkpoint": str(ckpt),
        "env_steps": sampled,
        "iterations": int(result.get("training_iteration", 0)),
        "wall_s": round(time.perf_counter() - t0, 1),
        "eval": last_eval,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return summary
