"""Episode metrics: a hand-scripted episode with known answers and a real native-env episode."""

from __future__ import annotations

import math

import numpy as np
import pytest

from coin_app.evaluation import EpisodeRecorder, VehicleRecord, aggregate, episode_metrics, metrics_from_infos
from coin_app.sim.driving_env import DrivingEnv

HORIZON = 10  # the scripted episode's vehicle step limit (each non-arrival's travel steps)


def _info(arrive=False, crash=False, oor=False, max_step=False, length=0, ret=0.0, step_reward=0.0):
    return {
        "arrive_dest": arrive,
        "crash_vehicle": crash,
        "out_of_road": oor,
        "max_step": max_step,
        "step_reward": step_reward,
        "episode_length": length,
        "episode_reward": ret,
    }


def _scripted_episode():
    """7 vehicles over 6 env steps.

    a0 arrives at step 3 (length 3), a1 arrives at step 5 (length 5), a2 crashes at step 2,
    a3 goes off road at step 4, a4 is still running at the end; a5 respawns at step 2 and is
    both crashed and off road at step 5 (length 3); a6 respawns at step 3 and times out
    (max_step) at step 6 (length 3).
    """
    reset = {f"a{i}": _info() for i in range(5)}
    ret = {"a0": 12.0, "a1": 14.0, "a2": -5.0, "a3": -4.0, "a4": 6.0, "a5": -5.0, "a6": 1.0}
    # (agent, step) -> terminal info; everything else is a plain running step
    final = {
        ("a2", 2): _info(crash=True, length=2, ret=ret["a2"]),
        ("a0", 3): _info(arrive=True, length=3, ret=ret["a0"]),
        ("a3", 4): _info(oor=True, length=4, ret=ret["a3"]),
        ("a1", 5): _info(arrive=True, length=5, ret=ret["a1"]),
        ("a5", 5): _info(crash=True, oor=True, length=3, ret=ret["a5"]),
        ("a6", 6): _info(max_step=True, length=3, ret=ret["a6"]),
    }
    alive = {"a0": 0, "a1": 0, "a2": 0, "a3": 0, "a4": 0}  # agent -> spawn step
    infos_l, terms_l, truncs_l = [], [], []
    for t in range(1, 7):
        infos, terms, truncs = {}, {}, {}
        for aid, born in list(alive.items()):
            done_info = final.get((aid, t))
            partial = 1.0 * (t - born)
            infos[aid] = done_info if done_info is not None else _info(length=t - born, ret=min(partial, ret[aid]))
            truncs[aid] = done_info is not None and done_info["max_step"]
            terms[aid] = done_info is not None and not truncs[aid]
            if done_info is not None:
                del alive[aid]
        spawn = {2: "a5", 3: "a6"}.get(t)
        if spawn:
            infos[spawn] = _info()
            alive[spawn] = t
        terms["__all__"] = False
        truncs["__all__"] = False
        infos_l.append(infos)
        terms_l.append(terms)
        truncs_l.append(truncs)
    return reset, infos_l, terms_l, truncs_l, ret


def _expected(ret):
    n = 7
    return {
        "success_rate": 2 / n,
        "collision_rate": 2 / n,  # a2 and a5 (crash + off road counts in both rates)
        "out_of_road_rate": 2 / n,  # a3 and a5
        "efficiency": 2 - 2 - 2,
        "safety": -(2 + 2),
        # finished: a0, a1 (arrived: 3, 5) and a2, a3, a5, a6 (at the horizon); a4 still runs: left out
        "avg_travel_steps": (3 + 5 + 4 * HORIZON) / 6,
        "avg_travel_steps_arrived": (3 + 5) / 2,
        "num_vehicles": n,
        "episode_return": sum(ret.values()) / n,
        "env_steps": 6,
        "num_arrived": 2,
        "num_crashed": 2,
        "num_out_of_road": 2,
        "num_timeout": 1,
        "num_running": 1,
        "num_outcome_arrived": 2,
        "num_outcome_out_of_road": 2,  # a3, a5 (off road beats crash)
        "num_outcome_crashed": 1,  # a2
        "num_outcome_timeout": 1,
        "num_outcome_running": 1,
    }


