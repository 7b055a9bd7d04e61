"""What a TD3-family checkpoint's critics say where its deterministic policy stands still (the freeze diagnosis).

A TD3 actor follows the action gradient of its critics. Where its deterministic vehicles stop
short of a junction and time out, :func:`probe_stopped` asks whether the critics prefer that
(a value problem: the critics rate braking above driving on) or not (an optimisation problem:
the actor fails to follow them). It runs the actor deterministically on test seeds (native
backend) and, at every acting vehicle slower than ``speed_below`` m/s, evaluates

* the individual critic ``Q^l_1(o, a)`` and, for CIG-TD3, the global critic ``Q^G_1`` (COIN
  Eq. 12's two terms; the counterfactual baseline V has no ego action and cancels in every
  comparison below) at the policy's action ``a``,
* and the same at ``a`` with its throttle replaced by each value of ``throttles`` (steering kept).

The result holds per throttle value the mean of each critic over those vehicle-steps and the share
of them where that throttle scores above the policy's action: on ``Q^l``, on ``Q^G`` and on the
actor's objective ``Q^l + global_weight * Q^G``. Plain torch and numpy; ``probe_checkpoint``
loads the networks from a coin_app checkpoint.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import torch

from coin_app.algorithms.checkpoint_files import read_metadata
from coin_app.algorithms.checkpoints import load_module, scenario_of
from coin_app.algorithms.ppo_family.neighbours import neighbour_indices
from coin_app.sim.config import ScenarioConfig
from coin_app.sim.rollout import BatchedEnvs, rollout
from coin_app.sim.seeds import eval_test_seeds
from coin_app.sim.simulator import DrivingSimulator

THROTTLE = 1  # the action's throttle / brake entry (steering is 0)
PROBE_THROTTLES = (-1.0, 0.0, 0.5, 1.0)  # full brake, coast, half and full throttle


@dataclass
class Probe:
    """The probe's result: the per-throttle table and what it was taken over."""

    table: pd.DataFrame  # one row per throttle value, see the module doc
    stopped_steps: int  # vehicle-steps below the speed threshold
    vehicle_steps: int  # all acting vehicle-steps
    policy_action: np.ndarray  # the policy's mean action (steering, throttle) at the stopped vehicle-steps
    policy_q_local: float  # mean Q^l_1 of the policy's action there
    policy_q_global: float  # mean Q^G_1 of the policy's action there (NaN without a global critic)
    policy_preact_abs: np.ndarray  # mean |pre-tanh output| per action entry there (NaN for an actor without ``preactivation``)


