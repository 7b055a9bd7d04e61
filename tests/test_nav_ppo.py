"""nav_ppo: the switching policy, pair files, the arena evaluation suite, and both training stages end to end."""

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from torch import nn

from coin_app.cli import main
from coin_app.evaluation.arena_suite import PAPER_TABLE_I, evaluate_suite, parse_cases, run_scenario, summarize
from coin_app.inference import export_numpy, load_policy
from coin_app.inference.switching import SwitchingPolicy, target_distance, write_pair
from coin_app.sim.arena.config import make_arena_config
from coin_app.sim.arena.env import ArenaEnv
from coin_app.sim.arena.generator import generate, heldout_rng
from coin_app.sim.arena.heuristic import heuristic_actions
from coin_app.training import build_config


def arena_obs(distances):
    """Arena observations whose target lies ``d`` metres straight ahead."""
    obs = np.zeros((len(distances), 13), np.float32)
    obs[:, 0] = np.asarray(distances) / 25.0
    obs[:, 3] = 1.0
    return obs


def test_switching_policy_switches_at_the_radius():
    long = lambda o: np.tile([[1.0, 0.5]], (len(o), 1))  # noqa: E731
    short = lambda o: np.tile([[-1.0, -0.5]], (len(o), 1))  # noqa: E731
    policy = SwitchingPolicy(long, short, 7.5)
    obs = arena_obs([7.49, 7.51, 0.0, 30.0])
    np.testing.assert_allclose(target_distance(obs), [7.49, 7.51, 0.0, 30.0], atol=1e-5)
    np.testing.assert_allclose(policy(obs), [[-1, -0.5], [1, 0.5], [-1, -0.5], [1, 0.5]])
    # off-axis targets: the Euclidean distance decides
    obs = arena_obs([0.0, 0.0])
    obs[:, 0:2] = [[6.0 / 25, 4.0 / 25], [6.0 / 25, 5.0 / 25]]  # 7.21 m and 7.81 m
    np.testing.assert_allclose(policy(obs)[:, 0], [-1.0, 1.0])
    with pytest.raises(ValueError, match="switch_radius"):
        SwitchingPolicy(long, short, 0.0)


def mlp(seed):
    torch.manual_seed(seed)
    return nn.Sequential(nn.Linear(13, 8), nn.Tanh(), nn.Linear(8, 2), nn.Hardtanh(-1.0, 1.0))


