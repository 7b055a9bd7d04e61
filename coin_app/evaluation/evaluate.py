"""Ray-free evaluation of a policy on the native simulator: one deterministic episode per seed.

A policy is any callable mapping a batch of observations ``(N, obs_dim)`` to actions
``(N, 2)``. All seeds run together in one batched simulator, so one policy call per env
step serves every agent of every episode.

Seed sets are disjoint: training runs seed their envs below ``VALIDATION_SEED_BASE``;
validation seeds (checkpoint selection, periodic evaluation) are ``VALIDATION_SEED_BASE + k``
and test seeds (reported results) ``TEST_SEED_BASE + k``. Never select on test seeds.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from coin_app.envs.config import ScenarioConfig
from coin_app.envs.driving_env import result_dicts
from coin_app.envs.simulator import ACTIVE, DrivingSimulator
from coin_app.evaluation.metrics import EpisodeRecorder

VALIDATION_SEED_BASE = 100_000
TEST_SEED_BASE = 200_000

Policy = Callable[[np.ndarray], np.ndarray]


def eval_test_seeds(n: int) -> list[int]:
    """The first ``n`` test seeds (the paper uses 20 per trained model)."""
    return [TEST_SEED_BASE + k for k in range(n)]


def validation_seeds(n: int) -> list[int]:
    """The first ``n`` validation seeds (periodic evaluation during training)."""
    return [VALIDATION_SEED_BASE + k for k in range(n)]


def evaluate_policy(policy: Policy, config: ScenarioConfig, seeds: Sequence[int], max_steps: int | None = None) -> list[dict[str, float]]:
    """Per-episode metrics (one dict per seed, in order) of ``policy`` on ``config``."""
    seeds = [int(s) for s in seeds]
    if not seeds:
        raise ValueError("evaluate_policy needs at least one seed")
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