def env_mates(positions: np.ndarray, env: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per row, the rows of every other vehicle of its env (nearest first) and their mask: ``(take (n, w), mask (n, w))``, w >= 1.

    Padded slots point at row 0 with a False mask.
    """
    idx = neighbour_indices(positions, env, np.inf)
    if idx.shape[1] == 0:  # every env holds one vehicle: one empty slot
        idx = np.full((len(env), 1), -1)
    return np.maximum(idx, 0), idx >= 0


def probe_stopped(
    actor: torch.nn.Module,
    local_q: torch.nn.Module,
    central: torch.nn.Module | None,
    config: ScenarioConfig,
    seeds: Sequence[int],
    global_weight: float = 1.0,
    speed_below: float = 0.5,
    throttles: Sequence[float] = PROBE_THROTTLES,
) -> Probe:
    """The critics at the stopped vehicles of deterministic episodes of ``actor`` on ``seeds`` (see the module doc)."""
    if speed_below <= 0:
        raise ValueError(f"bad speed_below {speed_below}; allowed: a speed > 0 (m/s)")
    if not throttles or any(not -1.0 <= t <= 1.0 for t in throttles):
        raise ValueError(f"bad throttles {list(throttles)}; allowed: one or more values in [-1, 1]")
    envs = BatchedEnvs(DrivingSimulator(config, num_envs=len(seeds)))
    sim = envs.sim
    parts: dict[str, list[np.ndarray]] = {"a": [], "pre": [], "ql": [], "qg": []}
    for t in throttles:
        parts[f"ql{t}"], parts[f"qg{t}"] = [], []
    seen = 0

    def act(obs: np.ndarray) -> np.ndarray:
        nonlocal seen
        o = torch.as_tensor(obs, dtype=torch.float32)
        with torch.no_grad():
            a = actor(o)
        seen += len(obs)
        rows = np.flatnonzero(sim.speed[envs.acting] < speed_below)
        if len(rows):
            _collect(rows, o, a)
        return a.numpy()

    def _collect(rows_np: np.ndarray, o: torch.Tensor, a: torch.Tensor) -> None:
        acting, rows = envs.acting, torch.as_tensor(rows_np)
        state = torch.as_tensor(envs.state[acting], dtype=torch.float32)
        take_np, mask_np = env_mates(sim.pos[acting], sim.env_of[acting])
        take, mask = torch.as_tensor(take_np[rows_np]), torch.as_tensor(mask_np[rows_np])
        others = (state[take] * mask[..., None], a[take] * mask[..., None], mask)
        variants = [a[rows]] + [_with_throttle(a[rows], t) for t in throttles]  # the policy's action, then each throttle
        k = len(variants)
        with torch.no_grad():
            parts["a"].append(a[rows].numpy())
            pre = actor.preactivation(o[rows]).abs().numpy() if hasattr(actor, "preactivation") else np.full((len(rows), 2), np.nan)
            parts["pre"].append(pre)
            ob, action = o[rows].repeat(k, 1), torch.cat(variants)  # one critic call for all variants
            ql = local_q.q1_only(ob, action).numpy().reshape(k, -1)
            if central is not None:
                rep = [x.repeat(k, *[1] * (x.dim() - 1)) for x in (state[rows], *others)]
                qg = central.q1(ob, rep[0], action, *rep[1:]).numpy().reshape(k, -1)
            else:
                qg = np.full((k, len(rows)), np.nan)
            # a variant equal to the policy's own action (e.g. its full brake) gets exactly its Q: in one batch the
            # rows would round differently by position, and a one-ulp difference would count as a preference
            for v in range(1, k):
                same = (variants[v] == variants[0]).all(1).numpy()
                ql[v, same], qg[v, same] = ql[0, same], qg[0, same]
            for key, q_l, q_g in zip(["", *map(str, throttles)], ql, qg, strict=True):
                parts[f"ql{key}"].append(q_l)
                parts[f"qg{key}"].append(q_g)

    for _ in rollout(envs, act, seeds, config.force_stop_factor * config.horizon):
        pass
    c = {k: np.concatenate(v) if v else np.zeros(0) for k, v in parts.items()}
    n = len(c["ql"])
    objective = c["ql"] + global_weight * np.nan_to_num(c["qg"])
    rows = []
    for t in throttles:
        ql, qg = c[f"ql{t}"], c[f"qg{t}"]
        rows.append(
            {
                "throttle": t,
                "q_local": float(ql.mean()) if n else float("nan"),
                "q_global": float(qg.mean()) if n else float("nan"),
                "local_prefers": _share_above(ql, c["ql"]),
                "global_prefers": _share_above(qg, c["qg"]) if central is not None else float("nan"),
                "objective_prefers": _share_above(ql + global_weight * np.nan_to_num(qg), objective),
            }
        )
    return Probe(
        pd.DataFrame(rows),
        n,
        seen,
        c["a"].reshape(-1, 2).mean(0) if n else np.full(2, np.nan),
        float(c["ql"].mean()) if n else float("nan"),
        float(c["qg"].mean()) if n else float("nan"),
        c["pre"].reshape(-1, 2).mean(0) if n else np.full(2, np.nan),
    )


def _share_above(x: np.ndarray, y: np.ndarray) -> float:
    """The share of entries where ``x > y`` (NaN when empty)."""
    return float(np.mean(x > y)) if len(x) else float("nan")


def _with_throttle(action: torch.Tensor, throttle: float) -> torch.Tensor:
    """``action`` with its throttle entry set to ``throttle``."""
    out = action.clone()
    out[:, THROTTLE] = throttle
    return out


def probe_checkpoint(checkpoint: Path, episodes: int = 10, speed_below: float = 0.5) -> Probe:
    """:func:`probe_stopped` on a TD3-family checkpoint (its actor and critics), on the first ``episodes`` test seeds."""
    if episodes < 1:
        raise ValueError(f"bad --episodes {episodes}; allowed: an integer >= 1")
    module: Any = load_module(Path(checkpoint))
    if getattr(module, "domain_q", None) is not None:  # TraCo: its actor also follows a domain critic the probe does not read
        raise ValueError(f"{checkpoint} is a TraCo checkpoint; the probe reads CIG-TD3 and ITD3 checkpoints")
    if getattr(module, "local_q", None) is None:
        raise ValueError(f"{checkpoint} has no individual critic (local_q); the probe reads CIG-TD3 and ITD3 checkpoints")
    config = scenario_of(Path(checkpoint))
    if not isinstance(config, ScenarioConfig) or config.backend != "native":
        raise ValueError(f"{checkpoint} was not trained on a native driving scenario; the probe runs the native simulator")
    overrides = read_metadata(Path(checkpoint)).get("overrides", {})
    central = getattr(module, "central", None)
    return probe_stopped(
        module.actor.eval(),
        module.local_q.eval(),
        None if central is None else central.eval(),
        config,
        eval_test_seeds(episodes),
        global_weight=float(overrides.get("global_weight", 1.0)),
        speed_below=speed_below,
    )
