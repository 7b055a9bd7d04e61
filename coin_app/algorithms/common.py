"""RLlib glue every algorithm shares: the one shared module, the agent-outcome metrics, backend checks.

All agents of a scenario map to one RLModule ``SHARED_MODULE_ID`` (parameter sharing, as in
the COIN paper and the official code). ``AgentOutcomes`` moves the adapter's per-agent outcome
counts into the env runner metrics, so every algorithm logs success and collision rates.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.callbacks.callbacks import RLlibCallback

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.adapters.rllib_env import ADAPTER_KEYS, ENV_IDS, OUTCOMES, SCENARIO_CONFIG_KEY, CoinMultiAgentEnv
from coin_app.algorithms.checkpoint_files import SHARED_MODULE_ID
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.scenarios import config_from_dict

ProgressCallback = Callable[[str, int, int], None]


class ProgressReporting:
    """Mixin for an Algorithm whose iterations are long: reports (phase, done, total) inside an iteration.

    ``progress_callback`` is set by the driver that owns a local algorithm (``coin_app train``);
    it stays ``None`` in Tune trials, where reporting costs nothing.
    """

    progress_callback: ProgressCallback | None = None

    def report_progress(self, phase: str, done: int, total: int) -> None:
        """Tell the driver how far the current iteration's ``phase`` is (``total`` 0: unknown)."""
        if self.progress_callback is not None:
            self.progress_callback(phase, done, total)


def policy_mapping_fn(agent_id: str, episode: Any = None, **kwargs: Any) -> str:
    """Map every agent to the one shared module."""
    return SHARED_MODULE_ID


def scenario_config_of(config: AlgorithmConfig) -> ScenarioConfig | ArenaConfig:
    """The scenario config an RLlib algorithm config trains on (its registered env id and ``env_config``)."""
    if not isinstance(config.env, str) or config.env not in ENV_IDS:
        raise ValueError(f"coin_app algorithms need one of the registered envs {sorted(ENV_IDS)}, got env={config.env!r}")
    env_config = dict(config.env_config or {})
    if SCENARIO_CONFIG_KEY in env_config:  # parsed once where the run was set up (training.build_config)
        return env_config[SCENARIO_CONFIG_KEY]
    overrides = {k: v for k, v in sorted(env_config.items()) if k not in ADAPTER_KEYS}  # a config built by hand
    return _parsed(ENV_IDS[config.env], repr(overrides), overrides)


_PARSED: dict[tuple[str, str], ScenarioConfig | ArenaConfig] = {}


def _parsed(scenario: str, key: str, overrides: dict[str, Any]) -> ScenarioConfig | ArenaConfig:
    """``config_from_dict(scenario, overrides)``, parsed once per distinct overrides (``key`` is their repr)."""
    if (scenario, key) not in _PARSED:
        _PARSED[scenario, key] = config_from_dict(scenario, overrides)
    return _PARSED[scenario, key]


def coin_envs(env_runner: Any) -> list[CoinMultiAgentEnv]:
    """The ``CoinMultiAgentEnv`` instances an RLlib env runner steps (one per vectorized sub-env)."""
    env = getattr(env_runner, "env", None)
    subs = getattr(env, "envs", [env]) if env is not None else []
    return [e.unwrapped for e in subs if isinstance(e.unwrapped, CoinMultiAgentEnv)]


def set_on_envs(env_runner: Any, method: str, *args: Any) -> int:
    """Call ``method(*args)`` on every coin env of an env runner (the batched runner's vector env at once); returns how many envs."""
    if isinstance(env_runner, BatchedEnvRunner):
        if env_runner.vector_env is None:
            return 0
        getattr(env_runner, method)(*args)
        return env_runner.vector_env.num_envs
    envs = coin_envs(env_runner)
    for env in envs:
        getattr(env, method)(*args)
    return len(envs)


class AgentOutcomes(RLlibCallback):
    """Logs how many agents ended, succeeded and collided in each sample call (``agents_<outcome>``, summed per iteration)."""

    def on_sample_end(self, *, env_runner: Any = None, metrics_logger: Any = None, **kwargs: Any) -> None:
        """Move every sub-env's outcome counts into the env runner's metrics."""
        envs = coin_envs(env_runner)
        if metrics_logger is None or not envs:
            return
        for key in OUTCOMES:
            metrics_logger.log_value(f"agents_{key}", sum(e.outcomes[key] for e in envs), reduce="sum")
            for e in envs:
                e.outcomes[key] = 0


def backend_errors(config: AlgorithmConfig) -> list[str]:
    """Problems of ``config``'s env runner layout with its env backend (MetaDrive: one engine per process)."""
    scenario = scenario_config_of(config)
    backend = scenario.backend if isinstance(scenario, ScenarioConfig) else "native"
    if backend == "metadrive" and config.num_envs_per_env_runner > 1:
        return [
            f"num_envs_per_env_runner={config.num_envs_per_env_runner} with backend 'metadrive'; allowed: 1 "
            "(MetaDrive runs one engine per process: scale with num_env_runners instead)"
        ]
    return []


def shared_policy_config(config: AlgorithmConfig) -> AlgorithmConfig:
    """``config`` with all agents mapped to one shared module ``"shared"`` (parameter sharing)."""
    return config.multi_agent(policies={SHARED_MODULE_ID}, policy_mapping_fn=policy_mapping_fn)
