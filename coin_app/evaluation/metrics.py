"""Per-episode evaluation metrics of a multi-agent driving episode (Ray-free, backend-agnostic).

The recorder only reads the dict-of-agents step output (PettingZoo parallel / RLlib
``MultiAgentEnv`` style): ``infos`` maps an agent id to an info dict carrying the boolean
flags ``arrive_dest``, ``crash_vehicle``, ``out_of_road`` and ``max_step`` and, if
available, ``episode_length`` and ``episode_reward``; ``terminations`` / ``truncations``
map the ids that acted to their done flags (an ``"__all__"`` key is ignored). The native
:class:`~coin_app.sim.driving_env.DrivingEnv` and MetaDrive's multi-agent envs both
produce exactly this.

Counting rules (``docs/decisions.md`` §5.1; the same as COIN's
``coin_eval.py`` and CoPO's ``RecorderEnv``):

* Every distinct agent id seen in an episode is one vehicle; respawned vehicles have fresh
  ids and count separately. Vehicles still running when recording stops count in the
  denominator (they are neither successes nor failures).
* Outcome flags are counted **independently**, once per vehicle, if the flag was ever set
  in one of its infos (in practice only on its terminal step). A vehicle that is both
  crashed and out of road in the same step therefore counts in ``collision_rate`` *and* in
  ``out_of_road_rate`` and is subtracted twice in ``efficiency`` and ``safety`` — COIN's
  convention. The same holds for the (rare) arrival that coincides with a crash or an
  off-road in the same step: it counts as a success and as a failure.
* For bookkeeping each vehicle also gets one exclusive :attr:`VehicleRecord.outcome`, by
  MetaDrive's terminal-reward priority success > out_of_road > crash, then ``timeout``
  (done without any of the three flags: ``max_step`` or a forced stop) and ``running``
  (never done). The ``num_outcome_*`` counts partition the vehicles.

Metrics of one episode (:func:`episode_metrics`):

* ``success_rate`` = arrivals / vehicles; ``collision_rate`` = vehicles with
  ``crash_vehicle`` / vehicles; ``out_of_road_rate`` = vehicles with ``out_of_road`` /
  vehicles (all NaN when there are no vehicles);
* ``efficiency`` = arrivals − crashes − off-roads (COIN's convention, no /1000);
  ``safety`` = −(crashes + off-roads);
* ``avg_travel_steps`` = COIN's Table 5.1 "travel steps" (the official evaluation's
  definition, ``docs/decisions.md`` §5.1): the mean over the *finished* vehicles (done:
  arrived, crashed, off road or timed out) of their travel steps, a vehicle that did not arrive
  counting as ``horizon``, the vehicle's own step limit (``ScenarioConfig.max_agent_steps``,
  1000 in the paper; :func:`~coin_app.evaluation.evaluate.evaluate_policy` passes it to the
  recorder). NaN without finished vehicles, or when no ``horizon`` was given;
* ``avg_travel_steps_arrived`` = the mean travel steps of the arrived vehicles only (NaN if
  none): what coin_app reported as ``avg_travel_steps`` before, kept beside it;
* ``num_vehicles``, ``episode_return`` (mean per-vehicle return, NaN if no vehicles),
  ``env_steps`` (number of recorded env steps), and the raw counts ``num_arrived``,
  ``num_crashed``, ``num_out_of_road``, ``num_timeout``, ``num_running`` and the exclusive
  ``num_outcome_{arrived,out_of_road,crashed,timeout,running}``.

What the travel steps count: a vehicle's travel steps (:attr:`VehicleRecord.travel_steps`)
are the env's ``episode_length`` in its latest info (else the steps it was seen acting), i.e.
the env steps in which it acted, **the step in which it finished included** (a vehicle that
arrives in its 300th action has 300; MetaDrive's ``info["episode_length"]`` counts the same
way). A count of the steps before the finishing one is one lower per vehicle; COIN's official
arrived-only figure is such a count, so ``avg_travel_steps_arrived`` = that figure + 1. In
``avg_travel_steps`` only arrivals carry their own count (a non-arrival is ``horizon``
exactly), so it exceeds a finishing-step-excluded count by arrivals / finished vehicles (less
than one step). Vehicles still running when recording stops (never done; none once an episode
has ended) are left out of both travel-step means (they still count in the rates'
denominator). Over episodes, :func:`aggregate` averages the per-episode values, as for every
metric.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from coin_app.sim import schema

ALL_KEY = "__all__"
OUTCOMES = ("arrived", "out_of_road", "crashed", "timeout", "running")
# the six metrics of COIN's Table 5.1 (avg_travel_steps: the paper's definition, see the module doc)
METRIC_KEYS = ("success_rate", "collision_rate", "out_of_road_rate", "efficiency", "safety", "avg_travel_steps")


@dataclass
class VehicleRecord:
    """Everything the metrics need about one vehicle (one agent id) of an episode."""

    agent_id: str
    first_step: int  # env step at which the id was first seen (0 = at reset)
    last_step: int  # env step of its latest info
    steps: int = 0  # env steps in which it acted
    episode_length: int | None = None  # latest info[schema.EPISODE_LENGTH], if the env reports it
    episode_return: float = 0.0
    arrived: bool = False
    crashed: bool = False
    out_of_road: bool = False
    max_step: bool = False
    done: bool = False

    @property
    def travel_steps(self) -> int:
        """The vehicle's own step count: the env's ``episode_length`` if reported, else the steps seen acting."""
        return self.steps if self.episode_length is None else self.episode_length

    @property
    def outcome(self) -> str:
        """Exclusive outcome: arrived > out_of_road > crashed > timeout > running."""
        if self.arrived:
            return "arrived"
        if self.out_of_road:
            return "out_of_road"
        if self.crashed:
            return "crashed"
        return "timeout" if self.done else "running"


class EpisodeRecorder:
    """Accumulates one episode's per-agent infos and done flags into per-vehicle records.

    ``horizon``: each vehicle's own step limit (``max_agent_steps``), at which a vehicle that did
    not arrive counts in ``avg_travel_steps``; without it that metric is NaN.
    """

    def __init__(self, horizon: int | None = None) -> None:
        self.horizon = horizon
        self.vehicles: dict[str, VehicleRecord] = {}
        self.env_steps = 0
        self._reward_from_info: set[str] = set()

    def reset(self, infos: Mapping[str, Mapping[str, Any]] | None = None) -> None:
        """Start a new episode; ``infos`` are the reset infos (the initial vehicles)."""
        self.vehicles = {}
        self.env_steps = 0
        self._reward_from_info = set()
        for aid, info in (infos or {}).items():
            if aid != ALL_KEY:
                self._update(aid, info, acted=False, done=False, reward=None)

    def step(
        self,
        infos: Mapping[str, Mapping[str, Any]],
        terminations: Mapping[str, bool] | None = None,
        truncations: Mapping[str, bool] | None = None,
        rewards: Mapping[str, float] | None = None,
    ) -> None:
        """Record one env step.

        Without ``terminations`` / ``truncations`` a vehicle is done when one of its
        ``arrive_dest``/``crash_vehicle``/``out_of_road``/``max_step`` flags is set, and
        every id in ``infos`` is taken to have acted.
        """
        self.env_steps += 1
        terms = terminations or {}
        truncs = truncations or {}
        have_dones = terminations is not None or truncations is not None
        ids = dict.fromkeys([*infos, *terms, *truncs])
        ids.pop(ALL_KEY, None)
        for aid in ids:
            info = infos.get(aid, {})
            if have_dones:
                acted = aid in terms or aid in truncs
                done = bool(terms.get(aid, False)) or bool(truncs.get(aid, False))
            else:
                acted = True
                done = any(bool(info.get(k, False)) for k in schema.DONE_FLAGS)
            reward = None if rewards is None or not acted else rewards.get(aid)
            self._update(aid, info, acted=acted, done=done, reward=reward)

    def _update(self, aid: str, info: Mapping[str, Any], acted: bool, done: bool, reward: float | None) -> None:
        rec = self.vehicles.get(aid)
        if rec is None:
            rec = self.vehicles[aid] = VehicleRecord(agent_id=aid, first_step=self.env_steps, last_step=self.env_steps)
        elif rec.done:
            return  # a finished vehicle's id is never reused; ignore stray late entries
        rec.last_step = self.env_steps
        rec.steps += int(acted)
        rec.arrived |= bool(info.get(schema.ARRIVE_DEST, False))
        rec.crashed |= bool(info.get(schema.CRASH_VEHICLE, False))
        rec.out_of_road |= bool(info.get(schema.OUT_OF_ROAD, False))
        rec.max_step |= bool(info.get(schema.MAX_STEP, False))
        rec.done |= done
        if schema.EPISODE_LENGTH in info:
            rec.episode_length = int(info[schema.EPISODE_LENGTH])
        if schema.EPISODE_REWARD in info:
            rec.episode_return = float(info[schema.EPISODE_REWARD])
            self._reward_from_info.add(aid)
        elif aid not in self._reward_from_info and acted:
            if reward is not None:
                rec.episode_return += float(reward)
            elif schema.STEP_REWARD in info:
                rec.episode_return += float(info[schema.STEP_REWARD])

    def outcome_counts(self) -> dict[str, int]:
        """Number of vehicles per exclusive outcome (the counts sum to the number of vehicles)."""
        counts = dict.fromkeys(OUTCOMES, 0)
        for rec in self.vehicles.values():
            counts[rec.outcome] += 1
        return counts

    def metrics(self) -> dict[str, float]:
        """The episode's metrics; see :func:`episode_metrics`."""
        return episode_metrics(self)