def _assert_metrics(got, want):
    assert set(want) <= set(got)
    for k, v in want.items():
        assert got[k] == pytest.approx(v), k


def test_scripted_episode_with_recorder():
    reset, infos_l, terms_l, truncs_l, ret = _scripted_episode()
    rec = EpisodeRecorder(horizon=HORIZON)
    rec.reset(reset)
    for infos, terms, truncs in zip(infos_l, terms_l, truncs_l):
        rec.step(infos, terms, truncs)
    m = rec.metrics()
    _assert_metrics(m, _expected(ret))
    assert set(rec.vehicles) == {f"a{i}" for i in range(7)}
    assert rec.vehicles["a5"].first_step == 2 and rec.vehicles["a6"].first_step == 3
    assert rec.vehicles["a5"].outcome == "out_of_road"
    assert rec.vehicles["a4"].outcome == "running" and not rec.vehicles["a4"].done
    assert sum(rec.outcome_counts().values()) == m["num_vehicles"]
    assert episode_metrics(rec) == m


def test_metrics_from_infos_with_and_without_done_dicts():
    reset, infos_l, terms_l, truncs_l, ret = _scripted_episode()
    want = _expected(ret)
    _assert_metrics(metrics_from_infos(infos_l, terms_l, truncs_l, reset_infos=reset, horizon=HORIZON), want)
    # the flags alone give the same answer (done = any outcome flag)
    _assert_metrics(metrics_from_infos(infos_l, horizon=HORIZON), want)
    with pytest.raises(ValueError, match="one dict per env step"):
        metrics_from_infos(infos_l, terms_l[:-1])


def test_return_from_rewards_when_infos_lack_episode_reward():
    rec = EpisodeRecorder()
    rec.reset({"x": {}})
    rec.step({"x": {"arrive_dest": False}}, {"x": False}, {"x": False}, rewards={"x": 1.5})
    rec.step({"x": {"arrive_dest": True}}, {"x": True}, {"x": False}, rewards={"x": 10.0})
    m = rec.metrics()
    assert m["episode_return"] == pytest.approx(11.5)
    assert m["avg_travel_steps_arrived"] == 2  # no episode_length in the infos: steps seen acting, the arriving one included
    assert math.isnan(m["avg_travel_steps"])  # the recorder was given no horizon
    assert m["success_rate"] == 1.0
    assert episode_metrics(rec, horizon=1000)["avg_travel_steps"] == 2  # the only finished vehicle arrived


def test_no_arrivals_and_empty_episode_give_nan():
    m = metrics_from_infos([{"a": _info(crash=True, length=1)}])
    assert math.isnan(m["avg_travel_steps"]) and math.isnan(m["avg_travel_steps_arrived"])
    crashed = metrics_from_infos([{"a": _info(crash=True, length=1)}], horizon=1000)
    assert crashed["avg_travel_steps"] == 1000  # the crash counts as the horizon
    assert m["collision_rate"] == 1.0 and m["efficiency"] == -1 and m["safety"] == -1
    empty = metrics_from_infos([])
    assert empty["num_vehicles"] == 0
    assert all(math.isnan(empty[k]) for k in ("success_rate", "collision_rate", "out_of_road_rate", "avg_travel_steps", "episode_return"))
    assert math.isnan(metrics_from_infos([], horizon=1000)["avg_travel_steps"])  # no finished vehicle
    assert empty["efficiency"] == 0 and empty["safety"] == 0


