"""Pairwise CVAE latents z_ij of a trained CIG-TD3 model along evaluation episodes (COIN App. B.1).

The model drives deterministically on the given seeds (one batched simulator). At every env
step each acting vehicle i is the ego and every other acting vehicle j of its episode a
partner; the centralized critic's CVAE encoder gives the posterior mean mu(z_ij | o_i, s_i,
a_i, s_j, a_j), exactly as the critic reads it during training. Up to ``pairs_per_step``
pairs per env and step are kept, drawn with a seeded generator, so long episodes do not
swamp the sample. Each latent comes with its scenario, env step and the ego-partner distance.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from coin_app.algorithms.checkpoints import load_module, scenario_of
from coin_app.algorithms.cig_td3.pairwise import PairCVAE, PairPacker
from coin_app.sim.rollout import BatchedEnvs, rollout
from coin_app.sim.simulator import DrivingSimulator


@dataclass
class LatentSample:
    """Latent means (n, L) and, per row, scenario, env step and ego-partner distance (m)."""

    z: np.ndarray
    scenario: np.ndarray
    env_step: np.ndarray
    distance: np.ndarray


def cvae_module(checkpoint: Path) -> object:
    """The checkpoint's RLModule if its centralized critic has a CVAE; a ValueError naming it otherwise."""
    module = load_module(Path(checkpoint))
    central = getattr(module, "central", None)
    if central is None or not isinstance(central.local, PairCVAE):
        raise ValueError(f"{checkpoint} has no CVAE local interaction module (only CIG-TD3 with local_module=cvae has latents)")
    return module


def collect_latents(checkpoint: Path, seeds: list[int], pairs_per_step: int = 8, sample_seed: int = 0) -> LatentSample:
    """CVAE latent means of ego-partner pairs along deterministic episodes of ``checkpoint`` on ``seeds``."""
    module = cvae_module(checkpoint)
    config = scenario_of(Path(checkpoint))
    if config.backend != "native":
        raise ValueError(f"latents are collected on the native backend; {checkpoint} was trained on {config.backend!r}")
    actor, central = module.actor.eval(), module.central.eval()
    rng = np.random.default_rng(sample_seed)
    envs = BatchedEnvs(DrivingSimulator(config, num_envs=len(seeds)))
    sim = envs.sim
    zs, steps, dists = [], [], []

    def act(obs: np.ndarray) -> np.ndarray:
        """The actor's actions for the acting vehicles; on the way, the latents of this step's sampled pairs."""
        with torch.no_grad():
            action = actor(torch.as_tensor(obs, dtype=torch.float32)).numpy()
        active = envs.acting  # the slots of the rows of obs
        egos, partners = _pick_pairs(active, sim.env_of[active], pairs_per_step, rng)
        if len(egos):
            row = np.zeros(sim.num_slots, dtype=np.int64)
            row[active] = np.arange(len(active))
            with torch.no_grad():
                mu = _pair_means(central, envs.obs[egos], envs.state[egos], action[row[egos]], envs.state[partners], action[row[partners]])
            zs.append(mu)
            steps.append(sim.env_step[sim.env_of[egos]])  # env steps taken before this one
            dists.append(np.linalg.norm(sim.pos[egos] - sim.pos[partners], axis=1))
        return action

    for _ in rollout(envs, act, seeds, config.force_stop_factor * config.horizon):
        pass
    z = np.concatenate(zs) if zs else np.zeros((0, central.cfg.latent_dim))
    return LatentSample(
        z,
        np.full(len(z), config.scenario),
        np.concatenate(steps) if steps else np.zeros(0, int),
        np.concatenate(dists) if dists else np.zeros(0),
    )


def _pick_pairs(active: np.ndarray, env: np.ndarray, per_env: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Up to ``per_env`` random ordered pairs (ego, partner) of distinct active slots in the same env."""
    egos, partners = [], []
    for e in np.unique(env):
        slots = active[env == e]
        n = len(slots)
        if n < 2:
            continue
        flat = rng.choice(n * (n - 1), size=min(per_env, n * (n - 1)), replace=False)
        i, r = np.divmod(flat, n - 1)
        j = r + (r >= i)  # skip the ego itself
        egos.append(slots[i])
        partners.append(slots[j])
    if not egos:
        return np.zeros(0, int), np.zeros(0, int)
    return np.concatenate(egos), np.concatenate(partners)


def _pair_means(
    central: object, obs: np.ndarray, state: np.ndarray, action: np.ndarray, p_state: np.ndarray, p_action: np.ndarray
) -> np.ndarray:
    """Posterior means (P, L) of the CVAE for P explicit (ego, partner) pairs."""

    def t(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.asarray(a, dtype=np.float32))

    packer = PairPacker(torch.ones(len(obs), 1, dtype=torch.bool))
    ego_x = torch.cat([t(obs), t(state), t(action)], -1)
    pair_x = torch.cat([t(p_state), t(p_action)], -1)
    with torch.no_grad():
        mu, _ = central.local.encode(ego_x, pair_x, packer)
    return mu.numpy()
