"""A run's validated RLlib config: the seed checked, ``--set`` routed, the scenario config parsed once, the callbacks attached."""

from __future__ import annotations

import logging
from typing import Any

from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.callbacks.callbacks import RLlibCallback
from ray.rllib.core.rl_module.rl_module import RLModule

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.adapters.rllib_env import make_env, register_envs
from coin_app.algorithms import registry
from coin_app.algorithms.common import SHARED_MODULE_ID, AgentOutcomes
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.training.monitor import PeriodicEvaluation


def build_config(name: str, scenario: str, overrides: dict[str, Any], seed: int) -> AlgorithmConfig:
    """A validated RLlib config of algorithm ``name`` on ``scenario`` (the scenario config parsed once)."""
    spec = registry.get(name)
    scenario_config, algo_cfg, run = registry.resolve_run(name, scenario, overrides, seed)  # refuses bad values before any work
    callbacks: list[type[RLlibCallback]] = [AgentOutcomes]
    if spec.capabilities.periodic_evaluation:
        callbacks.append(PeriodicEvaluation)
    cfg = spec.build_config(scenario_config, algo_cfg, seed).callbacks(callbacks)
    cfg = with_env_runner(cfg, run.env_runner, run.num_envs_per_env_runner, spec.capabilities.on_policy, scenario_config)
    if run.num_learners or run.num_gpus_per_learner:
        cfg = cfg.learners(num_learners=run.num_learners, num_gpus_per_learner=run.num_gpus_per_learner)
    notice = logging.getLogger("ray.rllib.algorithms.algorithm_config")  # "You are running X on the new API stack!" (once)
    level = notice.level
    notice.setLevel(logging.ERROR)
    try:
        cfg.validate()
    finally:
        notice.setLevel(level)
    register_envs()  # the coin-<scenario>-v0 names the config refers to
    return cfg


def with_env_runner(
    cfg: AlgorithmConfig, runner: str, num_envs: int | str, on_policy: bool, scenario: ScenarioConfig | ArenaConfig
) -> AlgorithmConfig:
    """``cfg`` sampling with ``runner`` and ``num_envs`` envs per env runner (the ``env_runner`` keys of ``registry.RUNNER_KEYS``)."""
    backend = scenario.backend if isinstance(scenario, ScenarioConfig) else "native"
    if runner == "auto":
        runner = "batched" if backend == "native" else "multi_agent"
    if runner == "batched" and backend != "native":
        raise ValueError(f"env_runner='batched' steps the native simulator, not backend {backend!r}; allowed: env_runner='multi_agent'")
    if num_envs == "auto":
        num_envs = 1
        fragment = cfg.rollout_fragment_length
        if on_policy and runner == "batched":  # the whole train batch in one sampling round
            per_round = (fragment if isinstance(fragment, int) else 200) * max(1, cfg.num_env_runners)
            num_envs = max(1, cfg.total_train_batch_size // per_round)
    cfg = cfg.env_runners(num_envs_per_env_runner=num_envs)
    if runner == "batched":
        cfg = cfg.env_runners(env_runner_cls=BatchedEnvRunner)
    return cfg


def fresh_module(name: str, scenario: str | None = None, overrides: dict[str, Any] | None = None, seed: int = 0) -> RLModule:
    """An untrained shared RLModule of algorithm ``name`` as its config builds it (no Ray session needed)."""
    scenario = scenario or registry.get(name).scenarios[0]
    cfg = build_config(name, scenario, dict(overrides or {}), seed)
    env = make_env(scenario, cfg.env_config)
    agent = env.possible_agents[0]
    spaces = {SHARED_MODULE_ID: (env.observation_spaces[agent], env.action_spaces[agent])}
    env.close()
    return cfg.get_multi_rl_module_spec(spaces=spaces).build()[SHARED_MODULE_ID]