def test_pair_files_load_without_torch_or_ray(tmp_path):
    long, short = export_numpy(mlp(0), tmp_path / "long.npz"), export_numpy(mlp(1), tmp_path / "short.npz")
    pair = write_pair(tmp_path / "pair" / "nav.json", long, short, 6.0)
    assert json.loads(pair.read_text())["long"] == "../long.npz"  # relative: the folder can move
    obs = arena_obs(np.linspace(0, 12, 9)).copy()
    obs[:, 5:] = np.random.default_rng(0).normal(size=(9, 8))
    want = np.where((target_distance(obs) < 6.0)[:, None], load_policy(short)(obs), load_policy(long)(obs))
    np.testing.assert_allclose(load_policy(pair)(obs), want, atol=1e-7)
    np.save(tmp_path / "obs.npy", obs)
    code = (
        "import sys; sys.modules['torch'] = None; sys.modules['ray'] = None\n"
        "import numpy as np\nfrom coin_app.inference import load_policy\n"
        f"print(np.abs(load_policy({str(pair)!r})(np.load({str(tmp_path / 'obs.npy')!r}))).sum())"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert float(out.stdout) == pytest.approx(np.abs(want).sum(), rel=1e-6)
    with pytest.raises(ValueError, match="does not exist"):
        write_pair(tmp_path / "x.json", tmp_path / "none.npz", short, 6.0)
    (tmp_path / "bad.json").write_text('{"format": "other"}')
    with pytest.raises(ValueError, match="not a coin_app switching-policy file"):
        load_policy(tmp_path / "bad.json")


def test_suite_is_deterministic_and_its_summary_aggregates_by_hand():
    rows = evaluate_suite("heuristic", [(2, 1), (3, 0)], 3, max_steps=150, workers=1, log=lambda s: None)
    again = evaluate_suite("heuristic", [(2, 1), (3, 0)], 3, max_steps=150, workers=2, log=lambda s: None)
    strip = [{k: v for k, v in r.items() if k != "step_time_s"} for r in rows]
    assert strip == [{k: v for k, v in r.items() if k != "step_time_s"} for r in again]
    assert [(r["case"], r["scenario"]) for r in rows] == [("2x1", k) for k in range(3)] + [("3x0", k) for k in range(3)]
    summary = summarize(rows).set_index(["vehicles", "obstacles"])
    case = [r for r in rows if r["case"] == "2x1"]
    want_success = sum(r["success_to_goal_rate"] * r["vehicles"] for r in case) / sum(r["vehicles"] for r in case)
    want_rate = sum(r["collisions"] for r in case) / sum(r["distance"] for r in case)
    assert summary.loc[(2, 1), "success_to_goal_rate"] == pytest.approx(want_success)
    assert summary.loc[(2, 1), "collision_rate"] == pytest.approx(want_rate)
    assert summary.loc[(2, 1), "scenarios"] == 3 and np.isnan(summary.loc[(2, 1), "paper_success"])


def test_short_generator_scores_the_parking_stages_starts_on_the_held_out_seeds(tmp_path):
    rows = evaluate_suite("heuristic", [(1, 0)], 3, max_steps=150, workers=1, log=lambda s: None, generator="short")
    paper = evaluate_suite("heuristic", [(1, 0)], 3, max_steps=150, workers=1, log=lambda s: None)
    cfg = make_arena_config(generator="short", obstacle_side="left", max_steps=150)
    for k, row in enumerate(rows):
        layout = generate(heldout_rng(1, 0, k), cfg, 1, 0)
        assert 1.0 <= np.linalg.norm(layout.starts[0, :2] - layout.targets[0, :2]) <= 7.5  # starts near the target
        direct = run_scenario(heuristic_actions, ArenaEnv(cfg), layout)
        assert row["distance"] == pytest.approx(direct["distance"]) and row["policy_calls"] == direct["policy_calls"]
    assert [r["distance"] for r in rows] != [r["distance"] for r in paper]  # not the paper's suite
    with pytest.raises(ValueError, match="bad arena value generator='far'; allowed: agnn, short"):
        evaluate_suite("heuristic", [(1, 0)], 1, workers=1, generator="far")
    args = ["evaluate-arena", "heuristic", "--generator", "short", "--cases", "1x0", "--scenarios-per-case", "1", "--workers", "1"]
    assert main([*args, "--max-steps", "50", "--out", str(tmp_path)]) == 0
    assert "`short` generator, not the paper's suite" in (tmp_path / "arena_side_by_side.md").read_text()
    assert json.loads((tmp_path / "arena_eval.json").read_text())["generator"] == "short"


def test_case_specs_and_refusals():
    assert len(parse_cases("all")) == 24 and set(parse_cases("all")) == set(PAPER_TABLE_I)
    assert parse_cases("4x3,20X8") == [(4, 3), (20, 8)]
    for bad in ("4by3", "0x2", "3x-1"):
        with pytest.raises(ValueError, match="bad case"):
            parse_cases(bad)
    with pytest.raises(ValueError, match="does not exist"):
        evaluate_suite("no/such/policy.npz", [(1, 0)], 1, workers=1)
    with pytest.raises(ValueError, match="nav_ppo does not train on scenario 'intersection'"):
        build_config("nav_ppo", "intersection", {}, 0)
    with pytest.raises(ValueError, match="cig_td3 does not train on scenario 'arena'"):
        build_config("cig_td3", "arena", {}, 0)
    with pytest.raises(ValueError, match="bad value for 'stage'"):
        build_config("nav_ppo", "arena", {"stage": "medium"}, 0)
    with pytest.raises(ValueError, match="unknown --set key"):
        build_config("nav_ppo", "arena", {"num_agents": 3}, 0)


TINY = ["train_batch_size_per_learner=400", "minibatch_size=200", "num_epochs=2", "hidden=16", "max_steps=60"]


def test_both_stages_train_export_pair_and_evaluate(ray_session, tmp_path, capsys):
    cfg = build_config("nav_ppo", "arena", {"stage": "short"}, 0)
    arena = cfg.env_config["scenario_config"]  # the stage's scenario mix, parsed once
    assert arena.generator == "short" and arena.max_vehicles == 8 and not cfg.use_kl_loss
    assert cfg.model_config["fcnet_hiddens"] == [256, 256]
    exported = {}
    for stage, budget in (("long", ["--steps", "400"]), ("short", ["--steps", "1000000000", "--max-minutes", "0.0001"])):
        out = tmp_path / stage
        args = ["train", "--algo", "nav_ppo", "--scenario", "arena", *budget, "--out", str(out), "--set", f"stage={stage}", *TINY]
        assert main(args) == 0
        # one 400-step batch either way: the wall-time budget stops the short stage after its first iteration
        assert json.loads((out / "summary.json").read_text())["env_steps"] == 400
        exported[stage] = tmp_path / f"{stage}.npz"
        assert main(["export", str(out / "checkpoint"), "--out", str(exported[stage])]) == 0
    capsys.readouterr()
    assert main(["pair", str(exported["long"]), str(exported["short"]), "--switch-radius", "7.5", "--out", str(tmp_path / "nav.json")]) == 0
    pair = load_policy(tmp_path / "nav.json")
    assert pair.long.obs_dim == 13 and pair.short.obs_dim == 13
    out = tmp_path / "eval"
    assert (
        main(
            [
                "evaluate-arena",
                str(tmp_path / "nav.json"),
                "--cases",
                "2x1",
                "--scenarios-per-case",
                "2",
                "--workers",
                "1",
                "--max-steps",
                "60",
                "--out",
                str(out),
                "--plots",
                "1",
            ]
        )
        == 0
    )
    text = capsys.readouterr().out
    assert "| 2 | 1 | 2 |" in text and (out / "arena_table.md").exists() and (out / "arena_scenarios.csv").exists()
    assert (out / "plots" / "arena_2x1_0.png").stat().st_size > 10_000
    assert main(["train", "--algo", "nav_ppo", "--scenario", "arena", "--max-minutes", "0", "--out", str(tmp_path / "x")]) != 0
    assert "bad max_minutes 0.0" in capsys.readouterr().err
    assert main(["evaluate", str(tmp_path / "long" / "checkpoint")]) != 0
    assert "is an arena policy; evaluate it with: python -m coin_app evaluate-arena" in capsys.readouterr().err