def test_travel_steps_paper_definition_from_hand_built_records():
    """COIN Table 5.1's travel steps: finished vehicles, a non-arrival counting as the horizon; running vehicles left out."""
    records = [
        VehicleRecord("arrived_300", 0, 300, steps=300, episode_length=300, arrived=True, done=True),
        VehicleRecord("arrived_500", 0, 500, steps=500, episode_length=500, arrived=True, done=True),
        VehicleRecord("crashed_100", 0, 100, steps=100, episode_length=100, crashed=True, done=True),
        VehicleRecord("timed_out", 0, 1000, steps=1000, episode_length=1000, max_step=True, done=True),
        VehicleRecord("running", 200, 600, steps=400, episode_length=400),
    ]
    m = episode_metrics(records, horizon=1000)
    assert m["avg_travel_steps"] == (300 + 500 + 1000 + 1000) / 4 == 700
    assert m["avg_travel_steps_arrived"] == (300 + 500) / 2 == 400
    assert (m["num_vehicles"], m["num_timeout"], m["num_running"]) == (5, 1, 1)
    assert math.isnan(episode_metrics(records)["avg_travel_steps"])  # no horizon given: undefined, not guessed
    # a force-stopped vehicle (done, no flag) before its limit and an off-road one also count as the horizon
    short = [
        VehicleRecord("arrived", 0, 40, steps=40, episode_length=40, arrived=True, done=True),
        VehicleRecord("forced", 0, 70, steps=70, episode_length=70, done=True),
        VehicleRecord("off_road", 0, 10, steps=10, episode_length=10, out_of_road=True, done=True),
    ]
    assert episode_metrics(short, horizon=80)["avg_travel_steps"] == (40 + 80 + 80) / 3
    assert episode_metrics(short, horizon=80)["avg_travel_steps_arrived"] == 40


def test_travel_steps_count_the_step_in_which_the_vehicle_finished():
    """A vehicle present at reset that acts in env steps 1, 2, 3 and arrives in step 3 has 3 travel steps (not 2)."""
    rec = EpisodeRecorder(horizon=1000)
    rec.reset({"x": {}, "y": {}})
    rec.step({"x": {}, "y": {}}, {"x": False, "y": False}, {"x": False, "y": False})
    rec.step({"x": {}, "y": {"crash_vehicle": True}}, {"x": False, "y": True}, {"x": False, "y": False})
    rec.step({"x": {"arrive_dest": True}}, {"x": True}, {"x": False})
    m = rec.metrics()
    assert m["avg_travel_steps_arrived"] == 3
    assert m["avg_travel_steps"] == (3 + 1000) / 2


def test_aggregate_mean_std_skips_nan():
    eps = [
        {"success_rate": 0.5, "avg_travel_steps": 100.0, "num_vehicles": 10},
        {"success_rate": 0.7, "avg_travel_steps": math.nan, "num_vehicles": 12},
        {"success_rate": 0.9, "avg_travel_steps": 120.0, "num_vehicles": 14},
    ]
    agg = aggregate(eps)
    assert agg["success_rate"]["mean"] == pytest.approx(0.7)
    assert agg["success_rate"]["std"] == pytest.approx(np.std([0.5, 0.7, 0.9]))
    assert agg["success_rate"]["n"] == 3
    assert agg["avg_travel_steps"] == {"mean": pytest.approx(110.0), "std": pytest.approx(10.0), "n": 2}
    assert aggregate(eps, ddof=1)["num_vehicles"]["std"] == pytest.approx(2.0)
    assert aggregate([]) == {}


