"""Batched policy evaluation: equals an episode-by-episode run through DrivingEnv, and is repeatable; evaluate's CLI."""

import json

import numpy as np
import pytest

from coin_app.cli import main
from coin_app.cli.evaluate import _evaluation_config
from coin_app.cli.policy_settings import with_preset
from coin_app.evaluation.evaluate import evaluate_policy, run_episode
from coin_app.evaluation.metrics import EpisodeRecorder
from coin_app.inference import export_policy
from coin_app.sim.config import DynamicsConfig, make_config
from coin_app.sim.driving_env import DrivingEnv
from coin_app.sim.seeds import TEST_SEED_BASE, VALIDATION_SEED_BASE, eval_test_seeds, validation_seeds


def policy(obs):
    # steer towards checkpoint 1's lateral offset, throttle from the speed feature
    steer = np.clip(4.0 * (obs[:, 10] - 0.5), -1, 1)
    throttle = np.where(obs[:, 3] < 0.35, 0.6, -0.1)
    return np.stack([steer, throttle], 1)


CFG = make_config("bottleneck", num_agents=6, horizon=80, max_agent_steps=80)


def one_by_one(seed):
    env = DrivingEnv(CFG)
    obs, infos = env.reset(seed=seed)
    rec = EpisodeRecorder(CFG.max_agent_steps)
    rec.reset(infos)
    while not env.episode_over:
        acts = {a: policy(obs[a][None])[0] for a in env.agents}
        new_obs, rewards, terms, truncs, infos = env.step(acts)
        obs = {**obs, **new_obs}
        rec.step(infos, terms, truncs, rewards)
    return rec.metrics()


def test_batched_evaluation_equals_sequential_runs():
    seeds = [3, 4, 5]
    batched = evaluate_policy(policy, CFG, seeds)
    for seed, m in zip(seeds, batched):
        ref = one_by_one(seed)
        assert m.keys() == ref.keys()
        for k in m:
            assert m[k] == pytest.approx(ref[k], nan_ok=True), k
        # the backend-agnostic episode loop (used for MetaDrive) gives the same episode
        generic = run_episode(DrivingEnv(CFG), policy, seed, 10_000)
        np.testing.assert_equal(generic, ref)
    assert any(m["num_vehicles"] > 6 for m in batched)  # respawns happened


def test_evaluation_is_repeatable_and_seed_sets_are_disjoint():
    a = evaluate_policy(policy, CFG, [7, 8])
    b = evaluate_policy(policy, CFG, [7, 8])
    assert a == b or all(np.allclose(list(x.values()), list(y.values()), equal_nan=True) for x, y in zip(a, b))
    assert not set(eval_test_seeds(20)) & set(validation_seeds(20))
    assert min(validation_seeds(1)) == VALIDATION_SEED_BASE and min(eval_test_seeds(1)) == TEST_SEED_BASE


def test_bad_policy_output_is_refused():
    with pytest.raises(ValueError, match="shape"):
        evaluate_policy(lambda o: np.zeros((len(o), 3)), CFG, [0], max_steps=3)


def test_evaluation_travel_steps_count_non_arrivals_at_the_vehicle_step_limit():
    """With a 5-step vehicle limit nobody arrives: every finished vehicle counts exactly 5 travel steps."""
    cfg = make_config("intersection", num_agents=3, horizon=5, max_agent_steps=5)
    for m in evaluate_policy(policy, cfg, [0, 1]):
        assert m["num_arrived"] == 0 and m["num_running"] == 0
        assert m["avg_travel_steps"] == 5.0
        assert np.isnan(m["avg_travel_steps_arrived"])


def _tiny_actor():
    import torch

    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(91, 4), torch.nn.Tanh(), torch.nn.Linear(4, 2), torch.nn.Tanh())


def _exported(tmp_path, env_config=None):
    meta = {"scenario": "intersection"} | ({"env_config": env_config} if env_config is not None else {})
    return export_policy(_tiny_actor(), tmp_path / "p.npz", "numpy", meta=meta)


def test_evaluate_preset_metadrive_compat_on_an_exported_policy(tmp_path, capsys):
    """--preset metadrive_compat: lidar 40 m and penalties 10 without --set; the printed table shows vehicles and time-outs."""
    policy_file = _exported(tmp_path)
    out = tmp_path / "eval.json"
    argv = ["evaluate", str(policy_file), "--seeds", "200000", "200001", "--set", "num_agents=2", "horizon=5", "max_agent_steps=5"]
    assert main([*argv, "--preset", "metadrive_compat", "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "settings (--preset metadrive_compat): lidar_range 40, crash_penalty 10, out_of_road_penalty 10, dynamics raycast" in text
    episodes = json.loads(out.read_text())["episodes"]
    rows = {line.split()[0]: line.split() for line in text.splitlines() if line.startswith("  ")}
    vehicles = sum(e["num_vehicles"] for e in episodes)
    timeouts = sum(e["num_timeout"] for e in episodes)
    assert vehicles >= 4 and rows["vehicles"][-3:] == [str(vehicles), "in", "all"]
    assert rows["time-outs"][-3:] == [str(timeouts), "in", "all"]
    # 5-step vehicle limit: no arrivals, every finished vehicle counts 5 travel steps
    assert "avg travel steps" in text and all(e["avg_travel_steps"] == 5.0 for e in episodes)
    # without --preset: the export's own config (the paper's 50 m)
    assert main(argv) == 0
    assert "settings (the policy's training config): lidar_range 50, crash_penalty 5" in capsys.readouterr().out


def test_evaluate_preset_replaces_the_stored_preset_keys_and_set_wins(tmp_path):
    stored = _exported(tmp_path, {"preset": "metadrive_compat", "crash_penalty": 7.0, "num_agents": 3})
    own = _evaluation_config(stored, None, {})
    assert (own.lidar_range, own.crash_penalty, own.out_of_road_penalty, own.num_agents) == (40.0, 7.0, 10.0, 3)
    paper = _evaluation_config(stored, None, {}, "paper")  # the stored preset and its keys give way; num_agents stays
    assert (paper.lidar_range, paper.crash_penalty, paper.out_of_road_penalty, paper.num_agents) == (50.0, 5.0, 5.0, 3)
    kin = _evaluation_config(stored, None, {"lidar_range": 30.0}, "kinematic")  # --set beats the preset
    assert (kin.lidar_range, kin.crash_penalty, kin.dynamics) == (30.0, 5.0, DynamicsConfig.kinematic())
    compat = _evaluation_config(_exported(tmp_path, {"lidar_range": 45.0}), None, {}, "metadrive_compat")
    assert compat.lidar_range == 40.0
    assert with_preset({"preset": "kinematic", "horizon": 300}, None) == {"preset": "kinematic", "horizon": 300}
    assert with_preset({"preset": "kinematic", "horizon": 300}, "paper") == {"horizon": 300, "preset": "paper"}


def test_evaluate_refuses_an_unknown_preset_in_one_line(tmp_path, capsys):
    assert main(["evaluate", str(_exported(tmp_path)), "--preset", "metadrive", "--set", "num_agents=2", "horizon=5"]) == 2
    captured = capsys.readouterr()
    assert captured.err == "error: unknown preset 'metadrive'; allowed: paper, metadrive_compat, kinematic\n"
    assert "evaluate:" not in captured.out  # refused before any work
