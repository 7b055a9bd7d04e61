"""nav_ppo's optional warm start (not in the paper): behaviour cloning of the scripted arena driver before PPO.

The paper trains both stages from scratch over 30–40M env steps. On this machine's budgets (under
1M per stage) PPO from scratch never found the parking manoeuvre (docs/arena/README.md): it
settles inside d_c, misaligned. With ``warm_start="heuristic"`` (or ``"avoiding"``, ``"planning"``) the
stage first drives ``warm_start_episodes`` scenarios of its own mix with that scripted driver
(``coin_app.sim.arena.heuristic``: the plain one ignores obstacles and other vehicles, the
avoiding one swerves from the closest entity ahead, the planning one filters the plain one's
actions by short rollouts against every observed entity), half of them with
Gaussian action noise so that the clone also sees states off the driver's path, labelled with the
driver's action at each visited state (DART, Laskey et al. 2017). With ``warm_start_rounds`` R > 1
the clone then drives R - 1 more rounds of as many fresh scenarios itself (the same noise rule),
its states labelled by the driver and added to the demonstrations, and is fitted again after each
round (DAgger, Ross et al. 2011): the clone learns the driver's answer in the states its own
mistakes lead to. With ``warm_start_weight`` W the rows where the driver's label differs from the plain
driver's action (the avoiding driver's reflex, the planning driver's filter: the rows that decide
collisions, about a quarter of the planning driver's) count W times in the action loss. Then, before the first PPO
iteration, the policy's Gaussian mean is fitted to those labels, its log std to ``log_std_init``,
and the value network to the discounted returns (Eqs. 2–6, the stage's own reward) that followed
each state. PPO then starts from a policy that parks and has to learn what the driver ignores.
(With our reward constants PPO unlearned the clone within about 100k env steps: docs/arena/README.md.)

``bc_coeff`` keeps a driver as a teacher during PPO (the warm start's; the plain one without a
warm start): an auxiliary loss, the squared gap between the policy's Gaussian mean and the
driver's action at each minibatch's own observations (the learner's states labelled by the
driver, as in DAgger; Ross et al. 2011), weighted by ``bc_coeff`` falling linearly to 0 over
``bc_steps`` env steps (``bc_weight``), as in DAPG's decaying demonstration term (Rajeswaran et
al. 2018).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from ray.rllib.core.columns import Columns
from torch import nn

from coin_app.algorithms.checkpoints import actor_policy
from coin_app.sim.arena.config import ArenaConfig
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.heuristic import DRIVERS
from coin_app.sim.arena.simulator import ArenaSimulator


@dataclass(frozen=True)
class Demonstrations:
    """The scripted driver's labelled states: one row per vehicle and step it drove."""

    obs: np.ndarray  # (T, obs_dim)
    actions: np.ndarray  # (T, 2): the driver's (steering, pedal) at that state
    returns: np.ndarray  # (T,): discounted sum of the rewards that followed (the executed actions', to the episode's end)
    success_rate: float  # share of the demonstrated vehicles that reached the success state


INTERVENTION_TOLERANCE = 1e-6  # a label farther than this from the plain driver's action is an intervention
ROUND_SEED_STRIDE = 1_000_003  # DAgger round r draws its scenarios and noise from seed + r * this (rounds never share seeds)