def test_recorder_on_native_env_counts_each_vehicle_once():
    env = DrivingEnv(scenario="intersection", num_agents=6, horizon=60, max_agent_steps=60)
    obs, infos = env.reset(seed=3)
    rng = np.random.default_rng(0)
    rec = EpisodeRecorder(horizon=env.config.max_agent_steps)
    rec.reset(infos)
    all_infos = [infos]
    all_dones = [{}]
    steps = 0
    while not env.episode_over:
        actions = {a: rng.uniform([-0.3, 0.2], [0.3, 1.0]) for a in env.agents}
        obs, rewards, terms, truncs, infos = env.step(actions)
        rec.step(infos, terms, truncs, rewards)
        all_infos.append(infos)
        all_dones.append({a: terms[a] or truncs[a] for a in terms})
        steps += 1
        assert steps < 500, "episode did not end"
    m = rec.metrics()

    # independent recount from the raw per-step infos
    seen = [aid for infos in all_infos for aid in infos]
    distinct = set(seen)
    assert set(rec.vehicles) == distinct
    assert m["num_vehicles"] == len(distinct) > 6  # respawns happened
    assert distinct == {f"agent{i}" for i in range(len(distinct))}  # fresh, never reused ids
    last, done = {}, {}
    for infos, dones in zip(all_infos, all_dones):
        for aid, info in infos.items():
            last[aid] = info
            done[aid] = done.get(aid, False) or dones.get(aid, False)
    arrivals = sum(last[a]["arrive_dest"] for a in distinct)
    crashes = sum(last[a]["crash_vehicle"] for a in distinct)
    offroads = sum(last[a]["out_of_road"] for a in distinct)

    def outcome(a):  # exclusive: arrived > out of road > crashed > timeout > running
        if last[a]["arrive_dest"]:
            return "arrived"
        if last[a]["out_of_road"]:
            return "out_of_road"
        if last[a]["crash_vehicle"]:
            return "crashed"
        return "timeout" if done[a] else "running"

    outcomes = [outcome(a) for a in distinct]
    n_arr, n_oor, n_crash = outcomes.count("arrived"), outcomes.count("out_of_road"), outcomes.count("crashed")
    n_timeout, n_running = outcomes.count("timeout"), outcomes.count("running")
    assert n_arr + n_crash + n_oor + n_timeout + n_running == m["num_vehicles"]
    assert n_running == 0  # the episode is over: every vehicle finished
    assert n_crash + n_oor > 0  # the random policy fails somewhere, so the test sees outcomes
    for name, count in (("arrived", n_arr), ("out_of_road", n_oor), ("crashed", n_crash), ("timeout", n_timeout), ("running", n_running)):
        assert m[f"num_outcome_{name}"] == count, name
    assert (m["num_arrived"], m["num_crashed"], m["num_out_of_road"]) == (arrivals, crashes, offroads)
    assert (m["num_timeout"], m["num_running"]) == (n_timeout, n_running)
    assert m["env_steps"] == steps
    assert m["success_rate"] == pytest.approx(arrivals / len(distinct))
    assert m["collision_rate"] == pytest.approx(crashes / len(distinct))
    assert m["out_of_road_rate"] == pytest.approx(offroads / len(distinct))
    assert m["efficiency"] == arrivals - crashes - offroads
    assert m["safety"] == -(crashes + offroads)
    lengths = [last[a]["episode_length"] for a in distinct if last[a]["arrive_dest"]]
    assert (math.isnan(m["avg_travel_steps_arrived"]) and not lengths) or m["avg_travel_steps_arrived"] == pytest.approx(np.mean(lengths))
    paper = [last[a]["episode_length"] if last[a]["arrive_dest"] else 60 for a in distinct if done[a]]
    assert m["avg_travel_steps"] == pytest.approx(np.mean(paper))
    # episode_length counts the env steps a vehicle acted in, the one it finished in included:
    # every step info after its first appearance (a respawn first appears, without acting, in a step)
    appearances = {a: sum(a in infos for infos in all_infos[1:]) for a in distinct}
    for a in distinct:
        acted = appearances[a] - (0 if a in all_infos[0] else 1)
        assert last[a]["episode_length"] == acted == rec.vehicles[a].travel_steps, a
    assert m["episode_return"] == pytest.approx(np.mean([last[a]["episode_reward"] for a in distinct]))