def episode_metrics(
    recorder: EpisodeRecorder | Iterable[VehicleRecord], env_steps: int | None = None, horizon: int | None = None
) -> dict[str, float]:
    """The six COIN metrics plus counts of one episode, from a recorder or its vehicle records (``horizon``: the recorder's)."""
    if isinstance(recorder, EpisodeRecorder):
        recs = list(recorder.vehicles.values())
        env_steps = recorder.env_steps if env_steps is None else env_steps
        horizon = recorder.horizon if horizon is None else horizon
    else:
        recs = list(recorder)
    n = len(recs)
    arrived = np.array([r.arrived for r in recs], bool)
    crashed = np.array([r.crashed for r in recs], bool)
    off_road = np.array([r.out_of_road for r in recs], bool)
    done = np.array([r.done for r in recs], bool)
    travel = np.array([r.travel_steps for r in recs], float)
    returns = np.array([r.episode_return for r in recs], float)
    n_arr, n_crash, n_oor = int(arrived.sum()), int(crashed.sum()), int(off_road.sum())
    flagged = arrived | crashed | off_road
    rate = (lambda k: k / n) if n else (lambda k: math.nan)
    n_done = int(done.sum())
    # the paper's travel steps: finished vehicles, each non-arrival at the horizon
    paper_travel = float(np.where(arrived, travel, horizon)[done].mean()) if n_done and horizon is not None else math.nan
    out: dict[str, float] = {
        "success_rate": rate(n_arr),
        "collision_rate": rate(n_crash),
        "out_of_road_rate": rate(n_oor),
        "efficiency": float(n_arr - n_crash - n_oor),
        "safety": float(-(n_crash + n_oor)),
        "avg_travel_steps": paper_travel,
        "avg_travel_steps_arrived": float(travel[arrived].mean()) if n_arr else math.nan,
        "num_vehicles": n,
        "episode_return": float(returns.mean()) if n else math.nan,
        "env_steps": int(env_steps) if env_steps is not None else max((r.last_step for r in recs), default=0),
        "num_arrived": n_arr,
        "num_crashed": n_crash,
        "num_out_of_road": n_oor,
        "num_timeout": int((done & ~flagged).sum()),
        "num_running": int((~done).sum()),
    }
    outcome = [r.outcome for r in recs]
    for name in OUTCOMES:
        out[f"num_outcome_{name}"] = outcome.count(name)
    return out


