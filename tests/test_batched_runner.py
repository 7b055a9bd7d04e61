"""The batched env runner gives the transitions of RLlib's MultiAgentEnvRunner on the adapter (same seeds, same actions)."""

from __future__ import annotations

from collections import Counter

import numpy as np
import pytest
import torch
from ray.rllib.algorithms.algorithm_config import AlgorithmConfig
from ray.rllib.algorithms.ppo import PPOConfig
from ray.rllib.core.columns import Columns
from ray.rllib.core.rl_module.rl_module import RLModuleSpec
from ray.rllib.core.rl_module.torch.torch_rl_module import TorchRLModule
from ray.rllib.env.multi_agent_env_runner import MultiAgentEnvRunner

from coin_app.adapters.batched_runner import BatchedEnvRunner
from coin_app.adapters.rllib_env import env_config_of, register_envs
from coin_app.algorithms.common import AgentOutcomes, shared_policy_config
from coin_app.sim import schema
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.config import make_config
from coin_app.training import build_config

OUTCOME_KEYS = ("agents_finished", "agents_succeeded", "agents_collided", "agents_agent_steps")


class ScriptedDriver(TorchRLModule):
    """Deterministic actions from the observation alone: straight ahead, throttle from a hash of the observation."""

    def setup(self) -> None:
        """A dummy parameter (RLlib's runners move modules to a device)."""
        self.dummy = torch.nn.Parameter(torch.zeros(1))

    def _actions(self, batch: dict) -> dict:
        obs = batch[Columns.OBS].to(torch.float64)
        frac = torch.remainder(obs.sum(-1) * 37.0, 1.0)
        throttle = torch.where(frac < 0.9, 1.0, -0.3)  # mostly full throttle: arrivals, crashes, off-road exits; some wait
        steer = torch.zeros_like(throttle)
        return {Columns.ACTIONS: torch.stack([steer, throttle], -1).to(torch.float32)}

    def _forward_inference(self, batch: dict, **kwargs) -> dict:
        return self._actions(batch)

    def _forward_exploration(self, batch: dict, **kwargs) -> dict:
        return self._actions(batch)

    def _forward_train(self, batch: dict, **kwargs) -> dict:
        return {}


def _config(scenario, seed: int, num_envs: int, fragment: int, lcf=None) -> AlgorithmConfig:
    register_envs()
    name = "arena" if scenario.__class__.__name__ == "ArenaConfig" else scenario.scenario
    cfg = (
        PPOConfig()
        .environment(f"coin-{name}-v0", env_config=env_config_of(scenario, lcf=lcf), disable_env_checking=True)
        .env_runners(num_env_runners=0, num_envs_per_env_runner=num_envs, rollout_fragment_length=fragment)
        .rl_module(rl_module_spec=RLModuleSpec(module_class=ScriptedDriver))
        .callbacks(AgentOutcomes)
        .debugging(seed=seed)
    )
    return shared_policy_config(cfg)


def _key(x) -> bytes:
    return np.asarray(x, np.float32).tobytes()


def _info_key(info: dict) -> tuple:
    return tuple(sorted((k, _key(v) if isinstance(v, np.ndarray) else v) for k, v in info.items()))


def _rows(episodes) -> Counter:
    """Every agent step of every chunk as a hashable row (order-free: a multiset)."""
    rows = Counter()
    for ma in episodes:
        for aid, sa in ma.agent_episodes.items():
            n = len(sa)
            obs, infos = sa.get_observations(), sa.get_infos()
            acts, rews = sa.get_actions(), sa.get_rewards()
            for i in range(n):
                last = i == n - 1
                rows[
                    (
                        aid,
                        infos[i][schema.ENV_STEP],
                        _key(obs[i]),
                        _key(acts[i]),
                        _key(rews[i]),
                        _key(obs[i + 1]),
                        _info_key(infos[i]),
                        _info_key(infos[i + 1]),
                        last and bool(sa.is_terminated),
                        last and bool(sa.is_truncated),
                        last and bool(ma.is_terminated),
                        last and bool(ma.is_truncated),
                    )
                ] += 1
    return rows


def _sample(runner, chunks: int) -> tuple[list, dict]:
    episodes = []
    for _ in range(chunks):
        episodes += runner.sample()
    metrics = runner.get_metrics()
    return episodes, {k: float(metrics[k].peek()) for k in OUTCOME_KEYS + ("num_env_steps_sampled_lifetime",)}