def heuristic_demonstrations(
    config: ArenaConfig,
    episodes: int,
    seed: int,
    noise: float,
    gamma: float,
    driver: str = "heuristic",
    actor: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Demonstrations:
    """``episodes`` scenarios of ``config``'s mix labelled by the scripted ``driver``, every second one with action noise ``noise``.

    The driver also drives, unless ``actor`` (observations -> actions) is given: then the actor
    drives and the driver only labels the states it visits (a DAgger round).
    """
    if episodes < 1:
        raise ValueError(f"bad value for 'warm_start_episodes': {episodes}; allowed: an integer >= 1")
    drive = DRIVERS[driver]
    layouts = ArenaEnv(config)
    layouts.reset(seed=seed)  # seeds the scenario stream; the layouts below are drawn from it
    sim = ArenaSimulator(config)
    rng = np.random.default_rng(seed)
    obs_rows, act_rows, ret_rows = [], [], []
    successes = vehicles = 0
    for episode in range(episodes):
        obs = sim.reset(layouts.draw_layout())
        sigma = noise if episode % 2 else 0.0
        steps_obs, steps_act, steps_rew, steps_mask = [], [], [], []
        while sim.driving.any():
            label = np.zeros((len(obs), 2))  # parked vehicles' rows: ignored by the step, masked out below
            label[sim.driving] = drive(obs[sim.driving], dt=config.dt, friction=config.friction)
            acted = label if actor is None else np.where(sim.driving[:, None], actor(obs), 0.0)
            action = np.clip(acted + sigma * rng.standard_normal(label.shape), -1.0, 1.0) if sigma else acted
            mask = sim.driving.copy()
            step = sim.step(action)
            steps_obs.append(obs)
            steps_act.append(label)
            steps_rew.append(step.reward)
            steps_mask.append(mask)
            obs = step.obs
        rewards, mask = np.array(steps_rew), np.array(steps_mask)
        returns = np.zeros_like(rewards)
        following = np.zeros(rewards.shape[1])
        for t in range(len(rewards) - 1, -1, -1):  # a vehicle's rewards are 0 once it is done
            following = rewards[t] + gamma * following
            returns[t] = following
        obs_rows.append(np.array(steps_obs)[mask])
        act_rows.append(np.array(steps_act)[mask])
        ret_rows.append(returns[mask])
        successes += int(sim.succeeded.sum())
        vehicles += sim.num_vehicles
    return Demonstrations(
        np.concatenate(obs_rows).astype(np.float32),
        np.concatenate(act_rows).astype(np.float32),
        np.concatenate(ret_rows).astype(np.float32),
        successes / vehicles,
    )


def intervention_weights(demos: Demonstrations, weight: float, dt: float = 0.1, friction: float = 0.99) -> np.ndarray:
    """Per-row weights (T,): ``weight`` where the label differs from the plain driver's action at that state, else 1.

    Those are the rows where the avoiding driver's reflex or the planning driver's safety filter
    acted; they decide collisions, and the plain driver's own rows far outnumber them.
    """
    changed = np.abs(DRIVERS["heuristic"](demos.obs, dt=dt, friction=friction) - demos.actions).max(axis=1) > INTERVENTION_TOLERANCE
    return np.where(changed, weight, 1.0).astype(np.float32)


def clone(
    module: nn.Module,
    demos: Demonstrations,
    epochs: int,
    log_std: float,
    seed: int,
    lr: float = 1e-3,
    weights: np.ndarray | None = None,
) -> dict[str, float]:
    """Fit a PPO module to ``demos``: Gaussian mean to the actions, log std to ``log_std``, values to the returns; final MSEs.

    ``weights`` (T,) weigh each row's action error (the action MSE is then the weighted mean); None weighs all alike.
    """
    device = next(module.parameters()).device
    obs, actions, returns = (torch.as_tensor(x, device=device) for x in (demos.obs, demos.actions, demos.returns))
    row_weights = None if weights is None else torch.as_tensor(weights, device=device)
    optimizer = torch.optim.Adam(module.parameters(), lr)
    generator = torch.Generator().manual_seed(seed)
    minibatch = 512
    losses = {"action_mse": float("nan"), "log_std_mse": float("nan"), "value_mse": float("nan")}
    module.train()
    for _ in range(epochs):
        order = torch.randperm(len(obs), generator=generator).to(device)
        sums, count = np.zeros(3), 0
        for start in range(0, len(obs), minibatch):
            idx = order[start : start + minibatch]
            batch = {Columns.OBS: obs[idx]}
            inputs = module.forward_train(batch)[Columns.ACTION_DIST_INPUTS]
            mean, log_stds = inputs.chunk(2, dim=-1)
            gap = (mean - actions[idx]) ** 2
            terms = (
                gap.mean() if row_weights is None else (gap.mean(dim=1) * row_weights[idx]).sum() / row_weights[idx].sum(),
                ((log_stds - log_std) ** 2).mean(),
                ((module.compute_values(batch) - returns[idx]) ** 2).mean(),
            )
            optimizer.zero_grad()
            sum(terms).backward()
            optimizer.step()
            sums += [float(t.detach()) * len(idx) for t in terms]
            count += len(idx)
        losses = dict(zip(losses, (sums / count).tolist()))
    return losses


def joined(a: Demonstrations, b: Demonstrations) -> Demonstrations:
    """Both sets of rows; the success rate is ``b``'s (the newest round's)."""
    return Demonstrations(
        *(np.concatenate([x, y]) for x, y in ((a.obs, b.obs), (a.actions, b.actions), (a.returns, b.returns))), b.success_rate
    )


def warm_start(
    module: nn.Module,
    config: ArenaConfig,
    driver: str,
    episodes: int,
    noise: float,
    epochs: int,
    log_std: float,
    seed: int,
    gamma: float,
    rounds: int = 1,
    log: Callable[[str], None] | None = None,
    weight: float = 1.0,
) -> tuple[dict[str, float], list[Demonstrations]]:
    """Clone ``driver`` into ``module`` (round 0), then ``rounds - 1`` DAgger rounds; (final fit's MSEs, each round's new rows).

    ``weight`` weighs the rows where the driver's label differs from the plain driver's (``intervention_weights``).

    ``log`` receives one line per round (rows, success while collecting, the fit's action MSE).
    """
    if rounds < 1:
        raise ValueError(f"bad value for 'warm_start_rounds': {rounds}; allowed: an integer >= 1")
    if not weight > 0:
        raise ValueError(f"bad value for 'warm_start_weight': {weight}; allowed: a number > 0")
    new: list[Demonstrations] = []
    demos: Demonstrations | None = None
    weights: np.ndarray | None = None  # the rows' weights, each row's computed once, in the rows' order
    for r in range(rounds):
        round_seed = seed + r * ROUND_SEED_STRIDE
        actor = actor_policy(module) if r else None  # round 0: the driver drives; then the clone, as evaluation runs it
        new.append(heuristic_demonstrations(config, episodes, round_seed, noise, gamma, driver, actor))
        demos = new[-1] if demos is None else joined(demos, new[-1])
        if weight != 1.0:
            fresh = intervention_weights(new[-1], weight, config.dt, config.friction)
            weights = fresh if weights is None else np.concatenate([weights, fresh])
        losses = clone(module, demos, epochs, log_std, round_seed, weights=weights)
        if log is not None:
            who = "the clone" if r else driver
            log(
                f"warm start round {r + 1}/{rounds}: {len(new[-1].obs)} rows driven by {who} (success {new[-1].success_rate:.3f}), "
                f"fit on {len(demos.obs)} rows, action MSE {losses['action_mse']:.4f}"
            )
    return losses, new


def bc_weight(env_steps: int, coeff: float, steps: int) -> float:
    """The auxiliary loss's weight after ``env_steps``: ``coeff`` falling linearly to 0 over ``steps`` (constant when ``steps`` is 0)."""
    if steps <= 0:
        return coeff
    return coeff * max(0.0, 1.0 - env_steps / steps)


class TeacherLabels:
    """A scripted driver's actions at observations, each distinct observation row computed once until ``clear``.

    PPO revisits every row of a training batch once per epoch (10 by default), and the planning
    driver's rollouts cost far more than a minibatch's update, so the learner keeps the labels of
    one batch; a row's label does not depend on the other rows it is computed with, so the
    labels are those of computing every minibatch afresh.
    """

    def __init__(self, driver: str):
        self.driver = DRIVERS[driver]
        self.cache: dict[bytes, np.ndarray] = {}

    def __call__(self, obs: np.ndarray) -> np.ndarray:
        """Actions (N, 2) of the driver at observations (N, obs_dim)."""
        rows = np.ascontiguousarray(obs, dtype=np.float32)
        keys = [row.tobytes() for row in rows]
        missing = [i for i, key in enumerate(keys) if key not in self.cache]
        if missing:
            for i, action in zip(missing, self.driver(rows[missing])):
                self.cache[keys[i]] = action
        return np.stack([self.cache[key] for key in keys]) if keys else np.zeros((0, 2))

    def clear(self) -> None:
        """Forget every label (a new training batch)."""
        self.cache.clear()


def bc_loss(
    obs: torch.Tensor, dist_inputs: torch.Tensor, mask: torch.Tensor | None = None, driver: str | TeacherLabels = "heuristic"
) -> torch.Tensor:
    """Mean squared gap between the Gaussian means in ``dist_inputs`` (mean, log std) and the ``driver``'s actions at ``obs``."""
    labeller = DRIVERS[driver] if isinstance(driver, str) else driver
    labels = labeller(obs.detach().float().cpu().numpy())  # the arena's default physics (dt 0.1, friction 0.99)
    target = torch.as_tensor(labels, dtype=dist_inputs.dtype, device=dist_inputs.device)
    gap = ((dist_inputs[:, : dist_inputs.shape[1] // 2] - target) ** 2).mean(dim=1)
    return gap[mask].mean() if mask is not None else gap.mean()


def teacher(options: Mapping[str, Any]) -> str:
    """The scripted driver of the auxiliary loss: the warm start's, or the plain ``"heuristic"`` without a warm start."""
    name = options.get("warm_start", "none")
    return "heuristic" if name == "none" else name