def metrics_from_infos(
    step_infos: Sequence[Mapping[str, Mapping[str, Any]]],
    terminations: Sequence[Mapping[str, bool]] | None = None,
    truncations: Sequence[Mapping[str, bool]] | None = None,
    reset_infos: Mapping[str, Mapping[str, Any]] | None = None,
    horizon: int | None = None,
) -> dict[str, float]:
    """Episode metrics from the list of per-step ``infos`` (one per ``env.step``; optional done dicts; ``horizon`` as the recorder's)."""
    for name, seq in (("terminations", terminations), ("truncations", truncations)):
        if seq is not None and len(seq) != len(step_infos):
            raise ValueError(f"{name} has {len(seq)} entries but step_infos has {len(step_infos)}; give one dict per env step")
    rec = EpisodeRecorder(horizon)
    rec.reset(reset_infos)
    for t, infos in enumerate(step_infos):
        term = terminations[t] if terminations is not None else None
        trunc = truncations[t] if truncations is not None else None
        rec.step(infos, term, trunc)
    return rec.metrics()


def aggregate(metrics: Sequence[Mapping[str, float]], ddof: int = 0) -> dict[str, dict[str, float]]:
    """Mean, std and count of every numeric metric over episodes: ``{key: {"mean", "std", "n"}}``.

    NaN values (e.g. ``avg_travel_steps_arrived`` of an episode without arrivals) are skipped;
    ``n`` is the number of non-NaN values. ``ddof=0`` is numpy's population std.
    """
    if not metrics:
        return {}
    keys = list(dict.fromkeys(k for m in metrics for k in m))
    out: dict[str, dict[str, float]] = {}
    for k in keys:
        vals = np.array(
            [m[k] for m in metrics if k in m and isinstance(m[k], (int, float, np.number)) and not isinstance(m[k], bool)], float
        )
        if len(vals) == 0:
            continue
        vals = vals[~np.isnan(vals)]
        cnt = len(vals)
        mean = float(vals.mean()) if cnt else math.nan
        std = float(vals.std(ddof=ddof)) if cnt > ddof else math.nan
        out[k] = {"mean": mean, "std": std, "n": cnt}
    return out