def _outcomes(episodes) -> Counter:
    """How the vehicles' lives ended, from their last infos."""
    out = Counter()
    for ma in episodes:
        for sa in ma.agent_episodes.values():
            if sa.is_done:
                info = sa.get_infos(-1)
                flags = [k for k in (schema.ARRIVE_DEST, schema.CRASH_VEHICLE, schema.OUT_OF_ROAD, schema.MAX_STEP) if info.get(k)]
                out.update(flags)
                out["force_stop"] += schema.ARRIVE_DEST in info and not flags  # truncated by the env's force stop
                out.update(k for k in (schema.SUCCESS,) if info.get(k))
                out["done"] += 1
    return out


CASES = {  # (scenario overrides, chunks of 50 steps, LCF, how vehicles must end in it)
    "outcomes": (
        {"num_agents": 8, "horizon": 100, "force_stop_factor": 2, "max_agent_steps": 120, "delay_done": 5},
        8,
        None,
        (schema.ARRIVE_DEST, schema.CRASH_VEHICLE, schema.OUT_OF_ROAD, schema.MAX_STEP),
    ),
    "force_stop_copo_lcf": (
        {"num_agents": 8, "horizon": 30, "force_stop_factor": 1, "max_agent_steps": 100, "delay_done": 5},
        3,
        {"mean": 0.3, "std": 0.4},
        ("force_stop",),
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_driving_transitions_equal_rllib_runner(case):
    """Intersection with respawns, arrivals, crashes, off-road exits, own time-outs, force stops, LCFs: same rows, same outcomes."""
    overrides, chunks, lcf, needed = CASES[case]
    scenario = make_config("intersection", "paper", **overrides)
    ref = MultiAgentEnvRunner(config=_config(scenario, 3, 1, 50, lcf), worker_index=0)
    new = BatchedEnvRunner(config=_config(scenario, 3, 1, 50, lcf), worker_index=0)
    ref_eps, ref_metrics = _sample(ref, chunks)
    new_eps, new_metrics = _sample(new, chunks)
    outcomes = _outcomes(ref_eps)
    for kind in needed:
        assert outcomes[kind] > 0, f"the scripted run never ends a vehicle by {kind}: {outcomes}"
    assert sum(ma.is_done for ma in ref_eps) >= 2  # env resets inside the run
    assert _rows(new_eps) == _rows(ref_eps)
    assert _outcomes(new_eps) == outcomes
    assert new_metrics["num_env_steps_sampled_lifetime"] == ref_metrics["num_env_steps_sampled_lifetime"] == 50 * chunks
    for key in OUTCOME_KEYS:
        assert new_metrics[key] == ref_metrics[key], key
    if lcf is not None:  # the LCF feature is the last observation entry and in every info
        sa = new_eps[0].agent_episodes["agent0"]
        assert sa.get_observations(0).shape == (scenario.obs_dim + 1,)
        assert sa.get_observations(0)[-1] == pytest.approx((sa.get_infos(0)["lcf"] + 1) / 2)


def test_driving_batch_of_envs_equals_single_env_runners():
    """Env e of a 3-env batched runner seeded s reproduces RLlib's one-env runner seeded s + e; chunks continue ids and t."""
    scenario = make_config("bottleneck", "paper", num_agents=6, horizon=50, force_stop_factor=2, max_agent_steps=40, delay_done=3)
    new = BatchedEnvRunner(config=_config(scenario, 10, 3, 40), worker_index=0)
    new_eps, new_metrics = _sample(new, 4)
    ref_rows = Counter()
    ref_finished = 0.0
    for e in range(3):
        ref_eps, ref_metrics = _sample(MultiAgentEnvRunner(config=_config(scenario, 10 + e, 1, 40), worker_index=0), 4)
        ref_rows += _rows(ref_eps)
        ref_finished += ref_metrics["agents_finished"]
    assert _rows(new_eps) == ref_rows
    assert new_metrics["agents_finished"] == ref_finished > 0
    assert new_metrics["num_env_steps_sampled_lifetime"] == 3 * 4 * 40
    # chunk continuity (RLlib's concat_episode rules): a life cut at a chunk end continues with the same id and t
    lives: dict[str, list] = {}
    for ma in new_eps:
        for sa in ma.agent_episodes.values():
            lives.setdefault(sa.id_, []).append(sa)
    continued = [chunks for chunks in lives.values() if len(chunks) > 1]
    assert continued
    for chunks in continued:
        for a, b in zip(chunks, chunks[1:]):
            assert not a.is_done and b.t_started == a.t_started + len(a)
            assert np.array_equal(a.get_observations(-1), b.get_observations(0))


def test_arena_transitions_equal_rllib_runner():
    """The arena (no respawn; time-outs end every vehicle; episodes reset): same rows, same outcomes."""
    scenario = make_arena_config(num_vehicles=3, num_obstacles=2, max_steps=35)
    ref_eps, ref_metrics = _sample(MultiAgentEnvRunner(config=_config(scenario, 5, 1, 30), worker_index=0), 4)
    new_eps, new_metrics = _sample(BatchedEnvRunner(config=_config(scenario, 5, 1, 30), worker_index=0), 4)
    assert sum(ma.is_done for ma in ref_eps) >= 2
    assert _rows(new_eps) == _rows(ref_eps)
    for key in OUTCOME_KEYS[:3]:
        assert new_metrics[key] == ref_metrics[key], key


def test_episode_metrics_and_weights_sync():
    """Finished env episodes are logged with their return and length; newer weights replace the runner's, older ones do not."""
    scenario = make_config("bottleneck", "paper", num_agents=4, horizon=20, force_stop_factor=1, max_agent_steps=20)
    runner = BatchedEnvRunner(config=_config(scenario, 0, 2, 25), worker_index=0)
    episodes = runner.sample()
    done = [ma for ma in episodes if ma.is_done]
    assert len(done) >= 2 and all(len(ma) == 20 for ma in done)  # the force stop at 20 steps ends each env's first episode
    metrics = runner.get_metrics()
    returns = [ma.get_return() for ma in done]
    assert metrics["episode_return_mean"].peek() == pytest.approx(np.mean(returns), rel=1e-5)
    assert metrics["episode_len_mean"].peek() == 20
    state = runner.get_state()
    module_state = state["rl_module"]
    bumped = {mid: {k: v + 1 for k, v in s.items()} for mid, s in module_state.items()}
    runner.set_state({"rl_module": bumped, "weights_seq_no": 3})
    assert runner.get_state()["weights_seq_no"] == 3
    runner.set_state({"rl_module": module_state, "weights_seq_no": 2})  # older: ignored
    now = runner.get_state()["rl_module"]
    for mid in bumped:
        for k in bumped[mid]:
            assert np.array_equal(now[mid][k], bumped[mid][k])


def test_metadrive_backend_is_refused():
    scenario = make_config("intersection", "paper", backend="metadrive")
    with pytest.raises(ValueError, match="env_runner='multi_agent'"):
        BatchedEnvRunner(config=_config(scenario, 0, 1, 10), worker_index=0)


def test_training_configs_pick_the_runner_and_the_envs_per_runner():
    """build_config: the batched runner by default on the native simulator, envs per runner from the train batch."""
    ippo = build_config("ippo", "intersection", {}, 0)
    assert ippo.env_runner_cls is BatchedEnvRunner and ippo.num_envs_per_env_runner == 8  # 1600 / 200: one round
    assert build_config("ippo", "intersection", {"num_env_runners": 4}, 0).num_envs_per_env_runner == 2  # 4 x 2 x 200
    assert build_config("ippo", "intersection", {"num_envs_per_env_runner": 4}, 0).num_envs_per_env_runner == 4
    td3 = build_config("cig_td3", "intersection", {}, 0)
    assert td3.env_runner_cls is BatchedEnvRunner and td3.num_envs_per_env_runner == 1  # one env step per update credit
    reference = build_config("ippo", "intersection", {"env_runner": "multi_agent"}, 0)
    assert reference.env_runner_cls is None and reference.num_envs_per_env_runner == 1
    nav = build_config("nav_ppo", "arena", {}, 0)
    assert nav.env_runner_cls is BatchedEnvRunner and nav.num_envs_per_env_runner >= 1
    for bad, match in (({"env_runner": "fast"}, "'env_runner': 'fast'"), ({"num_envs_per_env_runner": 0}, "'num_envs_per_env_runner': 0")):
        with pytest.raises(ValueError, match=match):
            build_config("ippo", "intersection", bad, 0)
