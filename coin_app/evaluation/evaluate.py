"""Ray-free evaluation of a policy on either backend: one deterministic episode per seed.

A policy is any callable mapping a batch of observations ``(N, obs_dim)`` to actions
``(N, 2)`` (see :mod:`coin_app.evaluation.policies` for checkpoints and exported files).
On the native backend all seeds run together in one batched simulator, so one policy call
per env step serves every agent of every episode. On MetaDrive each episode runs in a
fresh engine: MetaDrive's physics carries tiny state across resets of one engine, so
only a fresh engine makes an episode depend on its seed alone. MetaDrive allows one
engine per process; if this process already has one open (an env runner's), the
episodes run in a worker process instead.

The seed sets (training, validation, test) are defined in :mod:`coin_app.sim.seeds`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from coin_app.evaluation.metrics import EpisodeRecorder
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.driving_env import result_dicts
from coin_app.sim.simulator import ACTIVE, DrivingSimulator

Policy = Callable[[np.ndarray], np.ndarray]


def evaluate_policy(policy: Policy, config: ScenarioConfig, seeds: Sequence[int], max_steps: int | None = None) -> list[dict[str, float]]:
    """Per-episode metrics (one dict per seed, in order) of ``policy`` on ``config`` (native or MetaDrive backend)."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("evaluate_policy needs at least one seed")
    if config.backend == "metadrive":
        return _evaluate_metadrive(policy, config, seeds, max_steps)
    sim = DrivingSimulator(config, num_envs=len(seeds))
    res = sim.reset(seeds)
    returns = np.zeros(sim.num_slots)
    recorders = [EpisodeRecorder() for _ in seeds]
    for e, rec in enumerate(recorders):
        rec.reset(result_dicts(res, sim.env_slots(e), returns, e)[4])
    obs = res.obs.copy()
    finished = np.zeros(len(seeds), bool)
    limit = max_steps if max_steps is not None else config.force_stop_factor * config.horizon
    for _ in range(limit):
        active = np.nonzero(sim.status == ACTIVE)[0]
        actions = np.zeros((sim.num_slots, 2))
        if len(active):
            act = np.asarray(policy(obs[active]), dtype=float)
            if act.shape != (len(active), 2):
                raise ValueError(f"policy returned actions of shape {act.shape}; expected ({len(active)}, 2)")
            actions[active] = act
        res = sim.step(actions)
        fresh = res.acted | res.spawned
        obs[fresh] = res.obs[fresh]
        for e in np.nonzero(~finished)[0]:
            _, rewards, terms, truncs, infos = result_dicts(res, sim.env_slots(e), returns, e)
            recorders[e].step(infos, terms, truncs, rewards)
        finished |= res.episode_over
        if finished.all():
            break
    return [rec.metrics() for rec in recorders]


def run_episode(env: Any, policy: Policy, seed: int, max_steps: int, trace: Any = None) -> dict[str, float]:
    """Metrics of one episode of ``policy`` on a dict-API driving env (native ``DrivingEnv`` or MetaDrive).

    ``trace``: an :class:`~coin_app.sim.rendering.EpisodeTrace` to record the native env's vehicles into.
    """
    recorder = EpisodeRecorder()
    obs, infos = env.reset(seed)
    recorder.reset(infos)
    if trace is not None:
        trace.record(env, infos)
    for _ in range(max_steps):
        agents = list(env.agents)
        act = np.asarray(policy(np.stack([obs[a] for a in agents])), dtype=float) if agents else np.zeros((0, 2))
        if act.shape != (len(agents), 2):
            raise ValueError(f"policy returned actions of shape {act.shape}; expected ({len(agents)}, 2)")
        new_obs, rewards, terms, truncs, infos = env.step(dict(zip(agents, act)))
        obs.update(new_obs)
        recorder.step(infos, terms, truncs, rewards)
        if trace is not None:
            trace.record(env, infos)
        if env.episode_over:
            break
    return recorder.metrics()


def _evaluate_metadrive(policy: Policy, config: ScenarioConfig, seeds: list[int], max_steps: int | None) -> list[dict[str, float]]:
    """MetaDrive episodes, each in a fresh engine; in a worker process if this one already runs MetaDrive."""
    from coin_app.backends import metadrive as metadrive_env

    if metadrive_env.open_in_this_process():
        return _in_worker_process(policy, config, seeds, max_steps)
    limit = max_steps if max_steps is not None else config.force_stop_factor * config.horizon + 1
    out = []
    for seed in seeds:
        with metadrive_env.MetaDriveDrivingEnv(config) as env:
            out.append(run_episode(env, policy, seed, limit))
    return out


def _worker(payload: bytes) -> list[dict[str, float]]:
    import cloudpickle

    policy, config, seeds, max_steps = cloudpickle.loads(payload)
    return evaluate_policy(policy, config, seeds, max_steps)


def _in_worker_process(policy: Policy, config: ScenarioConfig, seeds: list[int], max_steps: int | None) -> list[dict[str, float]]:
    """``evaluate_policy`` in a fresh spawned process (the policy travels by cloudpickle)."""
    import multiprocessing as mp

    import cloudpickle

    payload = cloudpickle.dumps((policy, config, seeds, max_steps))
    with mp.get_context("spawn").Pool(1) as pool:
        return pool.apply(_worker, (payload,))
