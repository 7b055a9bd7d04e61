"""Ray-free evaluation of a policy on either backend: one deterministic episode per seed.

A policy is any callable mapping a batch of observations ``(N, obs_dim)`` to actions
``(N, 2)`` (see :mod:`coin_app.evaluation.policies` for checkpoints and exported files).
On the native backend all seeds run together in one batched simulator, so one policy call
per env step serves every agent of every episode. On MetaDrive each episode runs in a
fresh engine: MetaDrive's physics carries tiny state across resets of one engine, so
only a fresh engine makes an episode depend on its seed alone. MetaDrive allows one
engine per process; if this process already has one open (an env runner's), the
episodes run in a worker process instead. Both backends go through the one rollout loop,
:func:`coin_app.sim.rollout.rollout`.

The policy's matrix products run on one BLAS thread: OpenBLAS splits a product among its threads
differently for another thread count, which changes the actions in their last bits, and in closed loop
at 30 vehicles that is a different episode within 100 steps (docs/decisions.md §3.5). So an episode
depends on its seed, the policy and the envs batched with it, not on the thread count of the process
(``OPENBLAS_NUM_THREADS``, ``OMP_NUM_THREADS``, a Ray worker's one CPU, the machine's cores).

The seed sets (training, validation, test) are defined in :mod:`coin_app.sim.seeds`.
"""

from __future__ import annotations

import multiprocessing as mp
from collections.abc import Sequence
from typing import Any

import cloudpickle
from threadpoolctl import threadpool_limits

from coin_app.backends import metadrive as metadrive_env
from coin_app.evaluation.metrics import EpisodeRecorder
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.rollout import BatchedEnvs, DictEnvs, Policy, RolloutStep, rollout
from coin_app.sim.simulator import DrivingSimulator


def evaluate_policy(policy: Policy, config: ScenarioConfig, seeds: Sequence[int], max_steps: int | None = None) -> list[dict[str, float]]:
    """Per-episode metrics (one dict per seed, in order) of ``policy`` on ``config`` (native or MetaDrive backend)."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("evaluate_policy needs at least one seed")
    if config.backend == "metadrive":
        return _evaluate_metadrive(policy, config, seeds, max_steps)
    limit = max_steps if max_steps is not None else config.force_stop_factor * config.horizon
    recorders = [EpisodeRecorder(config.max_agent_steps) for _ in seeds]
    with threadpool_limits(limits=1, user_api="blas"):
        for step in rollout(BatchedEnvs(DrivingSimulator(config, num_envs=len(seeds))), policy, seeds, limit):
            record(step, recorders)
    return [rec.metrics() for rec in recorders]


def run_episode(env: Any, policy: Policy, seed: int, max_steps: int, trace: Any = None) -> dict[str, float]:
    """Metrics of one episode of ``policy`` on a dict-API driving env (native ``DrivingEnv`` or MetaDrive).

    ``trace``: an :class:`~coin_app.sim.rendering.EpisodeTrace` to record the native env's vehicles into. The travel
    steps' horizon is the env config's ``max_agent_steps``.
    """
    recorder = EpisodeRecorder(env.config.max_agent_steps)
    with threadpool_limits(limits=1, user_api="blas"):
        for step in rollout(DictEnvs([env]), policy, [seed], max_steps):
            record(step, [recorder])
            if trace is not None:
                trace.record(env, step.results[0].infos)
    return recorder.metrics()


def record(step: RolloutStep, recorders: Sequence[EpisodeRecorder]) -> None:
    """Feed a rollout step to the recorder of each env it reports (the reset starts the recorder's episode)."""
    for e, result in step.results.items():
        if step.t == 0:
            recorders[e].reset(result.infos)
        else:
            recorders[e].step(result.infos, result.terminateds, result.truncateds, result.rewards)


def _evaluate_metadrive(policy: Policy, config: ScenarioConfig, seeds: list[int], max_steps: int | None) -> list[dict[str, float]]:
    """MetaDrive episodes, each in a fresh engine; in a worker process if this one already runs MetaDrive."""
    if metadrive_env.open_in_this_process():
        return _in_worker_process(policy, config, seeds, max_steps)
    limit = max_steps if max_steps is not None else config.force_stop_factor * config.horizon + 1
    out = []
    for seed in seeds:
        with metadrive_env.MetaDriveDrivingEnv(config) as env:
            out.append(run_episode(env, policy, seed, limit))
    return out


def _worker(payload: bytes) -> list[dict[str, float]]:
    """``evaluate_policy`` on a cloudpickled (policy, config, seeds, max_steps)."""
    policy, config, seeds, max_steps = cloudpickle.loads(payload)
    return evaluate_policy(policy, config, seeds, max_steps)


def _in_worker_process(policy: Policy, config: ScenarioConfig, seeds: list[int], max_steps: int | None) -> list[dict[str, float]]:
    """``evaluate_policy`` in a fresh spawned process (the policy travels by cloudpickle)."""
    payload = cloudpickle.dumps((policy, config, seeds, max_steps))
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(_worker, (payload,))
